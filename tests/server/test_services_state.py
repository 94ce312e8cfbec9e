"""server.services.state.build_state without HTTP: what the page is told at each kind of step."""

from __future__ import annotations

from datetime import timedelta

import pytest

from experiment.flow import ParticipantStatus, TrialRef, TrialStage
from server.models import utcnow
from server.services import sessions, trials
from server.services.state import build_state
from server.services.studies import RuntimeCache
from tests.server.factories import at_practice, memory_session, open_study


@pytest.fixture
def session():
    with memory_session() as session:
        yield session


def test_a_fresh_participant_is_asked_for_consent(session):
    study, runtimes, now = open_study(session), RuntimeCache(), utcnow()
    participant, _, _ = sessions.join(session, study, {}, runtimes)
    runtime = sessions.runtime_of(session, runtimes, participant)

    state = build_state(session, study, participant, runtime, now=now)
    config = runtime.config
    assert (state.status, state.phase, state.step.phase) == (ParticipantStatus.ACTIVE, "consent", "consent")
    assert state.text == config.texts.consent and state.study_title == config.texts.title
    assert state.progress == 0 and state.score == 0 and state.server_time == now
    assert state.duration is not None and state.duration.low_minutes <= state.duration.high_minutes
    assert state.trial is state.last_trial is state.completion is state.questionnaire is None
    assert state.timing["decision_window_s"] == config.timing.decision_window_s


def test_a_declined_participant_gets_the_declined_code_and_no_text(session):
    study, runtimes, now = open_study(session), RuntimeCache(), utcnow()
    participant, _, _ = sessions.join(session, study, {}, runtimes)
    runtime = sessions.runtime_of(session, runtimes, participant)
    sessions.consent(session, participant, runtime, agree=False, now=now)

    state = build_state(session, study, participant, runtime, now=now)
    assert state.phase == "declined" and state.text is None and state.duration is None
    assert state.completion is not None and state.completion.code == runtime.config.completion.code_declined


def test_an_ended_session_shows_why_it_ended_as_its_phase(session):
    study, runtimes = open_study(session), RuntimeCache()
    participant, runtime = at_practice(session, study, runtimes)
    sessions.abandon(session, participant, utcnow())

    state = build_state(session, study, participant, runtime, now=utcnow())
    assert (state.status, state.phase, state.step.phase) == (ParticipantStatus.ABANDONED, "abandoned", "practice")


def test_a_trial_is_offered_to_start_then_shown_once_started(session):
    study, runtimes, now = open_study(session), RuntimeCache(), utcnow()
    participant, runtime = at_practice(session, study, runtimes)

    ready = build_state(session, study, participant, runtime, now=now)
    assert ready.phase == "practice" and ready.trial is None
    assert ready.ready_to_start == {"practice": True, "block": 0, "trial": 1}

    trials.start_trial(session, study, participant, runtime, TrialRef(True, 0, 1), now=now)
    later = now + timedelta(seconds=1)
    started = build_state(session, study, participant, runtime, now=later)
    assert started.ready_to_start is None and started.trial is not None
    assert (started.trial.practice, started.trial.block, started.trial.trial) == (True, 0, 1)
    assert started.trial.stage == TrialStage.PRESENTING
    assert started.trial.scene_wait_ms_left == pytest.approx((runtime.config.timing.scene_wait_s - 1) * 1000)
