"""A study's lifecycle through the API: created as a draft, opened, closed (running sessions finish), reopened."""

from __future__ import annotations

from contextlib import nullcontext

import pytest

from experiment.iohmm import paper_params
from experiment.lifecycle import TransitionError, transition
from server.errors import Conflict
from server.harness.bots import bot_resume_key
from server.harness.crowd import run_bots
from server.models import AdminAudit
from server.services.studies import create_study, get_study, set_status
from tests.server.factories import auth, fast_config, join, make_client, make_study, memory_session, tiny_study


@pytest.fixture
def client_admin(database_url):
    return make_client(database_url=database_url)


def test_a_new_study_is_a_draft_that_refuses_joins_until_opened(client_admin):
    client, admin = client_admin
    created = client.post("/api/admin/studies", json={"slug": "s1", "template": "demo-fast"}, headers=auth(admin))
    assert created.status_code == 201 and created.json()["status"] == "draft"
    refused = client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "early"})
    assert refused.status_code == 409, refused.text
    assert refused.json()["code"] == "study_not_open" and "has not opened yet" in refused.json()["detail"]
    assert client.get("/api/admin/studies/s1", headers=auth(admin)).json()["participants"] == {}

    opened = client.post("/api/admin/studies/s1/open", headers=auth(admin))
    assert opened.status_code == 200 and opened.json()["status"] == "open"
    assert join(client, "s1", PROLIFIC_PID="early")["created"] is True


def test_create_and_open_in_one_call(client_admin):
    client, admin = client_admin
    study = make_study(client, admin, status="open")
    assert study["status"] == "open" and join(client, "s1")["created"] is True
    closed = client.post("/api/admin/studies", json={"slug": "s2", "template": "demo-fast", "status": "closed"},
                         headers=auth(admin))
    assert closed.status_code == 422 and "status" in closed.text  # a study is created as a draft or open


def test_transitions_are_idempotent_and_forbidden_ones_say_why(client_admin):
    client, admin = client_admin
    make_study(client, admin, status="draft")
    draft_close = client.post("/api/admin/studies/s1/close", headers=auth(admin))
    assert draft_close.status_code == 409 and "a draft study has not opened" in draft_close.json()["detail"]
    for action, status in (("open", "open"), ("open", "open"), ("close", "closed"), ("close", "closed"),
                           ("open", "open")):  # reopening is allowed; repeating one is a no-op
        response = client.post(f"/api/admin/studies/s1/{action}", headers=auth(admin))
        assert response.status_code == 200 and response.json()["status"] == status, response.text
    with client.app.state.services.sessionmaker() as session:
        actions = session.query(AdminAudit.action).filter(AdminAudit.action.like("study.%")).order_by(AdminAudit.id)
        assert [a for (a,) in actions] == ["study.create", "study.open", "study.closed", "study.open"]


def test_the_lifecycle_table():
    assert transition("draft", "open") and transition("open", "closed") and transition("closed", "open")
    assert not transition("open", "open") and not transition("draft", "draft")
    for current, target, reason in (("closed", "draft", "cannot go back to draft"),
                                    ("open", "draft", "cannot go back to draft"),
                                    ("draft", "closed", "has not opened"), ("open", "archived", "unknown")):
        with pytest.raises(TransitionError, match=reason):
            transition(current, target)
    with memory_session() as session:
        study = create_study(session, fast_config(), "s1", status="open")
        set_status(session, study, "closed")
        with pytest.raises(Conflict, match="a closed study cannot go back to draft"):
            set_status(session, study, "draft")
        assert get_study(session, "s1").status == "closed"


def test_closing_stops_new_joins_and_a_running_session_finishes(client_admin):
    client, admin = client_admin
    make_study(client, admin, config=tiny_study("closing", hint="rely", n_high=1, animation_speed=8.0))
    # the external id and resume key (its browser's) the bot below resumes with
    running = join(client, "s1", resume_key=bot_resume_key("bot-0-00000"), PROLIFIC_PID="bot-0-00000")
    assert client.post("/api/admin/studies/s1/close", headers=auth(admin)).json()["status"] == "closed"

    refused = client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "late"})
    assert refused.status_code == 410 and refused.json()["code"] == "gone", refused.text
    assert "closed" in refused.json()["detail"]
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(), participants=1)
    assert summary.errors == [] and summary.completed == 1
    state = client.get(f"/api/p/{running['token']}/state").json()
    assert state["phase"] == "debrief"
    people = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()
    assert [(p["external_id"], p["status"]) for p in people] == [("bot-0-00000", "completed")]


def test_serve_creates_the_demo_study_open_and_marks_drafts_in_its_links(database_url, capsys):
    from fastapi.testclient import TestClient

    from server.cli.server import _prepare, _print_links
    from server.main import create_app
    from server.settings import Settings

    settings = Settings(database_url=database_url)
    token, studies = _prepare(settings)
    assert studies == [("demo", "open")]  # `trustlab serve` on an empty database: the demo can be tried at once
    client = TestClient(create_app(Settings(database_url=database_url, world_loop=False, planner_processes=0)))
    assert join(client, "demo")["created"] is True
    admin = token
    make_study(client, admin, slug="pilot", status="draft")
    make_study(client, admin, slug="ended", status="open")
    assert client.post("/api/admin/studies/ended/close", headers=auth(admin)).status_code == 200
    _print_links(settings, None, _prepare(settings)[1])
    lines = capsys.readouterr().out.splitlines()
    assert not any("[" in line for line in lines if "(demo)" in line)
    assert any("[draft: nobody can join until it is opened" in line for line in lines if "(pilot)" in line)
    assert any("[closed: nobody new can join until it is reopened" in line for line in lines if "(ended)" in line)
