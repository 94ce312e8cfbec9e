"""Admission control (issue 15): a study's cap on active participants refuses new joins clearly, never slowly."""

from __future__ import annotations

import threading
from datetime import timedelta

import pytest
from pydantic import ValidationError
from sqlalchemy import func, select

from experiment.config import RecruitmentConfig
from experiment.flow import QuestionnaireStep
from experiment.instruments import SCHAEFER_14
from server.models import Event, Participant, utcnow
from server.services.sessions import STUDY_FULL_REASON, STUDY_FULL_RETRY_AFTER_S, participant_by_token
from server.sweeper import sweep
from tests.server.factories import auth, browser_key, fast_config, join, make_client, make_study


def capped(cap: int | None):
    return fast_config(recruitment=RecruitmentConfig(max_active_participants=cap))


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=capped(2))
    return client, admin


def refused(response) -> None:
    """The answer to a join past the cap: 503, Retry-After, a typed body with the participant-facing reason."""
    assert response.status_code == 503, response.text
    assert response.headers["Retry-After"] == str(STUDY_FULL_RETRY_AFTER_S)
    assert response.json() == {"detail": STUDY_FULL_REASON, "code": "study_full", "message": "errors.study_full",
                               "retry_after_s": STUDY_FULL_RETRY_AFTER_S}


def statuses(client) -> list[str]:
    with client.app.state.services.sessionmaker() as session:
        return sorted(session.scalars(select(Participant.status)))


def refusal_events(client) -> list[dict]:
    with client.app.state.services.sessionmaker() as session:
        events = session.scalars(select(Event).where(Event.kind == "join_refused").order_by(Event.id))
        return [event.payload for event in events]


@pytest.mark.parametrize("cap", [0, -1, 2.5, "many"])
def test_the_cap_is_a_positive_whole_number_or_none(cap):
    assert RecruitmentConfig().max_active_participants is None  # the default: no cap
    with pytest.raises(ValidationError, match="max_active_participants"):
        RecruitmentConfig(max_active_participants=cap)


def test_the_cap_is_validated_and_stored_with_the_version(api):
    client, admin = api
    document = capped(None).model_dump(mode="json")
    document["recruitment"]["max_active_participants"] = 0
    response = client.put("/api/admin/studies/s1/config", json={"config": document}, headers=auth(admin))
    assert response.status_code == 422 and "recruitment.max_active_participants" in response.json()["detail"]
    study = client.get("/api/admin/studies/s1", headers=auth(admin)).json()
    assert study["config"]["recruitment"] == {"max_active_participants": 2}
    assert study["max_active_participants"] == 2 and study["refused_joins"] == 0
    join(client, PROLIFIC_PID="a")  # freezes version 1: a new cap is a new version, and joins go by the newest
    document["recruitment"]["max_active_participants"] = 1
    assert client.put("/api/admin/studies/s1/config", json={"config": document}, headers=auth(admin)).status_code == 200
    study = client.get("/api/admin/studies/s1", headers=auth(admin)).json()
    assert study["version"] == 2 and study["max_active_participants"] == 1
    refused(client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "b"}))


def test_joins_past_the_cap_are_refused_and_returning_participants_are_not(api):
    client, admin = api
    first = join(client, PROLIFIC_PID="a")
    join(client, PROLIFIC_PID="b")
    refused(client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "c"}))
    refused(client.post("/api/studies/s1/join"))  # without an external id too
    again = client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "a"},  # a reload of the join link
                        json={"resume_key": browser_key(client)})
    assert again.status_code == 200 and again.json()["token"] == first["token"] and not again.json()["created"]
    assert client.get(f"/api/p/{first['token']}/state").status_code == 200
    assert statuses(client) == ["active", "active"]  # a refused join writes no participant ...
    assert refusal_events(client) == [{"reason": "study_full", "active": 2, "cap": 2}] * 2  # ... only its event
    listed = client.get("/api/admin/studies", headers=auth(admin)).json()[0]
    assert listed["max_active_participants"] == 2 and listed["refused_joins"] == 2
    events = client.get("/api/admin/studies/s1/export/events.csv", headers=auth(admin)).text.splitlines()
    assert sum(line.startswith(",join_refused,") for line in events) == 2  # exported, with no participant
    client.post("/api/admin/studies/s1/close", headers=auth(admin))  # closed and full: new joins hear "closed"
    assert client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "d"}).status_code == 410
    assert join(client, PROLIFIC_PID="b")["created"] is False
    join_doc = client.get("/openapi.json").json()["paths"]["/api/studies/{slug}/join"]["post"]["responses"]
    assert "503" in join_doc


def finish(client, token: str):
    """Complete a session through the API: straight to the last questionnaire, then answer it."""
    with client.app.state.services.sessionmaker.begin() as session:
        participant = participant_by_token(session, token)
        participant.block_order = [block.name for block in capped(None).blocks]
        participant.step = QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id)
    body = {"questionnaire": SCHAEFER_14.id, "answers": {item.id: 50 for item in SCHAEFER_14.items}}
    response = client.post(f"/api/p/{token}/answers", json=body)
    assert response.status_code == 200 and response.json()["phase"] == "debrief", response.text
    return response


def test_an_ended_session_frees_its_place(api):
    client, admin = api
    tokens = {pid: join(client, PROLIFIC_PID=pid)["token"] for pid in ("a", "b")}
    ends = {  # each way a session ends, then the next newcomer gets its place and the one after is refused
        "c": lambda: finish(client, tokens["a"]),
        "d": lambda: client.post(f"/api/p/{tokens['b']}/consent", json={"agree": False}),
        "e": lambda: client.post(f"/api/admin/studies/s1/participants/{public_id('c')}/withdraw",
                                 json={"reason": "asked by email"}, headers=auth(admin)),
    }

    def public_id(external_id: str) -> str:
        return next(p["public_id"] for p in client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()
                    if p["external_id"] == external_id)

    for newcomer, end in ends.items():
        refused(client.post("/api/studies/s1/join", params={"PROLIFIC_PID": newcomer}))
        ended = end()
        assert ended.status_code == 200, ended.text
        tokens[newcomer] = join(client, PROLIFIC_PID=newcomer)["token"]
    assert statuses(client) == ["active", "active", "completed", "declined", "withdrawn"]
    refused(client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "f"}))
    app = client.app  # both active sessions go idle past the timeout: abandoned, and two places free
    assert sweep(app.state.services.sessionmaker, app.state.services.runtimes, app.state.services.hub,
                 now=utcnow() + timedelta(hours=2)) == 2
    join(client, PROLIFIC_PID="f")
    join(client, PROLIFIC_PID="g")
    refused(client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "h"}))
    assert len(refusal_events(client)) == 5


def at_once(client, external_ids: list[str]) -> list:
    """One join per id, all sent at the same moment from their own threads; the answers."""
    ready = threading.Barrier(len(external_ids))
    answers: list = []
    key = browser_key(client)  # one browser, as the join page: its resume key, made before the first join

    def one(external_id: str) -> None:
        ready.wait()
        answers.append(client.post("/api/studies/s1/join", params={"PROLIFIC_PID": external_id},
                                   json={"resume_key": key}))

    with client:  # one event loop for every thread's request (PostgreSQL units run concurrently in worker threads)
        threads = [threading.Thread(target=one, args=(external_id,)) for external_id in external_ids]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    return answers


def test_simultaneous_joins_never_take_more_places_than_the_cap(database_url):
    cap, joiners = 3, 10
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=capped(cap))
    answers = at_once(client, [f"x{i}" for i in range(joiners)])
    assert sorted(a.status_code for a in answers) == [200] * cap + [503] * (joiners - cap)
    assert statuses(client) == ["active"] * cap and len(refusal_events(client)) == joiners - cap
    with client.app.state.services.sessionmaker() as session:
        assert session.scalar(select(func.count()).select_from(Participant)) == cap


def test_one_person_joining_twice_at_once_for_the_last_place_gets_it_both_times(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=capped(1))
    answers = at_once(client, ["same"] * 4)  # e.g. a double click, or two tabs of the join link
    assert [a.status_code for a in answers] == [200] * 4 and len({a.json()["token"] for a in answers}) == 1
    assert statuses(client) == ["active"] and refusal_events(client) == []


def test_bots_count_a_refused_join_as_a_refusal_not_an_error(api):
    """Load runs with admission control (``bench_load.py --cap``): a bot told the study is full records a refusal."""
    from contextlib import nullcontext

    from experiment.iohmm import paper_params
    from server.harness.crowd import run_bots

    client, _ = api
    join(client, PROLIFIC_PID="a")
    join(client, PROLIFIC_PID="b")  # the two places are taken
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(), participants=2)
    assert summary.refused == 2 and summary.completed == 0 and summary.errors == []
    assert summary.to_dict()["refused"] == 2
