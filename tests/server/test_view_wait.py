"""A teleoperation's time limit stands still while the page has no usable view (issue 37): a page reloaded in the
middle of a teleoperation says so on the socket (``view`` messages) until its view is back; bounded per
teleoperation, and recorded."""

from __future__ import annotations

import time

import pytest
from sqlalchemy import select

from server.harness.teleop_client import CheckedSocket
from server.models import Event, Trial
from server.services import teleop as teleop_service
from tests.server.factories import make_client, make_study
from tests.server.test_teleop_socket import teleoperating

WAIT_S = 1.0


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    return client


def trial_row(client) -> Trial:
    with client.app.state.services.sessionmaker() as session:
        return session.scalars(select(Trial).where(Trial.stage == "teleop")).one()


def view(ws: CheckedSocket, seq: int, usable: bool) -> dict:
    ws.send({"type": "view", "seq": seq, "usable": usable})
    ack = ws.receive_until("ack")
    assert ack["ok"], ack
    return ws.receive_until("world")


def test_the_time_limit_stands_still_while_the_view_is_not_usable_and_the_wait_is_recorded(api):
    client = api
    token, _ = teleoperating(client)
    deadline = trial_row(client).teleop_deadline_at
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        hello = ws.receive()
        limits = hello["teleop"]["limits"]
        assert limits["max_view_wait_s"] == limits["view_wait_left_s"] == teleop_service.MAX_VIEW_WAIT_S
        waiting = view(ws, 1, usable=False)["time_left_ms"]
        # the stored deadline moved by the whole budget meanwhile: a sweep cannot end the teleoperation now
        assert (trial_row(client).teleop_deadline_at - deadline).total_seconds() == pytest.approx(
            teleop_service.MAX_VIEW_WAIT_S)
        time.sleep(WAIT_S)
        assert view(ws, 2, usable=False)["time_left_ms"] == pytest.approx(waiting, abs=50)  # (frozen; sent again)
        back = view(ws, 3, usable=True)["time_left_ms"]
        assert back == pytest.approx(waiting, abs=150)
        time.sleep(0.3)  # the clock runs again
        assert view(ws, 4, usable=True)["time_left_ms"] < back - 200  # (usable again: nothing to end)
    row = trial_row(client)
    assert row.teleop_view_wait_ms == pytest.approx(WAIT_S * 1000, abs=300)
    assert (row.teleop_deadline_at - deadline).total_seconds() == pytest.approx(row.teleop_view_wait_ms / 1000,
                                                                                 abs=0.002)
    with client.app.state.services.sessionmaker() as session:
        [event] = session.scalars(select(Event).where(Event.kind == "teleop_view_wait")).all()
    assert event.payload["waited_ms"] == row.teleop_view_wait_ms


def test_the_wait_is_bounded_per_teleoperation_and_a_closed_socket_ends_it(api, monkeypatch):
    monkeypatch.setattr(teleop_service, "MAX_VIEW_WAIT_S", 0.5)
    client = api
    token, _ = teleoperating(client)
    deadline = trial_row(client).teleop_deadline_at
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        ws.receive()
        waiting = view(ws, 1, usable=False)["time_left_ms"]
        time.sleep(WAIT_S + 0.5)  # past the budget: the clock runs again
        assert view(ws, 2, usable=False)["time_left_ms"] < waiting - 800
    row = trial_row(client)  # the socket closed during the wait: it ended there
    assert row.teleop_view_wait_ms == pytest.approx(500, abs=1)
    assert (row.teleop_deadline_at - deadline).total_seconds() == pytest.approx(0.5, abs=0.002)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:  # a reload: nothing left to wait
        ws = CheckedSocket(raw)
        assert ws.receive()["teleop"]["limits"]["view_wait_left_s"] == 0
        left = view(ws, 1, usable=False)["time_left_ms"]
        time.sleep(0.4)
        assert view(ws, 2, usable=True)["time_left_ms"] < left - 300
    assert trial_row(client).teleop_view_wait_ms == pytest.approx(500, abs=1)
