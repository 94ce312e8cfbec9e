"""Trial engine on the server: counterbalancing, teleoperation socket, time limits."""

from collections import Counter
from datetime import timedelta

import pytest
from sqlalchemy import select

from experiment.flow import PracticeStep, TrialStep
from server.models import Event, Participant, Trial, utcnow
from tests.server.factories import fast_config, join, make_client, make_study


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    return client, admin


def at_first_trial(client, token):
    """Put a joined participant at the first scored trial (consent and practice skipped)."""
    client.post(f"/api/p/{token}/consent", json={"agree": True})
    with client.app.state.services.sessionmaker.begin() as session:
        for participant in session.scalars(select(Participant).where(Participant.block_order.is_(None),
                                                                    Participant.status == "active")):
            participant.step = TrialStep(block=1, trial=1)


def start(client, token, **ref):
    return client.post(f"/api/p/{token}/trials/start", json={"practice": False, "block": 1, "trial": 1, **ref})


def test_block_orders_are_balanced_and_ignore_abandoned(api):
    client, _ = api
    tokens = [join(client)["token"] for _ in range(5)]
    for token in tokens[:3]:
        at_first_trial(client, token)
        assert start(client, token).status_code == 200
    with client.app.state.services.sessionmaker.begin() as session:  # the third one leaves
        third = session.scalars(select(Participant).order_by(Participant.id)).all()[2]
        third.status = "abandoned"
    for token in tokens[3:]:
        at_first_trial(client, token)
        start(client, token)
    with client.app.state.services.sessionmaker() as session:
        rows = session.scalars(select(Participant).where(Participant.status == "active")).all()
        orders = Counter(tuple(p.block_order) for p in rows)
        assert sorted(orders.values()) == [2, 2]
        assert all("assigned" in p.assignment["audit"] for p in rows)


def test_trial_record_has_the_policy_and_beliefs(api):
    client, _ = api
    token = join(client)["token"]
    at_first_trial(client, token)
    state = start(client, token).json()
    trial = state["trial"]
    assert trial["complexity"] in ("low", "high") and trial["message"]
    with client.app.state.services.sessionmaker() as session:
        row = session.scalar(select(Trial))
        participant = session.scalar(select(Participant))
        assert row.block_name == participant.block_order[0] and row.belief_before == pytest.approx(0.82)
        assert row.outcome is None  # not decided before it happens


def test_teleop_time_limit_ends_the_trial(database_url):
    """(The socket's side, and the guided practice that starts over instead: tests/server/test_teleop_socket.py.)"""
    config = fast_config()
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=config.model_copy(update={"practice": config.practice.model_copy(
        update={"tutorial": config.practice.tutorial.model_copy(update={"enabled": False})})}))
    token = join(client)["token"]
    client.post(f"/api/p/{token}/consent", json={"agree": True})
    with client.app.state.services.sessionmaker.begin() as session:
        session.scalar(select(Participant)).step = PracticeStep(index=2)
    client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": 3})
    with client.app.state.services.sessionmaker.begin() as session:
        session.scalar(select(Trial)).teleop_deadline_at = utcnow() - timedelta(seconds=1)
    state = client.get(f"/api/p/{token}/state").json()
    assert state["last_trial"]["teleop_success"] is False and state["step"] == {"phase": "practice", "index": 3}


def test_heartbeat_and_client_events(api):
    client, _ = api
    token = join(client)["token"]
    assert client.post(f"/api/p/{token}/heartbeat", json={"client_time_ms": 5.0}).json() == {"ok": True}
    r = client.post(f"/api/p/{token}/events", json={"events": [{"kind": "camera", "client_time_ms": 9.0,
                                                                "payload": {"view": "local", "kind": "x"}}]})
    assert r.status_code == 200
    with client.app.state.services.sessionmaker() as session:
        event = session.scalar(select(Event).where(Event.kind == "client.camera"))
        assert event.payload == {"view": "local", "kind": "x"} and event.client_time_ms == 9.0
