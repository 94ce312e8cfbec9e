"""server.services.trials without HTTP: starting a trial and the time-based transitions ``advance`` applies
from the deadlines stored in the row (scene wait, decision window, autonomous attempt, teleoperation limit)."""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import func, select

from experiment.flow import TrialRef, TrialStage, WindowOpener
from server.errors import Conflict
from server.models import Trial, utcnow
from server.services import trials
from server.services.studies import RuntimeCache
from server.world.attempts import AttemptInfo
from tests.server.factories import at_practice, memory_session, open_study, tiny_study

ATTEMPT_S = 3.0


class FakePlanner:
    """An AttemptPlanner whose attempt takes ``ATTEMPT_S`` and succeeds; it notes what it was asked."""

    def __init__(self) -> None:
        self.attempts: list[float] = []
        self.teleops_over: list[tuple[str, bool, int, int]] = []

    def attempt(self, study_seed, participant_key, planned, success, *, started_ago_s, speed):
        self.attempts.append(started_ago_s)
        return AttemptInfo(duration_s=ATTEMPT_S, failure_mode=None)

    def teleop_over(self, participant_key, ref):
        self.teleops_over.append((participant_key, *ref))

    def prepare_attempt(self, study_seed, participant_key, planned, success):
        pass


@pytest.fixture
def practice():
    """A session at its one practice trial (the robot tries by itself) of a study whose robot runs at speed 1."""
    with memory_session() as session:
        study = open_study(session, config=tiny_study("unit", hint="rely", n_high=1, animation_speed=1.0))
        participant, runtime = at_practice(session, study, RuntimeCache())
        yield session, study, participant, runtime


def start(practice, now):
    session, study, participant, runtime = practice
    return trials.start_trial(session, study, participant, runtime, TrialRef(True, 0, 1), now=now)


def test_only_the_current_trial_starts_and_starting_it_again_returns_the_same_row(practice):
    session, study, participant, runtime = practice
    now = utcnow()
    with pytest.raises(Conflict, match="cannot start trial 1 of block 1: the session is at practice index=0"):
        trials.start_trial(session, study, participant, runtime, TrialRef(False, 1, 1), now=now)
    row = start(practice, now)
    assert start(practice, now + timedelta(seconds=5)) is row and row.started_at == now
    assert row.stage == TrialStage.PRESENTING
    assert row.scene_deadline_at == now + timedelta(seconds=runtime.config.timing.scene_wait_s)
    assert session.scalar(select(func.count()).select_from(Trial)) == 1


def test_advance_opens_the_window_at_the_scene_wait_limit_and_not_before(practice):
    session, _, participant, runtime = practice
    row, planner = start(practice, utcnow()), FakePlanner()
    deadline = row.scene_deadline_at

    trials.advance(session, participant, runtime, now=deadline - timedelta(milliseconds=1), planner=planner)
    assert row.stage == TrialStage.PRESENTING and row.window_opened_at is None
    trials.advance(session, participant, runtime, now=deadline + timedelta(seconds=0.05), planner=planner)
    assert row.stage == TrialStage.DECISION and row.window_opened_by == WindowOpener.WAIT_LIMIT
    assert row.window_opened_at == deadline  # from the stored deadline, not from when advance ran
    assert row.decision_deadline_at == deadline + timedelta(seconds=runtime.config.timing.decision_window_s)


def test_advance_applies_a_due_decision_window_timeout_then_ends_the_attempt(practice):
    session, _, participant, runtime = practice
    planner = FakePlanner()
    row = trials.scene_shown(session, participant, runtime, start(practice, utcnow()), view="text", now=utcnow(),
                             planner=planner)
    closed = row.decision_deadline_at

    late = closed + timedelta(seconds=1)
    assert trials.advance(session, participant, runtime, now=late, planner=planner) is row
    assert (row.stage, row.human_action, row.decided_at) == (TrialStage.ATTEMPT, "rely", closed)
    assert planner.attempts == [pytest.approx(1.0)]  # played back from the deadline: one second in
    assert row.attempt_end_at == closed + timedelta(seconds=ATTEMPT_S)  # animation speed 1
    with pytest.raises(Conflict, match="the decision window has closed"):
        trials.intervene(session, participant, runtime, row, window_opened_ms=None, pressed_ms=None, now=late,
                         planner=planner)

    trials.advance(session, participant, runtime, now=row.attempt_end_at, planner=planner)
    assert row.stage == TrialStage.DONE and row.outcome is not None and participant.step.phase != "practice"


def test_a_teleoperation_past_its_limit_is_retried_while_guided_then_fails(practice):
    session, _, participant, runtime = practice
    planner, now = FakePlanner(), utcnow()
    row = trials.scene_shown(session, participant, runtime, start(practice, now), view="text", now=now,
                             planner=planner)
    trials.intervene(session, participant, runtime, row, window_opened_ms=0.0, pressed_ms=120.0, now=now,
                     planner=planner)
    assert row.stage == TrialStage.TELEOP and row.tutorial and row.decision_time_ms == 120.0
    tutorial = runtime.config.practice.tutorial

    for tries in range(1, tutorial.max_tries):
        trials.advance(session, participant, runtime, now=row.teleop_deadline_at, planner=planner)
        assert (row.stage, row.teleop_tries) == (TrialStage.TELEOP, tries + 1)
    trials.advance(session, participant, runtime, now=row.teleop_deadline_at, planner=planner)
    assert row.stage == TrialStage.DONE and row.teleop_success is False
    assert row.teleop_time_ms == tutorial.time_limit_s * 1000
    assert planner.teleops_over == [(participant.public_id, True, 0, 1)] * tutorial.max_tries
