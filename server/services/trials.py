"""The trial engine on the server: start, decide, attempt, teleoperate, complete.

A trial row is created when the trial starts and completed when it resolves,
in the same transaction that moves the participant on. When the robot tries
by itself, the trial is first "presenting": its decision window opens when
the page reports the trial's scene on screen (``scene_shown``), or after
``timing.scene_wait_s`` without a report. Time-based transitions (the scene
wait running out, the decision window closing, the autonomous attempt ending,
the teleoperation time limit) are applied by ``advance`` whenever the
session is touched and by the server's sweeper, always from the deadlines
stored in the row, so a restart changes nothing.
"""

from __future__ import annotations

import math
from collections import Counter
from datetime import datetime, timedelta
from typing import Protocol

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig
from experiment.engine import PlannedTrial, StudyRuntime
from experiment.events import EventKind
from experiment.flow import ParticipantStatus, PracticeStep, SceneView, TrialRef, TrialStage, WindowOpener
from experiment.policies import PolicyKind
from experiment.schedule import assign_block_order, derive_rng
from experiment.simulate import order_names
from experiment.task import HumanAction, Outcome, RobotAction, resolve_trial
from experiment.trust_belief import p_highest
from server.errors import Conflict, Invalid
from server.i18n import N_
from server.models import Participant, Study, Trial
from server.services.audit import log_event
from server.services.sessions import advance_step, describe, lock_study, require_active
from server.world.attempts import AttemptInfo

PRACTICE_BLOCK = "practice"
#: Longest plausible client-side decision time (a larger value is a client clock error).
MAX_DECISION_MS = 600_000.0


class AttemptPlanner(Protocol):
    """Plans (and shows) the autonomous attempt of a trial; the server's robot world implements it."""

    def attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool, *,
                started_ago_s: float, speed: float) -> AttemptInfo: ...

    def teleop_over(self, participant_key: str, ref: TrialRef) -> None:
        """The trial's teleoperation ended without a deposit (its time limit passed)."""

    def prepare_attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> None:
        """Plan the attempt ahead of time (optional: ``attempt`` plans it if this was not called)."""


def current_trial(session: Session, participant: Participant) -> Trial | None:
    """The row of the trial the participant's step points at, if it has started."""
    ref = participant.step.trial_ref
    if ref is None:
        return None
    return find_trial(session, participant, ref)


_FIND_TRIAL = select(Trial).where(Trial.participant_id == bindparam("participant_id"),
                                  Trial.practice == bindparam("practice"), Trial.block == bindparam("block"),
                                  Trial.trial == bindparam("trial"))


def find_trial(session: Session, participant: Participant, ref: TrialRef) -> Trial | None:
    """The trial's row; a row found (or started) once is remembered for the rest of the transaction (trial rows
    are never deleted), so a request that looks at it several times reads it once."""
    if (row := _found_trials(session).get((participant.id, ref))) is not None:
        return row
    row = session.scalar(_FIND_TRIAL, {"participant_id": participant.id, "practice": ref.practice, "block": ref.block,
                                       "trial": ref.trial})
    if row is not None:
        _remember_trial(session, row)
    return row


def _found_trials(session: Session) -> dict[tuple[int, TrialRef], Trial]:
    return session.info.setdefault("trials", {})


def _remember_trial(session: Session, row: Trial) -> None:
    _found_trials(session)[(row.participant_id, row.ref)] = row


def planned_trial(participant: Participant, runtime: StudyRuntime) -> PlannedTrial:
    """The plan of the trial the participant's step runs."""
    step, ref = participant.step, participant.step.trial_ref
    assert ref is not None
    if isinstance(step, PracticeStep):
        spec = runtime.config.practice.trials[step.index]
        return PlannedTrial(0, PRACTICE_BLOCK, ref.trial, ref.trial, 1, False, spec.complexity)
    assert participant.block_order is not None
    plan = runtime.plan(participant.public_id, participant.block_order)
    return next(t for t in plan if (t.block, t.trial) == (ref.block, ref.trial))


def start_trial(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, ref: TrialRef, *,
                now: datetime) -> Trial:
    """Start the trial the session is at; starting it again returns the same row."""
    require_active(participant)
    step = participant.step
    if ref != step.trial_ref:
        raise Conflict(f"cannot start {ref.describe()}: the session is at {describe(step)}", step=step)
    existing = current_trial(session, participant)
    if existing is not None:
        return existing
    if not ref.practice and participant.block_order is None:
        _assign_block_order(session, study, participant, runtime, now=now)
    planned = planned_trial(participant, runtime)
    if ref.practice:
        assert isinstance(step, PracticeStep)
        robot_action, policy_belief = runtime.config.practice.trials[step.index].robot_action, None
        policy = PolicyKind.PRACTICE
    else:
        acted_on = runtime.policy_belief(participant.beliefs, planned.block_name)
        robot_action = runtime.robot_action(participant.public_id, planned, acted_on)
        policy_belief = p_highest(acted_on)
        policy = runtime.policies[planned.block_name].kind
        participant.started_at = participant.started_at or now
    provenance = runtime.provenance(planned.block_name, ref.practice)
    row = Trial(participant_id=participant.id, study_version_id=participant.study_version_id, practice=ref.practice,
                block=planned.block, block_name=planned.block_name, policy=policy, trial=planned.trial,
                trial_overall=planned.trial_overall, shelf=planned.shelf, complexity=planned.complexity,
                robot_action=robot_action, belief_before=p_highest(participant.beliefs[""]),
                policy_belief=policy_belief, started_at=now, model_hash=provenance.model_hash,
                policy_hash=provenance.policy_hash, seed=provenance.seed)
    timing = runtime.config.timing
    if robot_action == RobotAction.AUTO:  # the decision window opens once the page shows the scene (scene_shown)
        row.stage, row.scene_deadline_at = TrialStage.PRESENTING, now + timedelta(seconds=timing.scene_wait_s)
    else:
        row.stage, row.human_action = TrialStage.TELEOP, HumanAction.INTERVENE
    session.add(row)
    session.flush()
    _remember_trial(session, row)
    if robot_action == RobotAction.ASK:
        _enter_teleop(session, participant, runtime, row, now=now)
    log_event(session, participant.study_id, participant.id, EventKind.TRIAL_STARTED, **ref._asdict(),
              complexity=row.complexity, robot_action=row.robot_action)
    return row


def _assign_block_order(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, *,
                        now: datetime) -> None:
    """Counterbalance at the first scored trial by counts of started, not abandoned participants (previews are not
    counted: trying the study must not change what real participants get)."""
    lock_study(session, study)
    orders = order_names(runtime.config)
    # Counted in Python: JSON columns have no equality operator to GROUP BY on PostgreSQL.
    started = session.scalars(select(Participant.block_order).where(
        Participant.study_id == study.id, Participant.block_order.is_not(None), Participant.preview.is_(False),
        Participant.status.in_((ParticipantStatus.ACTIVE, ParticipantStatus.COMPLETED))))
    counts = Counter(tuple(order) for order in started if order is not None)
    rng = derive_rng(runtime.config.seed, participant.public_id, "assignment")
    assignment = assign_block_order(orders, {o: counts.get(o, 0) for o in orders}, rng)
    participant.block_order = list(assignment.order)
    participant.assignment = {"method": assignment.method,
                              "counts_before": [[list(o), n] for o, n in assignment.counts_before],
                              "tied_orders": [list(o) for o in assignment.tied_orders], "at": now.isoformat(),
                              "audit": assignment.audit_line()}
    log_event(session, study.id, participant.id, EventKind.BLOCK_ORDER_ASSIGNED, order=list(assignment.order))


def scene_shown(session: Session, participant: Participant, runtime: StudyRuntime, trial: Trial, *, view: SceneView,
                now: datetime, planner: AttemptPlanner, client_time_ms: float | None = None) -> Trial:
    """The page reports the trial's scene on screen (proven: ``server.routes.participant.scene_shown``): the
    decision window opens now, unless it is open already (a repeated report changes nothing; the first report's
    time, view and client time are kept even when it came too late)."""
    require_active(participant)
    advance(session, participant, runtime, now=now, planner=planner)
    if trial.scene_shown_at is None:
        trial.scene_shown_at, trial.scene_shown_view, trial.scene_shown_client_ms = now, view, client_time_ms
        log_event(session, participant.study_id, participant.id, EventKind.SCENE_SHOWN, practice=trial.practice,
                  block=trial.block, trial=trial.trial, view=view, stage=trial.stage)
    if trial.stage == TrialStage.PRESENTING:
        _open_window(session, participant, runtime, trial, at=now, by=WindowOpener(view))
    return trial


def _open_window(session: Session, participant: Participant, runtime: StudyRuntime, trial: Trial, *, at: datetime,
                 by: WindowOpener) -> None:
    """Open the decision window at ``at``: by the page's report (``by`` = its view) or by the wait limit."""
    trial.stage, trial.window_opened_at, trial.window_opened_by = TrialStage.DECISION, at, by
    trial.decision_deadline_at = at + timedelta(seconds=runtime.config.timing.decision_window_s)
    log_event(session, participant.study_id, participant.id, EventKind.DECISION_WINDOW_OPENED, practice=trial.practice,
              block=trial.block, trial=trial.trial, by=by)


def intervene(session: Session, participant: Participant, runtime: StudyRuntime, trial: Trial, *,
              window_opened_ms: float | None, pressed_ms: float | None, now: datetime,
              planner: AttemptPlanner) -> Trial:
    """The participant pressed Intervene during the decision window."""
    require_active(participant)
    advance(session, participant, runtime, now=now, planner=planner)
    if trial.stage != TrialStage.DECISION:
        closed = trial.human_action == HumanAction.RELY
        reason = ("the decision window has closed" if closed
                  else "the decision window has not opened yet (the trial's scene is not shown)"
                  if trial.stage == TrialStage.PRESENTING
                  else f"this trial is not waiting for a decision (stage {trial.stage})")
        raise Conflict(f"{reason}; the session is at {describe(participant.step)}", step=participant.step,
                       message=N_("errors.window_closed") if closed else Conflict.message)
    trial.human_action, trial.decided_at = HumanAction.INTERVENE, now
    trial.decision_time_ms = _decision_ms(window_opened_ms, pressed_ms)
    _enter_teleop(session, participant, runtime, trial, now=now)
    log_event(session, participant.study_id, participant.id, EventKind.INTERVENE, client_time_ms=pressed_ms,
              block=trial.block, trial=trial.trial, window_opened_ms=window_opened_ms)
    return trial


_PRACTICE_DEPOSITS = select(Trial.id).where(Trial.participant_id == bindparam("participant_id"), Trial.practice,
                                            Trial.teleop_success.is_(True)).limit(1)


def _enter_teleop(session: Session, participant: Participant, runtime: StudyRuntime, trial: Trial, *,
                  now: datetime) -> None:
    """The participant takes the arm: record the rules it runs under, and whether it is the guided practice
    (every practice teleoperation until the participant's first deposit, when the study has the tutorial on)."""
    config = runtime.config
    trial.stage, trial.teleop_tries = TrialStage.TELEOP, 1
    trial.grasp_radius_m, trial.align_radius_m = config.teleop.grasp_radius_m, config.teleop.align_radius_m
    trial.tutorial = bool(trial.practice and config.practice.tutorial.enabled
                          and session.scalar(_PRACTICE_DEPOSITS, {"participant_id": participant.id}) is None)
    trial.teleop_deadline_at = now + timedelta(seconds=teleop_time_limit_s(config, trial))


def teleop_time_limit_s(config: StudyConfig, trial: Trial) -> float:
    """The time limit of one try of the trial's teleoperation."""
    return config.practice.tutorial.time_limit_s if trial.tutorial else config.timing.teleop_time_limit_s


def _decision_ms(opened: float | None, pressed: float | None) -> float | None:
    if opened is None or pressed is None:
        return None
    if not (math.isfinite(opened) and math.isfinite(pressed)) or not 0 <= pressed - opened <= MAX_DECISION_MS:
        raise Invalid("window_opened_ms and pressed_ms must be client times with 0 <= pressed - opened <= 600000")
    return pressed - opened


def advance(session: Session, participant: Participant, runtime: StudyRuntime, *, now: datetime,
            planner: AttemptPlanner) -> Trial | None:
    """Apply every transition whose deadline has passed; returns the current trial row."""
    trial = current_trial(session, participant)
    if trial is None or participant.status != ParticipantStatus.ACTIVE:
        return trial
    if trial.stage == TrialStage.PRESENTING and now >= _aware(trial.scene_deadline_at):
        _open_window(session, participant, runtime, trial, at=_aware(trial.scene_deadline_at),
                     by=WindowOpener.WAIT_LIMIT)
    if trial.stage == TrialStage.DECISION and now >= _aware(trial.decision_deadline_at):
        _rely(trial, participant, runtime, planner, now=now)
    if trial.stage == TrialStage.ATTEMPT and now >= _aware(trial.attempt_end_at):
        complete(session, participant, runtime, trial, now=now)
    elif trial.stage == TrialStage.TELEOP and now >= _aware(trial.teleop_deadline_at):
        limit_s = teleop_time_limit_s(runtime.config, trial)
        tries = trial.teleop_tries or 1
        log_event(session, participant.study_id, participant.id, EventKind.TELEOP_TIMEOUT, practice=trial.practice,
                  block=trial.block, trial=trial.trial, try_number=tries)
        planner.teleop_over(participant.public_id, trial.ref)
        if trial.tutorial and tries < runtime.config.practice.tutorial.max_tries:
            # The guided practice starts over from the ready pose, counted from the missed deadline.
            trial.teleop_tries = tries + 1
            trial.teleop_deadline_at = _aware(trial.teleop_deadline_at) + timedelta(seconds=limit_s)
            log_event(session, participant.study_id, participant.id, EventKind.TELEOP_RETRY, practice=True,
                      block=trial.block, trial=trial.trial, try_number=tries + 1)
            return advance(session, participant, runtime, now=now, planner=planner)
        complete(session, participant, runtime, trial, now=now, teleop_success=False, teleop_time_ms=limit_s * 1000)
    return trial


def _aware(value: datetime | None) -> datetime:
    assert value is not None
    return value


def _rely(trial: Trial, participant: Participant, runtime: StudyRuntime, planner: AttemptPlanner, *,
          now: datetime) -> None:
    """The window closed without an intervention: the robot attempts, from the deadline on."""
    deadline = _aware(trial.decision_deadline_at)
    trial.human_action, trial.stage, trial.decided_at = HumanAction.RELY, TrialStage.ATTEMPT, deadline
    info = play_attempt(trial, participant, runtime, planner, now=now)
    trial.failure_mode = info.failure_mode
    trial.attempt_end_at = deadline + timedelta(seconds=info.duration_s / runtime.config.timing.animation_speed)


def play_attempt(trial: Trial, participant: Participant, runtime: StudyRuntime, planner: AttemptPlanner, *,
                 now: datetime) -> AttemptInfo:
    """Play the trial's autonomous attempt back as from its start (``decided_at``), where it is at ``now``.

    Also for a process that did not start the attempt (after a restart, or another worker of a group): the
    attempt is deterministic, so it shows the same arm at the same moment.
    """
    planned = _planned_of(trial)
    return planner.attempt(runtime.config.seed, participant.public_id, planned,
                           autonomous_success(runtime, participant, planned),
                           started_ago_s=(now - _aware(trial.decided_at)).total_seconds(),
                           speed=runtime.config.timing.animation_speed)


def _planned_of(trial: Trial) -> PlannedTrial:
    return PlannedTrial(trial.block, trial.block_name, trial.trial, trial.trial_overall, trial.shelf, False,
                        trial.complexity)


def autonomous_success(runtime: StudyRuntime, participant: Participant, planned: PlannedTrial) -> bool:
    return runtime.autonomous_success(participant.public_id, planned)


def finish_teleop(session: Session, participant: Participant, runtime: StudyRuntime, trial: Trial, *, success: bool,
                  teleop_time_ms: float, now: datetime) -> None:
    """The world reports the item deposited (or given up): the trial resolves."""
    if trial.stage != TrialStage.TELEOP:
        raise Conflict(f"this trial is not being teleoperated (stage {trial.stage})")
    complete(session, participant, runtime, trial, now=now, teleop_success=success, teleop_time_ms=teleop_time_ms)


def complete(session: Session, participant: Participant, runtime: StudyRuntime, trial: Trial, *, now: datetime,
             teleop_success: bool | None = None, teleop_time_ms: float | None = None) -> None:
    planned = _planned_of(trial)
    assert trial.human_action is not None, "a trial is complete once the participant acted"
    robot_action, human_action = RobotAction(trial.robot_action), HumanAction(trial.human_action)
    if trial.practice:
        result = resolve_trial(planned.complexity, robot_action, human_action,
                               autonomous_success(runtime, participant, planned), runtime.config.task)
        trial.outcome, trial.experience, trial.reward = result.outcome, result.experience, result.reward
        trial.score, trial.belief_after = participant.score, trial.belief_before
    else:
        record = runtime.record(participant.public_id, participant.public_id, planned, robot_action, human_action,
                                belief_before=runtime.belief_of_trial(trial.belief_before, participant.beliefs[""]),
                                score_before=participant.score,
                                policy_belief=trial.policy_belief if trial.policy_belief is not None else math.nan)
        trial.outcome, trial.experience, trial.reward = record.outcome, record.experience, record.reward
        trial.score, trial.belief_after = record.score, record.belief_after
        participant.score = record.score
        participant.beliefs = runtime.updated_beliefs(participant.beliefs, record)
    if trial.outcome != Outcome.FAILURE:
        trial.failure_mode = None
    trial.stage, trial.completed_at = TrialStage.DONE, now
    trial.teleop_success, trial.teleop_time_ms = teleop_success, teleop_time_ms
    log_event(session, participant.study_id, participant.id, EventKind.TRIAL_COMPLETED, practice=trial.practice,
              block=trial.block, trial=trial.trial, outcome=trial.outcome, reward=trial.reward)
    advance_step(session, participant, runtime, now)
