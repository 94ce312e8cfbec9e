"""The bots' HTTP client (a connection the server closed as a request went out is retried once, where safe), and
their teleoperation at a person's pace."""

from __future__ import annotations

import json
import queue
import shutil
import statistics
import time
from contextlib import nullcontext

import httpx
import pytest
from sqlalchemy import select

from experiment.iohmm import paper_params
from experiment.participants.page import PAGE_FRAME_S
from experiment.world import build_scene
from server.harness.bots import Bot
from server.harness.client import BotStats, Refused
from server.harness.crowd import run_bots
from server.models import Event
from tests.experiment.test_operator import Simulation
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


def test_a_scene_report_refused_because_the_trial_moved_on_is_answered_by_reading_the_state():
    """A slow client (or one whose server restarted) may report a trial's scene after the window opened at its wait
    limit and closed: the page then reads the state again and goes on, and so does a bot. Other refusals stay errors."""
    seen: list = []
    moved_on = {"phase": "trial", "trial": {"stage": "attempt"}}

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append((request.method, request.url.path))
        if request.url.path.endswith("/trials/shown"):
            status = 409 if len(seen) == 1 else 422
            return httpx.Response(status, json={"detail": "the decision window has closed", "code": "conflict"})
        return httpx.Response(200, json=moved_on)

    bot = make_bot(httpx.MockTransport(handle), "bot-1")
    trial = {"practice": False, "block": 2, "trial": 6, "stage": "presenting", "scene_stamp": "s"}
    assert bot.show_scene(trial) == moved_on
    assert seen == [("POST", f"/api/p/{bot.token}/trials/shown"), ("GET", f"/api/p/{bot.token}/state")]
    with pytest.raises(Refused) as refused:
        bot.show_scene(trial)
    assert refused.value.status == 422


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
    with client.app.state.services.sessionmaker() as session:
        logs = [e.payload for e in session.scalars(select(Event).where(Event.kind == "teleop_log")).all()]
    entries = [entry for log in logs for entry in log["entries"]]
    inputs = [entry["input"] for entry in entries if "input" in entry]
    assert any(entry.get("event") == "deposited" for entry in entries)
    speeds = {abs(v) for held in inputs for v in held.get("ee_velocity", [])}
    assert speeds and speeds <= {0.0, 0.2, 0.025}  # the page's key speeds, never a controller's continuous ones
    assert any(held.get("gripper") == "close" for held in inputs)
    assert summary.stats.teleop_ack_ms  # acknowledgements were timed


class AckingSocket:
    """A teleoperation socket whose server acknowledges every message at once, ``over`` after ``messages``; it notes
    when each message went out and when its ack was handed to the reader."""

    def __init__(self, messages: int):
        self.left = messages
        self.sent: dict[int, float] = {}
        self.delivered: dict[int, float] = {}
        self._replies: queue.SimpleQueue[dict] = queue.SimpleQueue()

    def send_text(self, text: str) -> None:
        seq = json.loads(text)["seq"]
        self.sent[seq] = time.monotonic()
        self.left -= 1
        if self.left >= 0:
            self._replies.put({"type": "ack", "seq": seq, "ok": True, "error": None})
        if self.left == 0:
            self._replies.put({"type": "over", "reason": "ended", "trial_recorded": False, "retry": False})
        # (a message the page sends before it has read ``over`` gets no ack: the server had closed)

    def receive_text(self) -> str:
        reply = self._replies.get(timeout=30)
        if reply["type"] == "ack":
            self.delivered[reply["seq"]] = time.monotonic()
        return json.dumps(reply)


def test_a_persons_ack_latency_is_taken_when_the_ack_arrives_not_when_the_page_loop_looks():
    """The page's loop looks at its messages every ``PAGE_FRAME_S``; an ack's latency is from sending to its arrival
    (the page's ``onmessage``), not to the loop's next look, which would add up to a frame (half of one on average)."""
    setup = Simulation(build_scene("low", 1), 1, 30.0).setup
    socket = AckingSocket(messages=6)
    bot = make_bot(flaky_transport(0, []), "bot-1")
    bot._teleoperate_as_person(socket, setup)  # type: ignore[arg-type]
    assert len(bot.stats.teleop_ack_ms) == 6 and bot.last_teleop is not None
    assert bot.last_teleop["over"]["reason"] == "ended" and bot.last_teleop["acks"] == 6
    # what each took on the socket's side: the bot's figure differs by the reader's hand-over only
    on_the_socket = [(socket.delivered[seq] - socket.sent[seq]) * 1000 for seq in sorted(socket.delivered)]
    off_by = [measured - actual for measured, actual in zip(bot.stats.teleop_ack_ms, on_the_socket, strict=False)]
    assert statistics.median(off_by) < PAGE_FRAME_S * 1000 / 4, (bot.stats.teleop_ack_ms, on_the_socket)


def test_a_stall_says_where_the_session_stood_and_how_the_latest_teleoperation_ended():
    bot = make_bot(flaky_transport(0, []), "bot-1")
    bot.last_teleop = {"over": {"reason": "time_limit", "retry": True}, "sent": 40, "acks": 40, "worlds": 300,
                       "seconds": 300.2, "phase": "to_item"}
    state = {"phase": "practice", "step": {"phase": "practice", "index": 1}, "trial": {"stage": "teleop"}}
    said = bot._stalled(state, deadline=time.monotonic() - 5)
    assert said.startswith("stalled at practice {'phase': 'practice', 'index': 1} (trial stage teleop, 125 s")
    assert "'reason': 'time_limit'" in said and "'seconds': 300.2" in said
