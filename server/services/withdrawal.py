"""Withdrawal from a study: by the participant ("Withdraw from the study" on every page) or by the researcher.

What happens to the data is the study's choice (``experiment.privacy``, config ``privacy.withdrawal`` of the version
the participant runs under, which their consent text described):

- ``keep``: the session ends as withdrawn (outcome ``withdrawn``: its own code and redirect, config ``completion``),
  marked excluded with the reason "withdrawn" (left out of fits and reports by default); its research data stay and
  its personal fields are erased at once (``erasure.erase_personal``). An event ``withdrawn`` says who withdrew.
- ``delete``: the same end, then every row of the participant is deleted (``erasure.delete_participant``).

The page gets the state it shows next (phase ``withdrawn``, the outcome's code and redirect), built before anything
is deleted. A repeated withdrawal answers the same: from the kept session, or (its data deleted) from the deletion's
audit line, which the session link's keyed hash finds (``deleted_state``; the redirect then has no external id).
"""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from experiment.events import EventKind
from experiment.flow import ParticipantStatus, first_step
from experiment.outcomes import SessionOutcome, redirect_link
from server.models import AuditAction, Participant, Study, StudyVersion
from server.schemas import CompletionRead, StateRead, WithdrawalRead
from server.services import erasure, wording
from server.services.audit import audit, log_event
from server.services.state import build_state
from server.services.studies import RuntimeCache

#: Who withdrew a session.
Withdrawer = Literal["participant", "researcher"]
#: The exclusion reason of a withdrawn session (the experimenter's own words are in the audit log).
WITHDRAWN_REASON = "withdrawn"


def withdraw(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, *, by: Withdrawer,
             reason: str | None, now: datetime) -> tuple[StateRead, bool]:
    """End ``participant``'s session as withdrawn, as the study says (module docstring): (the state the page shows,
    whether the data were deleted). A session withdrawn already is left as it is."""
    if participant.status != ParticipantStatus.WITHDRAWN:
        _end(session, study, participant, runtime, by=by, reason=reason, now=now)
    state = build_state(session, study, participant, runtime, now=now)
    if runtime.config.privacy.withdrawal == "delete":
        erasure.delete_participant(session, study, participant,
                                   by="participant" if by == "participant" else "admin", reason=reason)
        return state, True
    erasure.erase_personal(participant, now)
    return state, False


def _end(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, *, by: Withdrawer,
         reason: str | None, now: datetime) -> None:
    participant.status, participant.finished_at = ParticipantStatus.WITHDRAWN, participant.finished_at or now
    participant.excluded, participant.exclusion_reason = True, WITHDRAWN_REASON
    participant.completion_code = runtime.config.completion.code(SessionOutcome.WITHDRAWN)
    log_event(session, participant.study_id, participant.id, EventKind.WITHDRAWN, by=by,
              step=participant.step.model_dump())
    audit(session, AuditAction.PARTICIPANT_WITHDRAW, study_id=study.id, participant=participant.public_id,
          reason=reason, by=by, data=runtime.config.privacy.withdrawal)


def deleted_state(session: Session, runtimes: RuntimeCache, token: str, now: datetime) -> StateRead | None:
    """The end state of a session whose data were deleted (withdrawn by the participant, or by the researcher: a
    withdrawal or the dashboard's deletion); None when the link has no deleted session. The session's step is gone:
    the state carries the first step."""
    deletion = erasure.deleted_session(session, token)
    if deletion is None or deletion.version_id is None or session.get(StudyVersion, deletion.version_id) is None:
        return None
    runtime = runtimes.for_version(session, deletion.version_id)
    config = runtime.config
    outcome = SessionOutcome.WITHDRAWN
    code = config.completion.code(outcome)
    url = redirect_link(config.completion.redirect_template(outcome), outcome=outcome, code=code, external_id=None)
    timing = config.timing
    language = deletion.language or config.default_language
    title = wording.participant_texts(config, language, wording.translator(language)).title  # may be per language
    state = StateRead(
        status=ParticipantStatus.WITHDRAWN, phase=ParticipantStatus.WITHDRAWN, step=first_step(), progress=0.0,
        score=0.0, study_title=title, server_time=now,
        timing={"decision_window_s": timing.decision_window_s, "animation_speed": timing.animation_speed,
                "teleop_time_limit_s": timing.teleop_time_limit_s, "next_item_pause_s": timing.next_item_pause_s},
        teleop_time_limit_s=timing.teleop_time_limit_s,
        completion=CompletionRead(outcome=outcome, code=code, redirect_url=url) if code or url else None,
        withdrawal=WithdrawalRead(data="delete", text=config.privacy.withdrawal_text,
                                  by="participant" if deletion.by == "participant" else "researcher"))
    if deletion.language:
        state.language = deletion.language
    return state
