"""The 3D view: viser's client page, the viewer websocket, per-session scenes, poses, cameras.

No browser: a simulated viser client connects to the viewer socket with the
``viser-v1.1.1`` subprotocol, sends one ``ViewerCameraMessage`` (as viser's
client does; the server drops it) and decodes the server's frames
(``[u64 raw len][u64 zstd len][zstd(msgpack {"messages": [...]})][binary]``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta
from typing import Any

import anyio
import msgspec
import numpy as np
import pytest
import viser
from sqlalchemy import select
from starlette.websockets import WebSocketDisconnect

from experiment.engine import PlannedTrial
from experiment.flow import PracticeStep
from experiment.task import Complexity
from experiment.templates import demo_fast
from experiment.world import (
    ItemMode,
    ItemState,
    WorldState,
    build_scene,
    link_poses,
    teleop_start_state,
)
from experiment.world.robot import solve_ik
from experiment.world.scene import ITEM_COLORS, OBSTACLE_COLOR
from server.harness.teleop_client import CheckedSocket
from server.models import Event, Participant, Trial, utcnow
from server.services.sessions import participant_by_token
from server.services.trials import PRACTICE_BLOCK
from server.viewer.cameras import VIEW_FOV_DEG, camera_for, world_camera
from server.viewer.live import LiveView
from server.viewer.scene import (
    ARROW_HEAD,
    ARROW_HEAD_RADIUS,
    ARROW_SHAFT,
    ARROW_SHAFT_RADIUS,
    BIN_HIGHLIGHT,
    HIGHLIGHT_COLOR,
    MARKER_HEIGHT,
    STAMP_PREFIX,
    TARGET_ARROW,
    TARGET_HALO,
    TARGET_LABEL,
    TARGET_MARKER,
    TARGET_SLOT,
    arrow_axis,
    arrow_mesh,
    pose_tuples,
    start_state,
)
from server.viewer.wire import unpack
from tests.server.factories import fast_config, join, make_client, make_study

#: The PostgreSQL runs add nothing here (tests/conftest.py): the 3D view's messages, scenes and cameras; the trial rows
#: it reads are the other modules' on both databases.
STORAGE_INCIDENTAL = True

SUBPROTOCOL = f"viser-v{viser.__version__}"
HELLO = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, -3.0, 2.0], "fov": 0.9,
         "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 1000, "look_at": [1.0, 0.0, 0.5],
         "up_direction": [0.0, 0.0, 1.0]}
CONFIG = fast_config(timing=demo_fast().timing.model_copy(update={"decision_window_s": 60.0, "animation_speed": 1.0}))


@pytest.fixture
def client(database_url):
    client, admin = make_client(database_url=database_url, world_loop=True)
    make_study(client, admin, config=CONFIG)
    with client:  # runs the lifespan: the world loop and the viewer manager
        yield client


# --- helpers ---------------------------------------------------------------------------------

def decode(frame: bytes) -> list[dict[str, Any]]:
    return unpack(frame)[0]["messages"]


def receive_within(ws, timeout: float) -> bytes:
    """One frame, or TimeoutError (TestClient's receive has no timeout of its own)."""
    async def receive() -> Any:
        with anyio.fail_after(timeout):
            return await ws._send_rx.receive()
    message = ws.portal.call(receive)
    ws._raise_on_close(message)
    return message["bytes"]


class Viewer:
    """A simulated viser client on the viewer socket; ``seen`` keeps every message received so far."""

    def __init__(self, ws):
        self.ws = ws
        self.seen: list[dict[str, Any]] = []

    def collect(self, until: Callable[[list[dict[str, Any]]], bool], timeout: float = 5.0) -> list[dict[str, Any]]:
        """Receive until ``until(every message so far)`` holds; returns the messages of this call.

        AssertionError after ``timeout`` s; WebSocketDisconnect if the server closes the socket.
        """
        start = len(self.seen)
        deadline = time.monotonic() + timeout
        while not until(self.seen):
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"gave up after {timeout} s; {len(self.seen) - start} new messages")
            try:
                self.seen.extend(decode(receive_within(self.ws, left)))
            except TimeoutError:
                continue
        return self.seen[start:]

    def replayed(self) -> list[dict[str, Any]]:
        """Everything up to the end of the scene's replay."""
        self.collect(lambda ms: any(m["type"] == "ReplayDoneMessage" for m in ms))
        return self.seen

    def stamp(self) -> str | None:
        """The stamp of the scene this client holds (its ``/scene_stamp_<stamp>`` node), as a page reads it back."""
        held = None
        for m in self.seen:
            if m.get("name", "").startswith(STAMP_PREFIX):
                held = m["name"][len(STAMP_PREFIX):] if m["type"] == "FrameMessage" else None
        return held

    def await_stamp(self, stamp: str, timeout: float = 5.0) -> None:
        """Receive until this client holds the scene of ``stamp``."""
        self.collect(lambda _: self.stamp() == stamp, timeout)


@contextmanager
def viewer(client, token: str) -> Iterator[Viewer]:
    with client.websocket_connect(f"/viewer/{token}", subprotocols=[SUBPROTOCOL]) as ws:
        assert ws.accepted_subprotocol == SUBPROTOCOL
        ws.send_bytes(msgspec.msgpack.encode(HELLO))
        yield Viewer(ws)


FIELDS = {"SetOrientationMessage": "wxyz", "SetPositionMessage": "position", "SetCameraPositionMessage": "position",
          "SetCameraLookAtMessage": "look_at", "SetCameraUpDirectionMessage": "position", "SetCameraFovMessage": "fov"}
CAMERA_MESSAGES = ("SetCameraPositionMessage", "SetCameraLookAtMessage", "SetCameraUpDirectionMessage",
                   "SetCameraFovMessage")


def latest(messages: list[dict[str, Any]], kind: str, name: str | None = None) -> Any:
    """The newest value a ``kind`` message (for node ``name``) carried, or None."""
    values = [m[FIELDS[kind]] for m in messages if m["type"] == kind and m.get("name") == name]
    return values[-1] if values else None


def close_to(expected) -> Callable[[list[dict[str, Any]]], bool]:
    """Until the newest /robot/j1 pose equals ``expected`` (position (3,), wxyz (4,))."""
    def check(messages: list[dict[str, Any]]) -> bool:
        p = latest(messages, "SetPositionMessage", "/robot/j1")
        q = latest(messages, "SetOrientationMessage", "/robot/j1")
        return (p is not None and q is not None and np.allclose(p, expected[0], atol=1e-6)
                and np.allclose(q, expected[1], atol=1e-6))
    return check


def in_practice_trial(client, index: int) -> tuple[str, str]:
    """A consented participant whose practice trial ``index`` (0: low/auto, 1: high/auto, 2: low/ask) has started.

    Returns (token, public id).
    """
    token = join(client)["token"]
    assert client.post(f"/api/p/{token}/consent", json={"agree": True}).status_code == 200
    with client.app.state.services.sessionmaker.begin() as session:
        participant = participant_by_token(session, token)
        participant.step = PracticeStep(index=index)
        public_id = participant.public_id
    response = client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": index + 1})
    assert response.status_code == 200, response.text
    return token, public_id


def open_decision_window(client, token: str, trial: int) -> None:
    """Report the practice trial's scene as shown (a page without a view): its decision window opens."""
    response = client.post(f"/api/p/{token}/trials/shown", json={"practice": True, "block": 0, "trial": trial,
                                                                  "view": "text"})
    assert response.status_code == 200, response.text


def session_of(client, public_id: str):
    return next(vs for vs in client.app.state.services.viewers.sessions() if vs.public_id == public_id)


# --- the page and the socket -------------------------------------------------------------------

def test_page_is_served_for_valid_tokens_only(client):
    token = join(client)["token"]
    page = client.get(f"/viewer/{token}/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '<div id="root">' in page.text and "<title>Robot view</title>" in page.text
    assert page.headers["referrer-policy"] == "no-referrer"
    assert client.get("/viewer/" + "x" * 32 + "/").status_code == 404
    redirect = client.get(f"/viewer/{token}?websocket=x", follow_redirects=False)
    assert redirect.status_code == 307 and redirect.headers["location"] == f"{token}/?websocket=x"
    assert client.app.state.services.viewers.sessions() == []  # a page alone starts no server


def test_the_socket_refuses_unknown_tokens_and_wrong_versions(client):
    for path in ("/viewer/" + "x" * 32, "/viewer/short"):
        with pytest.raises(WebSocketDisconnect) as closed, \
                client.websocket_connect(path, subprotocols=[SUBPROTOCOL]) as ws:
            ws.receive_bytes()
        assert closed.value.code == 4404
    token = join(client)["token"]
    for offered in (["viser-v0.9.0"], []):
        with pytest.raises(WebSocketDisconnect) as closed, \
                client.websocket_connect(f"/viewer/{token}", subprotocols=offered) as ws:
            ws.receive_bytes()
        assert closed.value.code == 1002
    assert client.app.state.services.viewers.sessions() == []


# --- the scene ----------------------------------------------------------------------------------

@pytest.mark.parametrize(("index", "complexity"), [(1, "high"), (0, "low")])
def test_scene_of_the_current_trial(client, index, complexity):
    token, public_id = in_practice_trial(client, index)
    with viewer(client, token) as ws:
        messages = ws.replayed()
        nodes = {m["name"] for m in messages if m["type"] in ("BoxMessage", "CylinderMessage", "FrameMessage")}
        obstacles = {n for n in nodes if n.startswith("/obstacles/")}
        scene = session_of(client, public_id).view.scene
        assert scene.complexity == complexity and len(obstacles) == len(scene.obstacles)
        assert bool(obstacles) == (complexity == "high")
        assert {"/floor", "/shelf/board_0", "/robot/base/bin_floor", "/robot/j2/link", "/items/target/geom",
                "/target_slot", "/robot/j1", "/items/target"} <= nodes
        assert {f"/items/{it.slot}" for i, it in enumerate(scene.items) if i != scene.target_index} <= nodes
        # before the attempt the robot waits at the trial's start pose (the first frame after the replay)
        messages = ws.collect(close_to(pose_tuples(link_poses(start_state(scene)))["/robot/j1"]), timeout=2.0)
        assert latest(messages, "SetPositionMessage", "/robot/base") == pytest.approx(list(scene.start[:2]) + [0.0])


def test_attempt_playback_moves_the_arm_and_the_item(client):
    token, public_id = in_practice_trial(client, 1)
    hub = client.app.state.services.hub
    with viewer(client, token) as ws:
        ws.replayed()
        open_decision_window(client, token, 2)
        with client.app.state.services.sessionmaker.begin() as session:  # the decision window closes now
            session.scalar(select(Trial)).decision_deadline_at = utcnow() - timedelta(seconds=0.1)
        assert client.get(f"/api/p/{token}/state").json()["trial"]["stage"] == "attempt"
        # ... and the attempt does not end during the test
        with client.app.state.services.sessionmaker.begin() as session:
            session.scalar(select(Trial)).attempt_end_at = utcnow() + timedelta(hours=1)
        planned = PlannedTrial(0, PRACTICE_BLOCK, 2, 2, 1, False, Complexity.HIGH)
        attempt = hub.attempts.get(CONFIG.seed, public_id, planned, True)
        # hold the playback at moments of interest (a tiny speed keeps the frames still)
        for t in (attempt.arm_start_time - 1.0, attempt.deposit_time - 0.6, attempt.duration):
            hub.play(public_id, attempt, time.monotonic() - t / 1e-9, 1e-9)
            expected = link_poses(attempt.state_at(t))
            messages = ws.collect(close_to(pose_tuples(expected)["/robot/j1"]))
            item = latest(messages, "SetPositionMessage", "/items/target")
            assert item is None or np.allclose(item, expected["/items/target"][0], atol=1e-6)
        shown = session_of(client, public_id).live.poses["/robot/j1"]
        assert np.allclose(shown[1], expected["/robot/j1"][1]) and np.allclose(shown[0], expected["/robot/j1"][0])
        assert attempt.state_at(attempt.duration).item.mode == ItemMode.IN_BIN


def test_a_dropped_item_falls_in_view(client):
    token, public_id = in_practice_trial(client, 1)
    hub = client.app.state.services.hub
    planned = PlannedTrial(0, PRACTICE_BLOCK, 2, 2, 1, False, Complexity.HIGH)
    attempt = hub.attempts.get(CONFIG.seed, public_id, planned, False)
    with viewer(client, token) as ws:
        ws.replayed()
        with client.app.state.services.sessionmaker.begin() as session:
            session.scalar(select(Trial)).stage = "attempt"
        t = attempt.duration
        hub.play(public_id, attempt, time.monotonic() - t / 1e-9, 1e-9)
        expected = pose_tuples(link_poses(attempt.state_at(t)))
        assert attempt.state_at(t).item.mode == ItemMode.DROPPED
        fallen = expected["/items/target"][0]
        assert np.linalg.norm(np.subtract(fallen, session_of(client, public_id).view.scene.target.center)) > 0.05
        ws.collect(lambda ms: latest(ms, "SetPositionMessage", "/items/target") is not None
                and np.allclose(latest(ms, "SetPositionMessage", "/items/target"), fallen, atol=1e-6))


def test_teleoperation_moves_the_arm(client):
    token, public_id = in_practice_trial(client, 2)  # the robot asks: teleoperation
    with viewer(client, token) as ws:
        ws.replayed()
        scene = session_of(client, public_id).view.scene
        ws.collect(close_to(pose_tuples(link_poses(teleop_start_state(scene)))["/robot/j1"]), timeout=2.0)
        with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
            teleop = CheckedSocket(raw)
            assert teleop.receive()["stage"] == "teleop"
            assert teleop.input(0, ee_velocity=[0.0, 0.3, -0.1])["ok"]
            for _ in range(4):
                world = teleop.receive_until("world")["world"]
            assert teleop.input(1)["ok"]  # released: the next world message shows where the arm stays
            world = teleop.receive_until("world")["world"]
        item = world["item"]
        state = WorldState(world["t"], tuple(world["base"]), tuple(world["joints"]), world["gripper"],
                           world["gripper_target"], ItemState(ItemMode(item["mode"]), tuple(item["position"]),
                                                              tuple(item["wxyz"])))
        expected = pose_tuples(link_poses(state))["/robot/j1"]
        assert not np.allclose(expected[1], pose_tuples(link_poses(teleop_start_state(scene)))["/robot/j1"][1])
        ws.collect(close_to(expected))


def test_a_timed_out_teleoperation_ends_and_the_next_attempt_shows(client):
    token, public_id = in_practice_trial(client, 2)
    with client.websocket_connect(f"/api/p/{token}/teleop") as teleop:
        assert CheckedSocket(teleop).receive()["stage"] == "teleop"
    hub = client.app.state.services.hub
    assert len(hub.arms) == 1
    with client.app.state.services.sessionmaker.begin() as session:
        row = session.scalar(select(Trial))
        row.teleop_deadline_at, row.tutorial = utcnow() - timedelta(seconds=1), False  # not the guided practice
    assert client.get(f"/api/p/{token}/state").json()["last_trial"]["teleop_success"] is False
    assert len(hub.arms) == 0 and hub.world_of(public_id) is None  # the time limit ended it in the hub
    with client.app.state.services.sessionmaker.begin() as session:
        participant_by_token(session, token).step = PracticeStep(index=1)
    assert client.post(f"/api/p/{token}/trials/start",
                       json={"practice": True, "block": 0, "trial": 2}).status_code == 200
    planned = PlannedTrial(0, PRACTICE_BLOCK, 2, 2, 1, False, Complexity.HIGH)
    attempt = hub.attempts.get(CONFIG.seed, public_id, planned, True)
    t = attempt.deposit_time - 0.6
    hub.play(public_id, attempt, time.monotonic() - t / 1e-9, 1e-9)
    assert np.allclose(hub.tick()[public_id].state.joints, attempt.state_at(t).joints)
    with viewer(client, token) as ws:
        ws.collect(close_to(pose_tuples(link_poses(attempt.state_at(t)))["/robot/j1"]))


def attempt_the_hub_does_not_play(client) -> tuple[str, str, Any, datetime, datetime]:
    """A participant whose practice attempt is under way (and does not end during the test) but whose playback the
    hub no longer has, as a restarted process or another worker never had it: (token, public id, the playback the hub
    had, the attempt's planned end, when it was decided)."""
    token, public_id = in_practice_trial(client, 1)
    hub = client.app.state.services.hub
    open_decision_window(client, token, 2)
    with client.app.state.services.sessionmaker.begin() as session:
        session.scalar(select(Trial)).decision_deadline_at = utcnow() - timedelta(seconds=0.5)
    assert client.get(f"/api/p/{token}/state").json()["trial"]["stage"] == "attempt"
    started = hub.playbacks.get(public_id)
    with client.app.state.services.sessionmaker.begin() as session:
        trial = session.scalar(select(Trial))
        planned_end, decided = trial.attempt_end_at, trial.decided_at
        trial.attempt_end_at = utcnow() + timedelta(hours=1)  # the attempt does not end during the test
    hub.stop(public_id)
    assert hub.world_of(public_id) is None
    return token, public_id, started, planned_end, decided


def test_an_attempt_this_process_did_not_start_is_played_back(client):
    """After a restart, or when another worker of a group closed the decision window, the view shows the attempt."""
    token, public_id, started, planned_end, decided = attempt_the_hub_does_not_play(client)
    hub = client.app.state.services.hub
    with viewer(client, token) as ws:
        ws.replayed()
        deadline = time.monotonic() + 10
        while hub.world_of(public_id) is None:
            assert time.monotonic() < deadline, "the viewer did not play the attempt back"
            time.sleep(0.05)
    replayed = hub.playbacks.get(public_id)
    assert (replayed.attempt.scene.seed, replayed.attempt.failure_mode, replayed.attempt.duration) == (
        started.attempt.scene.seed, started.attempt.failure_mode, started.attempt.duration)  # the same attempt ...
    assert replayed.attempt.duration == pytest.approx((planned_end - decided).total_seconds())
    assert replayed.start == pytest.approx(started.start, abs=0.25)  # ... from the same moment on


def test_a_view_process_leaves_an_attempt_that_just_began_to_its_servers_playback(client):
    """A view process is sent each playback as its attempt begins: a poll that reads the attempt before that message
    arrives does not plan it too, unless it began longer ago than the message takes (then no one will send it)."""
    manager = client.app.state.services.viewers
    manager.poll_s = 3600.0  # only the polls the test runs
    token, public_id, _, _, decided = attempt_the_hub_does_not_play(client)  # (its playback message is on its way)
    hub = client.app.state.services.hub
    manager.announced_playback_s = 3600.0
    with viewer(client, token) as ws:
        ws.replayed()
        client.portal.call(manager.poll_once)  # type: ignore[union-attr]
        assert hub.world_of(public_id) is None  # left to the message on its way
        manager.announced_playback_s = (utcnow() - decided).total_seconds() - 0.1  # ... which is now overdue
        client.portal.call(manager.poll_once)  # type: ignore[union-attr]
        assert hub.world_of(public_id) is not None


def test_a_started_trial_is_in_the_viewer_when_its_start_is_answered(client):
    """Starting a trial shows its scene in this process's viewer before the answer, which says so; the viewer's
    client gets the scene's stamp after the rest of its first picture, and the page's report with that stamp opens
    the window (one report per trial). A report with the stamp the client held before (the previous trial's) does
    not count. Without a viewer client the answer says the viewer does not hold the scene."""
    manager = client.app.state.services.viewers
    manager.poll_s = 3600.0  # no poll during the test: only the trial's start can tell the viewer
    token, public_id = in_practice_trial(client, 0)
    second = {"practice": True, "block": 0, "trial": 2}
    with viewer(client, token) as ws:
        ws.replayed()
        old_seed = session_of(client, public_id).view.scene.seed
        old_stamp = session_of(client, public_id).view.scene.stamp
        ws.await_stamp(old_stamp)  # after the replay
        with client.app.state.services.sessionmaker.begin() as session:
            participant_by_token(session, token).step = PracticeStep(index=1)
        started = client.post(f"/api/p/{token}/trials/start", json=second)
        assert started.status_code == 200, started.text
        assert started.json()["trial"]["stage"] == "presenting" and started.json()["trial"]["scene_in_viewer"] is True
        assert session_of(client, public_id).view.scene.seed != old_seed  # (shown before the answer)
        repeated = client.post(f"/api/p/{token}/trials/start", json=second)  # a retried start says the same
        assert repeated.json()["trial"]["scene_in_viewer"] is True
        stale = client.post(f"/api/p/{token}/trials/shown", json=second | {"view": "3d", "scene_stamp": old_stamp})
        assert stale.status_code == 200 and stale.json()["trial"]["stage"] == "presenting"
        new_stamp = started.json()["trial"]["scene_stamp"]
        ws.await_stamp(new_stamp)
        assert ws.seen[-1]["name"] == f"{STAMP_PREFIX}{new_stamp}"  # the last message of the trial's change
        shown = client.post(f"/api/p/{token}/trials/shown", json=second | {"view": "3d", "scene_stamp": ws.stamp()})
        assert shown.status_code == 200 and shown.json()["trial"]["stage"] == "decision"
    with client.app.state.services.sessionmaker() as session:
        trial = session.scalars(select(Trial).where(Trial.block_name == PRACTICE_BLOCK, Trial.trial == 2)).one()
        assert trial.window_opened_by == "3d"
    other, other_id = in_practice_trial(client, 0)
    with viewer(client, other) as ws:
        ws.replayed()
    deadline = time.monotonic() + 5.0  # the socket has closed: the session's viewer has no client
    while session_of(client, other_id).sinks and time.monotonic() < deadline:
        time.sleep(0.02)
    with client.app.state.services.sessionmaker.begin() as session:
        participant_by_token(session, other).step = PracticeStep(index=1)
    started = client.post(f"/api/p/{other}/trials/start", json=second).json()["trial"]
    assert started["stage"] == "presenting" and started["scene_in_viewer"] is False


def test_a_scene_the_viewer_fails_to_build_does_not_fail_the_start(client, monkeypatch, caplog):
    """A trial's scene that fails to build (once) does not hold up or fail the start: its answer says the viewer
    does not hold the scene, the error is logged, and the next poll builds it, which the page's reports then find."""
    from server.viewer.scene import SceneView

    manager = client.app.state.services.viewers
    manager.poll_s = 3600.0  # no poll until the test runs one
    token, public_id = in_practice_trial(client, 0)
    second = {"practice": True, "block": 0, "trial": 2}
    real, failures = SceneView.show_trial, []

    def fails_once(view, scene):
        if not failures:
            failures.append(scene.seed)
            raise RuntimeError("viser refused a node")
        return real(view, scene)
    with viewer(client, token) as ws:
        ws.replayed()
        with client.app.state.services.sessionmaker.begin() as session:
            participant_by_token(session, token).step = PracticeStep(index=1)
        monkeypatch.setattr(SceneView, "show_trial", fails_once)
        started = client.post(f"/api/p/{token}/trials/start", json=second)
        assert started.status_code == 200 and started.json()["trial"]["scene_in_viewer"] is False
        assert failures and "cannot show" in caplog.text
        report = second | {"view": "3d", "scene_stamp": ws.stamp()}  # what the client holds: the previous scene's
        assert client.post(f"/api/p/{token}/trials/shown", json=report).json()["trial"]["stage"] == "presenting"
        client.portal.call(manager.poll_once)  # type: ignore[union-attr]  # the poll, on the app's event loop
        assert session_of(client, public_id).view.scene.seed == failures[0]
        ws.await_stamp(started.json()["trial"]["scene_stamp"])
        shown = client.post(f"/api/p/{token}/trials/shown", json=report | {"scene_stamp": ws.stamp()}).json()["trial"]
        assert shown["scene_in_viewer"] is True and shown["stage"] == "decision"


def test_the_previous_trials_world_is_not_shown_for_the_next_trial(client):
    """The hub keeps a finished attempt until the participant's next world; the viewer rests instead."""
    token, public_id = in_practice_trial(client, 1)
    hub = client.app.state.services.hub
    old = PlannedTrial(0, PRACTICE_BLOCK, 1, 1, 1, False, Complexity.LOW)
    stale = hub.attempts.get(CONFIG.seed, public_id, old, True)
    hub.play(public_id, stale, time.monotonic() - stale.deposit_time, 1.0)
    current = hub.scene(CONFIG.seed, public_id, PlannedTrial(0, PRACTICE_BLOCK, 2, 2, 1, False, Complexity.HIGH))
    resting, stale_pose = (pose_tuples(link_poses(state))["/robot/j1"]
                           for state in (start_state(current), stale.state_at(stale.deposit_time)))
    assert not np.allclose(np.concatenate(resting), np.concatenate(stale_pose))
    with viewer(client, token) as ws:
        ws.collect(close_to(resting))


# --- cameras --------------------------------------------------------------------------------

def test_camera_presets(client):
    token, public_id = in_practice_trial(client, 0)
    assert client.post(f"/api/p/{token}/camera", json={"view": "top"}).status_code == 422
    assert client.post(f"/api/p/{token}/camera", json={"view": "local"}).json() == {"view": "local", "viewers": 0}
    with viewer(client, token) as ws:  # a new viewer gets the session's preset: looking at the gripper
        ws.replayed()
        live = session_of(client, public_id).live
        _, look, _ = camera_for("local", live.poses, marker_height=MARKER_HEIGHT, focus=live._local_focus())
        ws.collect(lambda ms: latest(ms, "SetCameraLookAtMessage") is not None
                and np.allclose(latest(ms, "SetCameraLookAtMessage"), look))
        assert latest(ws.seen, "SetCameraFovMessage") == pytest.approx(np.radians(VIEW_FOV_DEG["local"]))
        response = client.post(f"/api/p/{token}/camera", json={"view": "world", "client_time_ms": 12.5})
        assert response.status_code == 200 and response.json() == {"view": "world", "viewers": 1}
        position, look_at = world_camera(MARKER_HEIGHT)
        ws.collect(lambda ms: np.allclose(latest(ms, "SetCameraLookAtMessage"), look_at))
        assert latest(ws.seen, "SetCameraPositionMessage") == pytest.approx(list(position))
        assert latest(ws.seen, "SetCameraFovMessage") == pytest.approx(np.radians(VIEW_FOV_DEG["world"]))
    with client.app.state.services.sessionmaker() as session:
        events = session.scalars(select(Event).where(Event.kind == "camera")).all()
        assert [e.payload["view"] for e in events] == ["local", "world"] and events[-1].client_time_ms == 12.5


def camera_messages(messages: list[dict[str, Any]]) -> list[tuple[str, tuple[float, ...]]]:
    """Every camera message in order: (type, value)."""
    return [(m["type"], tuple(np.atleast_1d(m[FIELDS[m["type"]]]).tolist())) for m in messages
            if m["type"] in CAMERA_MESSAGES]


def test_the_world_camera_is_the_same_in_every_trial(client):
    """The world preset is one pose: the next trial sends no camera, and going back to it gives the same pose."""
    token, public_id = in_practice_trial(client, 0)
    position, look_at = world_camera(MARKER_HEIGHT)
    with viewer(client, token) as ws:
        first = camera_messages(ws.replayed())
        assert ("SetCameraPositionMessage", pytest.approx(position)) in first
        assert ("SetCameraLookAtMessage", pytest.approx(look_at)) in first
        assert ("SetCameraFovMessage", pytest.approx((np.radians(VIEW_FOV_DEG["world"]),))) in first
        seen = len(ws.seen)
        vs = session_of(client, public_id)
        old_seed = vs.view.scene.seed
        with client.app.state.services.sessionmaker.begin() as session:  # on to the next trial (another target)
            participant_by_token(session, token).step = PracticeStep(index=1)
        response = client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": 2})
        assert response.status_code == 200, response.text
        ws.collect(lambda ms: any(m.get("name") == "/items/target/geom" for m in ms[seen:]))
        assert vs.view.scene.seed != old_seed
        with pytest.raises(AssertionError, match="gave up"):  # what the new trial sends in a poll or two
            ws.collect(lambda ms: False, timeout=1.5)
        assert camera_messages(ws.seen[seen:]) == []  # the new trial leaves the camera where it is
        for view in ("end_effector", "world"):  # and the world preset is the same pose as before
            assert client.post(f"/api/p/{token}/camera", json={"view": view}).status_code == 200
        world_fov = pytest.approx(np.radians(VIEW_FOV_DEG["world"]))
        ws.collect(lambda ms: latest(ms[seen:], "SetCameraFovMessage") == world_fov)
        ws.collect(lambda ms: latest(ms[seen:], "SetCameraLookAtMessage") is not None
                   and np.allclose(latest(ms[seen:], "SetCameraLookAtMessage"), look_at))
        assert latest(ws.seen, "SetCameraPositionMessage") == pytest.approx(list(position))
        assert latest(ws.seen, "SetCameraUpDirectionMessage") == pytest.approx([0.0, 0.0, 1.0])


# --- lifecycle ------------------------------------------------------------------------------

def test_views_stop_when_sessions_end_or_idle(client):
    manager = client.app.state.services.viewers
    token, public_id = in_practice_trial(client, 0)
    with viewer(client, token) as ws:
        ws.replayed()
        first = session_of(client, public_id)
        with viewer(client, token) as second:  # a second tab shares the session's view
            second.replayed()
            assert session_of(client, public_id) is first and first.viewers == 2
        with client.app.state.services.sessionmaker.begin() as session:
            session.scalar(select(Participant)).status = "withdrawn"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.collect(lambda ms: False, timeout=5.0)
        assert closed.value.code == 4404
    assert first.closed and manager.sessions() == []
    with client.websocket_connect(f"/viewer/{token}", subprotocols=[SUBPROTOCOL]) as ws:
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_bytes()
        assert closed.value.code == 4404

    token, public_id = in_practice_trial(client, 0)
    manager.idle_stop_s = 0.2
    with viewer(client, token) as ws:
        ws.replayed()
    idle = session_of(client, public_id)
    deadline = time.monotonic() + 5
    while not idle.closed and time.monotonic() < deadline:
        time.sleep(0.05)
    assert idle.closed and manager.sessions() == []
    with viewer(client, token) as ws:  # a later viewer gets a new view with the same scene
        ws.replayed()
        assert session_of(client, public_id).view.scene.seed == idle.view.scene.seed


# --- what marks the target and the bin ------------------------------------------------------------

def visibility(messages: list[dict[str, Any]], name: str) -> list[bool]:
    """Every visibility ``name`` was given, in order (creation included)."""
    return [m["visible"] for m in messages if m["type"] == "SetSceneNodeVisibilityMessage" and m.get("name") == name]


def created(messages: list[dict[str, Any]], name: str) -> dict[str, Any]:
    return next(m for m in messages if m.get("name") == name and "props" in m)


@pytest.mark.parametrize("index", [1, 0])  # high, low complexity
def test_the_target_is_marked_above_the_obstacles_and_outlined(client, index):
    token, public_id = in_practice_trial(client, index)
    with viewer(client, token) as ws:
        messages = ws.replayed()
        scene = session_of(client, public_id).view.scene
        target = scene.target
        top = float(target.center[2] + target.height / 2)
        marker = latest(messages, "SetPositionMessage", TARGET_MARKER)
        assert marker[:2] == pytest.approx([float(v) for v in target.center[:2]])  # right above the item ...
        assert marker[2] > top + 0.05
        for obstacle in scene.obstacles:  # ... and above every obstacle in front of it
            assert marker[2] > float(obstacle.center[2] + obstacle.size[2] / 2)
        assert bool(scene.obstacles) == (scene.complexity == "high")
        arrow = created(messages, TARGET_ARROW)
        assert arrow["type"] == "MeshMessage" and tuple(arrow["props"]["color"]) == HIGHLIGHT_COLOR
        vertices, _ = arrow_mesh(ARROW_HEAD, ARROW_HEAD_RADIUS, ARROW_SHAFT, ARROW_SHAFT_RADIUS)
        assert vertices[:, 2].min() == 0.0 and list(vertices[np.argmin(vertices[:, 2])]) == [0.0, 0.0, 0.0]
        assert vertices[:, 2].max() == pytest.approx(ARROW_HEAD + ARROW_SHAFT)  # it points down from above at the item
        label = created(messages, TARGET_LABEL)
        assert label["type"] == "LabelMessage" and label["props"]["depth_test"] is False  # drawn over everything
        halo = created(messages, TARGET_HALO)  # an outline: a larger copy of the item, seen from inside
        assert halo["props"]["side"] == "back" and tuple(halo["props"]["color"]) == HIGHLIGHT_COLOR
        size = halo["props"]["dimensions"] if halo["type"] == "BoxMessage" else [2 * halo["props"]["radius"]] * 2 + [
            halo["props"]["height"]]
        assert all(s > float(t) for s, t in zip(size, target.size, strict=True))
        assert HIGHLIGHT_COLOR not in ITEM_COLORS and HIGHLIGHT_COLOR != OBSTACLE_COLOR
        for name in (TARGET_MARKER, TARGET_HALO, TARGET_SLOT):
            assert visibility(messages, name)[-1] is True


def test_the_bin_is_highlighted_only_while_the_item_is_held(client):
    token, public_id = in_practice_trial(client, 1)
    hub = client.app.state.services.hub
    planned = PlannedTrial(0, PRACTICE_BLOCK, 2, 2, 1, False, Complexity.HIGH)
    attempt = hub.attempts.get(CONFIG.seed, public_id, planned, True)

    def hold(t: float) -> None:
        hub.play(public_id, attempt, time.monotonic() - t / 1e-9, 1e-9)

    with viewer(client, token) as ws:
        messages = ws.replayed()
        assert BIN_HIGHLIGHT.startswith("/robot/base/")  # it rides on the base: no message of its own as it drives
        assert visibility(messages, BIN_HIGHLIGHT) == [False]
        hold(attempt.arm_start_time - 1.0)
        with client.app.state.services.sessionmaker.begin() as session:
            session.scalar(select(Trial)).stage = "attempt"
        ws.collect(close_to(pose_tuples(link_poses(attempt.state_at(attempt.arm_start_time - 1.0)))["/robot/j1"]))
        # the gripper closing on the item: the arrow (which it would pass through) hides, the outline stays
        hold(attempt.grasp_time - 0.05)
        assert attempt.state_at(attempt.grasp_time - 0.05).item.mode == ItemMode.ON_SHELF
        ws.collect(lambda ms: visibility(ms, TARGET_MARKER)[-1] is False)
        assert visibility(ws.seen, TARGET_HALO)[-1] is True and visibility(ws.seen, BIN_HIGHLIGHT) == [False]
        # carried at full speed: the bin lights up, once, while every frame moves the arm
        hub.play(public_id, attempt, time.monotonic() - attempt.grasp_time - 0.1, 1.0)
        ws.collect(lambda ms: visibility(ms, BIN_HIGHLIGHT)[-1] is True)
        start = len(ws.seen)
        time.sleep(1.0)
        with pytest.raises(AssertionError):
            ws.collect(lambda ms: False, timeout=0.3)
        moving = [m for m in ws.seen[start:] if m["type"] == "SetOrientationMessage" and m["name"] == "/robot/j2"]
        assert len(moving) >= 5, "the arm moved meanwhile"
        assert attempt.state_at(attempt.grasp_time + 1.5).item.mode == ItemMode.GRASPED
        assert visibility(ws.seen, BIN_HIGHLIGHT) == [False, True]  # sent when the mode changed, not per frame
        for name in (TARGET_MARKER, TARGET_HALO, TARGET_SLOT):
            assert visibility(ws.seen, name)[-1] is False
        # deposited: the highlight goes
        hold(attempt.duration)
        assert attempt.state_at(attempt.duration).item.mode == ItemMode.IN_BIN
        ws.collect(lambda ms: visibility(ms, BIN_HIGHLIGHT)[-1] is False)
        assert visibility(ws.seen, BIN_HIGHLIGHT) == [False, True, False]
        assert visibility(ws.seen, TARGET_MARKER)[-1] is False


def test_the_arrow_gives_way_to_the_gripper_sooner_in_the_end_effector_view():
    """Over the item, the arrow would fill the end-effector camera's view: there it hides farther away."""
    scene = build_scene("low", 3, target_slot=1)  # the bottom shelf: the gripper can rise well above the arrow
    view = LiveView(scene)
    grasp = scene.target.grasp_point()
    arrow_top = arrow_axis(scene)[3]
    resting = teleop_start_state(scene)
    palm_above_arrow = 0.17  # m: between the two views' radii
    tcp = (grasp[0], grasp[1], arrow_top + palm_above_arrow - 0.06)  # the palm is 0.06 m up the tool from the TCP
    above = dataclasses.replace(resting, joints=tuple(float(q) for q in solve_ik(scene.park, tcp)))
    assert view.update(above)[0] == []  # world view: the arrow still shows where to go down
    assert view.poses["/robot/palm"][0][2] == pytest.approx(arrow_top + palm_above_arrow, abs=1e-3)
    assert view.shown[TARGET_MARKER]
    changes = view.set_view("end_effector")
    # the arrow goes, the outline stays
    assert visibility(changes, TARGET_MARKER) == [False] and view.shown[TARGET_HALO]
    assert visibility(view.set_view("local"), TARGET_MARKER) == [True]
    down = dataclasses.replace(resting, joints=tuple(float(q) for q in solve_ik(scene.park, (grasp[0], grasp[1],
                                                                                             grasp[2] + 0.1))))
    assert visibility(view.update(down)[0], TARGET_MARKER) == [False]  # down at the item: gone in every view
    assert visibility(view.update(resting)[0], TARGET_MARKER) == [True]
