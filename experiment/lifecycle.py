"""A study's lifecycle: draft → open ⇄ closed.

A study is created as a draft (the experimenter tries it in preview sessions); participants can join only while
it is open; closing stops new joins while running sessions go on to their end; a closed study can be reopened.
A study that has been open never goes back to draft: its data were collected under an open study.
"""

from __future__ import annotations

from enum import StrEnum


class StudyStatus(StrEnum):
    DRAFT = "draft"  # being prepared: only preview sessions
    OPEN = "open"  # taking new participants
    CLOSED = "closed"  # no new participants; running sessions finish


#: What a study can be created as: a draft, or open at once (create and open in one step).
INITIAL_STATUSES: tuple[StudyStatus, ...] = (StudyStatus.DRAFT, StudyStatus.OPEN)

#: The changes of status a study can make (setting the status it has is a no-op, not a change).
TRANSITIONS: frozenset[tuple[StudyStatus, StudyStatus]] = frozenset({
    (StudyStatus.DRAFT, StudyStatus.OPEN),
    (StudyStatus.OPEN, StudyStatus.CLOSED),
    (StudyStatus.CLOSED, StudyStatus.OPEN),
})

_WHY_NOT = {
    (StudyStatus.DRAFT, StudyStatus.CLOSED): "a draft study has not opened, so it cannot be closed (open it first)",
    (StudyStatus.OPEN, StudyStatus.DRAFT): "an open study cannot go back to draft: participants may have joined it",
    (StudyStatus.CLOSED, StudyStatus.DRAFT): ("a closed study cannot go back to draft: it has been open to "
                                              "participants (reopen it instead)"),
}


class TransitionError(ValueError):
    """A change of status the lifecycle does not allow; the message says why."""


def transition(current: str, target: str) -> bool:
    """Whether going from ``current`` to ``target`` changes anything (False: already there); raises
    ``TransitionError`` with the reason for a change the lifecycle does not allow."""
    try:
        source, goal = StudyStatus(current), StudyStatus(target)
    except ValueError:
        raise TransitionError(f"unknown study status {target!r}; statuses: "
                              f"{', '.join(s.value for s in StudyStatus)}") from None
    if source == goal:
        return False
    if (source, goal) not in TRANSITIONS:
        raise TransitionError(_WHY_NOT.get((source, goal), f"a {source} study cannot become {goal}"))
    return True
