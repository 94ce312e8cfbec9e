"""What a participant session's 3D view should show: the trial its step runs, and that trial's stage.

The decision (``step_scene``, ``Targets.target``) takes plain rows: the participant (its status, step, study
version, block order), its open trial and its study's runtime. ``Targets.read`` is the database side: the
participants and their open trials of every watched session at once (two queries, read only), in the unit of
work the viewer manager runs on the event loop (``server.db.units.Database.run``). Nothing here writes to the database
or applies transitions; requests and the sweeper do that. Starting the playback of an attempt under way is the
manager's own step, after the read (``Reading.attempts``).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session, defer

from experiment.engine import StudyRuntime
from experiment.flow import ParticipantStatus, TrialRef, TrialStage
from experiment.task import Complexity
from experiment.world import Scene
from experiment.world.trial import trial_scene
from server.models import Participant, Trial
from server.services import sessions, trials
from server.services.studies import RuntimeCache

log = logging.getLogger("trustlab.viewer")

#: What the scene shows before the participant reaches the first trial.
LOBBY_SCENE = ("low", 0)
#: How many sessions' steps ``Targets`` remembers the scene of before it starts again.
REMEMBERED_STEPS = 4096

#: The open trials' rows, as ``Targets.read`` keys them: by (participant id, which of their trials).
OpenTrials = Mapping[tuple[int, TrialRef], Trial]


@dataclass(frozen=True)
class Target:
    """What a session's scene should show, as read from the database."""

    active: bool
    scene: Scene | None = None  # None: keep the current trial's scene (questionnaires and the like)
    stage: TrialStage | None = None  # the open trial's stage (decision, attempt, teleop...), or None between trials


@dataclass(frozen=True)
class AttemptUnderWay:
    """A trial whose autonomous attempt is under way in the database: the hub should be playing it back."""

    participant: Participant
    trial: Trial
    scene_seed: object  # the scene's seed (Scene.seed): the hub's world of this trial has the same


@dataclass
class Reading:
    """What ``Targets.read`` found: every listed session's target, and the attempts under way among them."""

    targets: dict[int, Target]
    attempts: list[AttemptUnderWay] = field(default_factory=list)


_scene = functools.lru_cache(maxsize=512)(trial_scene)  # a trial's scene, as the hub builds it


def step_scene(participant: Participant, trial: Trial | None, runtime: StudyRuntime) -> Scene | None:
    """The scene of the trial the participant's step runs: its row's once it has started, else the planned one if
    it is known. None before the first scored trial: its block is drawn when it starts."""
    ref = participant.step.trial_ref
    assert ref is not None
    seed = runtime.config.seed
    if trial is not None:
        return _scene(seed, participant.public_id, trial.block_name, trial.trial, trial.complexity)
    if ref.practice or participant.block_order:
        planned = trials.planned_trial(participant, runtime)
        return _scene(seed, participant.public_id, planned.block_name, planned.trial,
                      Complexity(planned.complexity).value)
    return None


class Targets:
    """What sessions' views should show. Remembers the scene of each session's step, so that a poll looks up the
    study's runtime (a query) and plans only when a session's step changes."""

    def __init__(self, remembered: int = REMEMBERED_STEPS):
        self._remembered = remembered
        self._scenes: dict[tuple, Scene] = {}  # (participant, version, step, has order) -> its trial's scene

    def target(self, participant: Participant, open_trials: OpenTrials,
               runtime: Callable[[], StudyRuntime]) -> Target:
        """The trial a participant's scene should show (the current one, else the next one if it is known) and its
        stage; an active session between trials keeps its scene, an inactive one shows nothing."""
        if participant.status != ParticipantStatus.ACTIVE:
            return Target(False)
        ref = participant.step.trial_ref
        if ref is None:
            return Target(True)
        trial = open_trials.get((participant.id, ref))
        memo = (participant.id, participant.study_version_id, ref, participant.block_order is not None)
        scene = self._scenes.get(memo)
        if scene is None:
            scene = step_scene(participant, trial, runtime())
            if scene is None:
                return Target(True)
            if len(self._scenes) > self._remembered:
                self._scenes.clear()
            self._scenes[memo] = scene
        return Target(True, scene, trial.stage if trial is not None else None)

    def read(self, session: Session, participant_ids: list[int], runtimes: RuntimeCache) -> Reading:
        """Every listed session's target (``Target(False)`` for one that is gone) and the attempts under way."""
        participants, open_trials = read_sessions(session, participant_ids)
        reading = Reading({pid: Target(False) for pid in participant_ids})
        for participant in participants:
            try:
                target = self.target(participant, open_trials,
                                     functools.partial(sessions.runtime_of, session, runtimes, participant))
            except Exception:  # an unexpected step: keep showing what is shown
                log.exception("cannot tell what participant %s's viewer should show", participant.public_id)
                target = Target(True)
            reading.targets[participant.id] = target
            if target.stage == TrialStage.ATTEMPT and target.scene is not None:
                ref = participant.step.trial_ref
                assert ref is not None
                reading.attempts.append(AttemptUnderWay(participant, open_trials[(participant.id, ref)],
                                                        target.scene.seed))
        return reading


#: Participant columns the view never reads (deferred: loaded only if something asks, in the same unit).
_NOT_FOR_THE_VIEW = (Participant.beliefs, Participant.recruitment, Participant.assignment, Participant.survey_draft,
                     Participant.exclusion_reason)


# Built once (building the deferred-column options alone took tens of milliseconds per poll under load).
_PARTICIPANTS = (select(Participant).where(Participant.id.in_(bindparam("ids", expanding=True)))
                 .options(*(defer(column) for column in _NOT_FOR_THE_VIEW)))
_OPEN_TRIALS = select(Trial).where(Trial.participant_id.in_(bindparam("ids", expanding=True)),
                                   Trial.stage != TrialStage.DONE)


def read_sessions(session: Session, participant_ids: list[int]) -> tuple[Sequence[Participant], OpenTrials]:
    """The listed participants and their open trials (``OpenTrials``): two queries for all of them, read only."""
    # Without the columns no view needs (the belief history grows with every trial): the poll reads every watched
    # session, on the event loop.
    participants = session.scalars(_PARTICIPANTS, {"ids": participant_ids}).all()
    open_trials = session.scalars(_OPEN_TRIALS, {"ids": participant_ids}).all()
    return participants, {(t.participant_id, t.ref): t for t in open_trials}
