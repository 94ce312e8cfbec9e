"""The bots' HTTP client (a connection the server closed as a request went out is retried once, where safe), and
their teleoperation at a person's pace."""

from __future__ import annotations

import json
import shutil

from contextlib import nullcontext

import httpx
import pytest
from sqlalchemy import select

from experiment.iohmm import paper_params
from server.bots import Bot, BotStats, run_bots
from server.models import Event
from tests.server.factories import make_client, make_study, tiny_study


def flaky_transport(failures: int, seen: list[tuple[str, str, str | None]]) -> httpx.MockTransport:
    """Fails the first ``failures`` requests as a server closing a kept-alive connection does."""

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append((request.method, request.url.path, request.headers.get("Idempotency-Key")))
        if len(seen) <= failures:
            raise httpx.ReadError("[Errno 104] Connection reset by peer", request=request)
        return httpx.Response(200, json={"ok": True})

    return httpx.MockTransport(handle)


def make_bot(transport: httpx.MockTransport, external_id: str | None) -> Bot:
    http = httpx.Client(transport=transport, base_url="http://server")
    bot = Bot(http, lambda path: None, "s1", paper_params(), 0, BotStats(), external_id=external_id)  # type: ignore[arg-type]
    bot.token = "t" * 32
    return bot


def test_a_reset_connection_is_retried_once_with_the_same_idempotency_key():
    seen: list = []
    bot = make_bot(flaky_transport(1, seen), "bot-1")
    assert bot.post("consent", {"agree": True}) == {"ok": True}
    assert len(seen) == 2 and seen[0] == seen[1] and seen[0][2]  # the same request, the same key
    assert len(bot.stats.latencies_ms) == 1  # one call, timed from its first attempt


def test_a_second_failure_is_an_error():
    seen: list = []
    bot = make_bot(flaky_transport(2, seen), "bot-1")
    with pytest.raises(httpx.ReadError):
        bot.state()
    assert len(seen) == 2


def test_a_join_without_an_external_id_is_not_repeated():
    seen: list = []
    bot = make_bot(flaky_transport(1, seen), None)
    with pytest.raises(httpx.ReadError):
        bot.call("POST", "/api/studies/s1/join", {"params": {}})
    assert len(seen) == 1  # a second join would make a second participant
    seen.clear()
    resuming = make_bot(flaky_transport(1, seen), "bot-2")
    assert resuming.call("POST", "/api/studies/s1/join", {"params": {"PROLIFIC_PID": "bot-2"}}) == {"ok": True}
    assert len(seen) == 2 and json.dumps(seen[0]) == json.dumps(seen[1])


def person_paced_study():
    """One practice trial the bot is told to take over (a teleoperation), the robot at 2x: a person's pace."""
    return tiny_study("person-paced bot", hint="intervene", n_high=0, animation_speed=2.0)


def test_at_a_persons_pace_a_bot_teleoperates_with_keys_as_a_person_does(sqlite_template, tmp_path):
    """The robot at 2x: the bot steers as ``HumanModel`` at the page's keyboard: on/off keys, an input message per
    change and keep-alives while a key is held, far fewer messages than the scripted controller's 30 a second."""
    shutil.copy(sqlite_template, tmp_path / "bots.db")  # one backend: this is about the bot, not the database
    client, admin = make_client(database_url=f"sqlite:///{tmp_path / 'bots.db'}")
    make_study(client, admin, config=person_paced_study())
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(), participants=1)
    assert summary.errors == [] and summary.completed == 1
    with client.app.state.sessionmaker() as session:
        logs = [e.payload for e in session.scalars(select(Event).where(Event.kind == "teleop_log")).all()]
    entries = [entry for log in logs for entry in log["entries"]]
    inputs = [entry["input"] for entry in entries if "input" in entry]
    assert any(entry.get("event") == "deposited" for entry in entries)
    speeds = {abs(v) for held in inputs for v in held.get("ee_velocity", [])}
    assert speeds and speeds <= {0.0, 0.2, 0.025}  # the page's key speeds, never a controller's continuous ones
    assert any(held.get("gripper") == "close" for held in inputs)
    assert summary.stats.teleop_ack_ms  # acknowledgements were timed
