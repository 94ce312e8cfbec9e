"""server.services.sessions without HTTP: joining, opening a session by its token, consent and answers."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from experiment.flow import ParticipantStatus
from server.errors import Conflict, Gone, NotFound
from server.models import Participant, utcnow
from server.services import sessions
from server.services.studies import RuntimeCache, set_status
from tests.server.factories import memory_session, open_study


@pytest.fixture
def session():
    with memory_session() as session:
        yield session


def test_open_session_finds_the_token_and_refuses_any_other(session):
    study, runtimes = open_study(session), RuntimeCache()
    participant, token, created = sessions.join(session, study, {}, runtimes)
    assert created and len(token) >= 16

    found, found_study, runtime = sessions.open_session(session, runtimes, token)
    assert (found, found_study) == (participant, study) and runtime.config.title == study.title
    for wrong in (token[:-1] + ("A" if token[-1] != "A" else "B"), "", token + "x"):
        with pytest.raises(NotFound, match="unknown session link"):
            sessions.open_session(session, runtimes, wrong)


def test_a_returning_external_id_resumes_its_session(session):
    study, runtimes = open_study(session), RuntimeCache()
    browser = sessions.JoinRequest(resume_key=sessions.new_resume_key())  # the resume key the join page keeps
    first, token, created = sessions.join(session, study, {"PROLIFIC_PID": "abc", "STUDY_ID": "s"}, runtimes, browser)
    again, token_again, created_again = sessions.join(session, study, {"PROLIFIC_PID": "abc"}, runtimes, browser)
    other, other_token, _ = sessions.join(session, study, {"PROLIFIC_PID": "xyz"}, runtimes, browser)

    assert created and not created_again and again.id == first.id and token_again == token
    assert other.id != first.id and other_token != token
    assert first.external_id == "abc" and first.recruitment == {"PROLIFIC_PID": "abc", "STUDY_ID": "s"}
    assert session.scalar(select(func.count()).select_from(Participant)) == 2


def test_a_closed_study_takes_no_new_participants_but_resumes_known_ones(session):
    study, runtimes = open_study(session), RuntimeCache()
    browser = sessions.JoinRequest(resume_key=sessions.new_resume_key())
    known, _, _ = sessions.join(session, study, {"pid": "p1"}, runtimes, browser)
    set_status(session, study, "closed")

    with pytest.raises(Gone, match="closed"):
        sessions.join(session, study, {}, runtimes)
    assert sessions.join(session, study, {"pid": "p1"}, runtimes, browser)[0].id == known.id
    with pytest.raises(Gone, match="closed"):  # the id without its browser's key is someone new
        sessions.join(session, study, {"pid": "p1"}, runtimes)


def test_consent_moves_on_or_ends_the_session_declined(session):
    study, runtimes = open_study(session), RuntimeCache()
    agreeing, _, _ = sessions.join(session, study, {}, runtimes)
    declining, _, _ = sessions.join(session, study, {}, runtimes)
    runtime, now = sessions.runtime_of(session, runtimes, agreeing), utcnow()

    sessions.consent(session, agreeing, runtime, agree=True, now=now)
    assert agreeing.step.phase == "instructions" and agreeing.consented_at == now
    assert agreeing.status == ParticipantStatus.ACTIVE and agreeing.completion_code is None
    with pytest.raises(Conflict, match="this request is for consent"):  # only once
        sessions.consent(session, agreeing, runtime, agree=True, now=now)

    sessions.consent(session, declining, runtime, agree=False, now=now)
    assert declining.status == ParticipantStatus.DECLINED and declining.step.phase == "declined"
    assert declining.completion_code == runtime.config.completion.code_declined and declining.finished_at == now
    with pytest.raises(Conflict, match="already finished"):
        sessions.consent(session, declining, runtime, agree=True, now=now)


def test_answers_for_a_questionnaire_not_asked_now_are_refused(session):
    study, runtimes = open_study(session), RuntimeCache()
    participant, _, _ = sessions.join(session, study, {}, runtimes)
    runtime = sessions.runtime_of(session, runtimes, participant)

    with pytest.raises(Conflict, match="'trust' is not asked now; the session is at consent"):
        sessions.answer(session, participant, runtime, questionnaire_id="trust", answers={"1": 50},
                        now=utcnow())
    assert participant.step.phase == "consent"
