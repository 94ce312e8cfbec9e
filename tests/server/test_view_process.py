"""The 3D view in a process of its own (``server.viewer.remote``, ``server.viewer.process``), as served: uvicorn in
front, a viewer socket on the server's own origin handed to the view process, which plays the server's attempts,
shows its teleoperations, and tells it whose views hold which scene.

A simulated viser client, as in ``test_viewer.py``; a real uvicorn server (``server.harness.live``).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import msgspec
import pytest
import websockets
from sqlalchemy import text
from websockets.sync.client import connect

from experiment.flow import PracticeStep
from server.harness.live import free_port, live_server, start_server
from server.services.sessions import participant_by_token
from server.viewer.link import hand_off, socket_pairs, take_handoffs
from server.viewer.manager import ViewerManager
from server.viewer.remote import RemoteViewers
from server.viewer.scene import STAMP_PREFIX
from tests.server.factories import join
from tests.server.test_viewer import CONFIG, HELLO, SUBPROTOCOL, decode

#: A short decision window: the attempt plays soon after the trial starts.
QUICK = CONFIG.model_copy(update={"timing": CONFIG.timing.model_copy(update={"decision_window_s": 1.0})})

POSE_MESSAGES = ("SetPositionMessage", "SetOrientationMessage")


def view_processes(parent: int) -> list[int]:
    """The view processes ``parent`` started (running, not zombies)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == parent and fields[0] != "Z" and b"server.viewer.process" in cmdline:
            found.append(int(stat.parent.name))
    return found


def wait_until(check, timeout: float = 20.0, what: str = "") -> Any:
    deadline = time.monotonic() + timeout
    while not (value := check()):
        assert time.monotonic() < deadline, f"gave up waiting for {what or check}"
        time.sleep(0.05)
    return value


class Viewer:
    """viser's client on a real socket: every message received, with when its frame arrived."""

    def __init__(self, url: str, token: str):
        self.ws = connect(f"{url.replace('http', 'ws', 1)}/viewer/{token}", subprotocols=[SUBPROTOCOL],
                          max_size=None, max_queue=None, open_timeout=10)  # (a full queue stalls close())
        assert self.ws.subprotocol == SUBPROTOCOL
        self.ws.send(msgspec.msgpack.encode(HELLO))
        self.seen: list[tuple[float, dict[str, Any]]] = []

    def collect(self, until, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not until([m for _, m in self.seen]):
            left = deadline - time.monotonic()
            assert left > 0, f"gave up after {timeout} s ({len(self.seen)} messages)"
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                continue
            now = time.monotonic()
            self.seen += [(now, m) for m in decode(frame)]

    def replayed(self) -> None:
        self.collect(lambda ms: any(m["type"] == "ReplayDoneMessage" for m in ms))

    def await_stamp(self, stamp: str) -> str:
        """Receive until the client holds the scene node of ``stamp`` (the page's proof of the scene it draws)."""
        name = f"{STAMP_PREFIX}{stamp}"
        self.collect(lambda ms: any(m["type"] == "FrameMessage" and m.get("name") == name for m in ms))
        return stamp

    def close(self) -> None:
        self.ws.close()


@contextmanager
def served(database_url: str) -> Iterator[tuple[Any, httpx.Client]]:
    with live_server(database_url, planner_processes=0) as live, httpx.Client(base_url=live.url, timeout=10) as http:
        response = live.admin("POST", "/api/admin/studies",
                              json={"status": "open", "slug": "s1", "config": QUICK.model_dump(mode="json")})
        assert response.status_code == 201, response.text
        yield live, http


def at_practice_trial(live, http: httpx.Client, index: int) -> str:
    token = join(http)["token"]
    assert http.post(f"/api/p/{token}/consent", json={"agree": True}).status_code == 200
    with live.app.state.services.sessionmaker.begin() as session:
        participant_by_token(session, token).step = PracticeStep(index=index)
    return token


# --- the link ---------------------------------------------------------------------------------------------------

def test_a_connection_handed_off_is_the_same_connection_with_its_bytes():
    messages, (ours, theirs) = socket_pairs()
    for end in messages:
        end.close()
    browser, server_end = socket.socketpair()
    ours.setblocking(False)
    theirs.setblocking(False)
    assert take_handoffs(theirs) == []  # nothing yet
    assert hand_off(ours, b"GET /viewer/x HTTP/1.1\r\n\r\n", server_end.fileno())
    server_end.close()  # the sender's descriptor: the connection stays open in the receiver
    [(received, request)] = take_handoffs(theirs)
    assert request == b"GET /viewer/x HTTP/1.1\r\n\r\n"
    received.sendall(b"101")
    assert browser.recv(3) == b"101"
    received.close()
    ours.close()
    assert take_handoffs(theirs) is None  # the server has gone
    browser.close()
    theirs.close()


def test_the_view_processs_reads_run_in_a_worker_thread_and_its_shutdown_waits_for_them(database_url):
    """The view process's units only read; they run off its event loop, which keeps sending frames meanwhile."""
    import asyncio
    import threading

    from server.settings import Settings
    from server.viewer.process import create_view_app

    app = create_view_app(Settings(database_url=database_url))
    manager = app.state.services.viewers

    async def read() -> tuple[int, int, int]:
        loop_thread = threading.get_ident()
        unit_thread, studies = await manager._run_unit(
            lambda session: (threading.get_ident(), session.execute(text("SELECT count(*) FROM study")).scalar()))
        await app.state.services.database.settle()
        return loop_thread, unit_thread, studies

    loop_thread, unit_thread, studies = asyncio.run(read())
    app.state.services.engine.dispose()
    assert unit_thread != loop_thread and studies == 0


# --- served ------------------------------------------------------------------------------------------------------

def test_the_view_process_serves_the_viewer_and_the_server_knows_what_it_holds(database_url):
    with served(database_url) as (live, http):
        views = live.app.state.services.viewers
        assert isinstance(views, RemoteViewers)
        [child] = wait_until(lambda: view_processes(os.getpid()), what="the view process")
        token = at_practice_trial(live, http, 1)  # high complexity, the robot acts
        assert http.get(f"/viewer/{token}/").status_code == 200  # viser's page from the server itself
        viewer = Viewer(live.url, token)
        viewer.replayed()
        wait_until(lambda: views.viewer_count() == 1, what="the viewer counted by the server")

        # The trial starts: its scene is shown at once, and the start's answer says the view holds it.
        started = http.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": 2})
        assert started.status_code == 200, started.text
        assert started.json()["trial"]["scene_in_viewer"] is True
        stamp = viewer.await_stamp(started.json()["trial"]["scene_stamp"])  # through the view process
        shown = http.post(f"/api/p/{token}/trials/shown", json={"practice": True, "block": 0, "trial": 2,
                                                                  "view": "3d", "scene_stamp": stamp})
        assert shown.status_code == 200 and shown.json()["trial"]["stage"] == "decision", shown.text

        # A camera preset goes to the viewer through the view process.
        camera = http.post(f"/api/p/{token}/camera", json={"view": "local"})
        assert camera.status_code == 200 and camera.json()["viewers"] == 1, camera.text
        viewer.collect(lambda ms: any(m["type"] == "SetCameraFovMessage" for m in ms))

        # The decision window passes without intervening: the server plays the attempt, and so does the view.
        before = len(viewer.seen)
        wait_until(lambda: http.get(f"/api/p/{token}/state").json()["trial"]["stage"] != "decision", what="the attempt")
        viewer.collect(lambda ms: sum(m["type"] == "SetPositionMessage" and m["name"] == "/robot/j2"
                                      for m in ms[before:]) >= 45, timeout=20)
        moves = [t for t, m in viewer.seen[before:] if m["type"] == "SetPositionMessage" and m["name"] == "/robot/j2"]
        assert (len(moves) - 1) / (moves[-1] - moves[0]) > 15  # frames at the world loop's pace, not the poll's

        # The load report counts the view process's views and ticks.
        load = live.admin("GET", "/api/admin/server/load")
        assert load.status_code == 200
        assert views.ticks_seen > 0
        viewer.close()
        wait_until(lambda: views.viewer_count() == 0, what="the viewer gone")

        # A teleoperated arm moves in the view: the server sends the view process its world each tick.
        teleoperated = at_practice_trial(live, http, 1)
        steering = Viewer(live.url, teleoperated)
        steering.replayed()
        trial = {"practice": True, "block": 0, "trial": 2}
        started = http.post(f"/api/p/{teleoperated}/trials/start", json=trial).json()["trial"]
        assert started["scene_in_viewer"]
        stamp = steering.await_stamp(started["scene_stamp"])
        http.post(f"/api/p/{teleoperated}/trials/shown", json=trial | {"view": "3d", "scene_stamp": stamp})
        intervened = http.post(f"/api/p/{teleoperated}/trials/intervene", json=trial)
        assert intervened.status_code == 200 and intervened.json()["trial"]["stage"] == "teleop", intervened.text
        before = len(steering.seen)
        with connect(f"{live.url.replace('http', 'ws', 1)}/api/p/{teleoperated}/teleop", max_queue=None,
                     open_timeout=10) as teleop:
            assert json.loads(teleop.recv(timeout=10))["type"] == "hello"
            teleop.send(json.dumps({"type": "input", "seq": 1, "ee_velocity": [0.0, 0.0, 0.05]}))
            for seq in range(2, 10):  # held for about 1.6 s
                time.sleep(0.2)
                teleop.send(json.dumps({"type": "keepalive", "seq": seq}))
            steering.collect(lambda ms: sum(m["type"] == "SetPositionMessage" and m["name"] == "/robot/palm"
                                            for m in ms[before:]) >= 20, timeout=10)
        palm = [t for t, m in steering.seen[before:] if m["type"] == "SetPositionMessage"
                and m["name"] == "/robot/palm"]
        assert (len(palm) - 1) / (palm[-1] - palm[0]) > 15
        steering.close()

        # A view process that dies is replaced; a viewer that reconnects is served again.
        os.kill(child, signal.SIGKILL)
        [replacement] = wait_until(lambda: [p for p in view_processes(os.getpid()) if p != child], timeout=30,
                                   what="a new view process")
        assert replacement != child and views.restarts >= 1
        again = wait_until(lambda: _connects(live.url, token), timeout=30, what="a viewer served again")
        again.replayed()
        again.close()
    assert wait_until(lambda: not view_processes(os.getpid()), what="the view process to end with the server")


def _connects(url: str, token: str) -> Viewer | None:
    try:
        return Viewer(url, token)
    except (OSError, websockets.InvalidHandshake, websockets.ConnectionClosed, TimeoutError):
        return None


def test_the_view_process_ends_with_a_killed_server(tmp_path, sqlite_template):
    database = tmp_path / "trustlab.db"
    database.write_bytes(sqlite_template.read_bytes())
    port = free_port()
    with open(tmp_path / "serve.log", "w+") as log:
        server, _token = start_server(f"sqlite:///{database}", port, log)
        try:
            [child] = wait_until(lambda: view_processes(server.pid), what="the view process")
            server.kill()
            server.wait()
        finally:
            if server.poll() is None:
                server.kill()
        wait_until(lambda: not Path(f"/proc/{child}").exists() or "Z" in Path(f"/proc/{child}/stat").read_text()
                   .rsplit(")", 1)[1].split()[0], timeout=15, what="the view process to end")


def test_without_the_view_process_the_server_serves_the_views_itself(database_url):
    with live_server(database_url, planner_processes=0, view_process=False) as live:
        assert isinstance(live.app.state.services.viewers, ViewerManager)
        assert not view_processes(os.getpid())


def test_other_websockets_stay_with_the_server(database_url):
    with live_server(database_url, planner_processes=0) as live:
        with pytest.raises(websockets.ConnectionClosed) as closed:
            with connect(live.url.replace("http", "ws", 1) + "/api/p/" + "x" * 32 + "/teleop", open_timeout=10) as ws:
                ws.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 4404  # the server's teleoperation route
