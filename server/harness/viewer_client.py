"""A headless client of a participant's 3D view, as viser's browser client drives it (for the benchmarks).

``ViewerClient`` connects through the server's relay (``WS /viewer/{token}``,
subprotocol ``viser-v<viser version>``), sends the ``ViewerCameraMessage``
hello the browser sends on connecting, and decodes every frame as the
browser's worker does (``[u64 raw length][u64 packed length][zstd(msgpack
{"messages": [...]})]``). It records when each frame that moves the robot
arrived (an *update*: what the browser draws the robot from), the bytes, and
when the scene replay ended. It reconnects when the server restarts the
session's viewer (close 1012), as the page does, and stops when the session is
over (4404).

``ViewerPool`` runs the clients of many sessions on one asyncio loop in one
thread, so that a process of thread-per-participant bots (``server.harness.bots``)
opens a view per bot for little CPU, and measures that thread's CPU.
``BotView`` is one bot's view (``server.harness.bots.SceneDisplay``): it opens the
client when the bot joins, tells the bot which scene the view has drawn (a pass of
the client's loop, see ``drawn_stamp``) and records when the robot moved.
``motion_stats`` gives a view's update rate and longest gap while the robot
moved, by arrival and by the server's stamps: a gap between arrivals adds this
process's own delays (its threads share the server's cores, niced below it) to
the server's; a gap between the stamps viser's wire format carries
(``timestampSec``, taken as the server packs the frame for the socket) is the
server's alone. Used by ``bench_load.py`` (a view per bot) and ``bench_scenes.py``.
"""

from __future__ import annotations

import asyncio
import bisect
import concurrent.futures
import itertools
import os
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import websockets
import zstandard
from websockets.typing import Subprotocol

from server.routes.viewer import CLOSE_RESTART, CLOSE_UNKNOWN_TOKEN, SUBPROTOCOL
from server.viewer.scene import STAMP_PREFIX

#: What viser's browser client sends first: its camera (the page's default view, a 1000 x 600 canvas).
HELLO = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [-1.0, -2.4, 1.9], "fov": 0.87,
         "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 1000, "look_at": [1.25, 0.0, 0.6],
         "up_direction": [0.0, 0.0, 1.0]}
#: Messages that move a scene node; a frame holding one for a robot node is an update of the robot.
POSE_MESSAGES = frozenset({"SetPositionMessage", "SetOrientationMessage"})
ROBOT_PREFIX = "/robot/"
#: Wait before reconnecting after the server restarted the session's viewer (the page waits about as long).
RECONNECT_S = 0.2
TICKS_PER_S = os.sysconf("SC_CLK_TCK")
#: Loop passes of a barrier: one reads the socket (the protocol parses the frame), the next wakes the client that
#: decodes it; one more for a frame that arrived in pieces.
BARRIER_PASSES = 3


def decode_frame(frame: bytes, unzstd: zstandard.ZstdDecompressor) -> dict:
    """One websocket frame: its viser ``messages`` and the server's ``timestampSec``."""
    raw, packed = struct.unpack_from("<QQ", frame)
    return msgspec.msgpack.decode(unzstd.decompress(frame[16:16 + packed], max_output_size=raw))


@dataclass
class ViewerClient:
    """One browser's 3D view of one session (see the module's docstring)."""

    ws_base: str  # ws://host:port
    token: str
    updates: list[float] = field(default_factory=list)  # time.monotonic() of each frame that moved the robot
    stamps: list[float] = field(default_factory=list)  # the server's timestampSec of each of those frames
    frame_bytes: list[tuple[float, int]] = field(default_factory=list)
    frames: int = 0
    replayed: threading.Event = field(default_factory=threading.Event)  # the scene's replay has arrived
    reconnects: int = 0
    scene_stamp: str | None = None  # of the scene held: its stamp node (server.viewer.scene.STAMP_PREFIX)
    close_code: int | None = None
    error: str | None = None

    async def run(self) -> None:
        """Connect and decode until the session is over, the connection fails, or the task is cancelled."""
        unzstd = zstandard.ZstdDecompressor()
        while True:
            try:
                async with websockets.connect(f"{self.ws_base}/viewer/{self.token}",
                                              subprotocols=[Subprotocol(SUBPROTOCOL)],
                                              max_size=None, compression=None, open_timeout=30) as ws:
                    await ws.send(msgspec.msgpack.encode(HELLO))
                    async for frame in ws:
                        self._receive(frame, unzstd)
            except websockets.ConnectionClosed as closed:
                self.close_code = closed.rcvd.code if closed.rcvd else None
            except (OSError, TimeoutError, websockets.InvalidHandshake) as exc:
                self.error = f"{type(exc).__name__}: {exc}"
                return
            else:
                self.close_code = ws.close_code
            if self.close_code != CLOSE_RESTART:
                if self.close_code not in (1000, 1001, CLOSE_UNKNOWN_TOKEN):
                    self.error = f"closed {self.close_code}"
                return
            self.reconnects += 1
            self.replayed.clear()
            await asyncio.sleep(RECONNECT_S)

    def _receive(self, frame: bytes | str, unzstd: zstandard.ZstdDecompressor) -> None:
        if isinstance(frame, str):
            return  # viser sends binary frames only
        now = time.monotonic()
        self.frames += 1
        self.frame_bytes.append((now, len(frame)))
        moved = False
        payload = decode_frame(frame, unzstd)
        for message in payload["messages"]:
            kind = message["type"]
            if kind in POSE_MESSAGES and message["name"].startswith(ROBOT_PREFIX):
                moved = True
            elif kind == "ReplayDoneMessage":
                self.replayed.set()
            elif kind == "FrameMessage" and message["name"].startswith(STAMP_PREFIX):
                self.scene_stamp = message["name"][len(STAMP_PREFIX):]
            elif kind == "RemoveSceneNodeMessage" and message["name"].startswith(STAMP_PREFIX):
                self.scene_stamp = None
        if moved:
            self.updates.append(now)
            self.stamps.append(float(payload.get("timestampSec", now)))


class ViewerPool:
    """Viewer clients on one asyncio loop in a thread of this process (``open`` and ``close`` from any thread)."""

    def __init__(self, base_url: str):
        self.ws_base = "ws" + base_url.rstrip("/")[4:]  # http://h:p -> ws://h:p
        self.loop = asyncio.new_event_loop()
        self._started = threading.Event()
        self._native_id = 0
        self.thread = threading.Thread(target=self._run, name="viewer-clients", daemon=True)
        self.thread.start()
        self._started.wait()

    def _run(self) -> None:
        self._native_id = threading.get_native_id()
        asyncio.set_event_loop(self.loop)
        self.loop.call_soon(self._started.set)
        self.loop.run_forever()

    def open(self, token: str) -> tuple[ViewerClient, concurrent.futures.Future]:
        client = ViewerClient(self.ws_base, token)
        return client, asyncio.run_coroutine_threadsafe(client.run(), self.loop)

    def barrier(self, timeout: float = 10.0) -> None:
        """Return once the loop has gone round a few times after this call, each time reading its sockets: a frame
        that had reached a client's socket by the call has been read, then decoded (``BARRIER_PASSES``)."""
        async def passes() -> None:
            for _ in range(BARRIER_PASSES):
                await asyncio.sleep(0)
        asyncio.run_coroutine_threadsafe(passes(), self.loop).result(timeout)

    def cpu_seconds(self) -> float:
        """CPU time of the clients' thread so far (from /proc: user + system)."""
        fields = Path(f"/proc/self/task/{self._native_id}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / TICKS_PER_S

    def stop(self) -> None:
        async def cancel_all() -> None:
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        asyncio.run_coroutine_threadsafe(cancel_all(), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(30)
        self.loop.close()


class BotView:
    """A bot's 3D view (``server.harness.bots.SceneDisplay``): a ``ViewerClient`` in a ``ViewerPool``, and the times the
    bot saw its robot move (an autonomous attempt, a teleoperation)."""

    def __init__(self, pool: ViewerPool):
        self.pool = pool
        self.client: ViewerClient | None = None
        self._future: concurrent.futures.Future | None = None
        self.motion: list[tuple[str, float, float]] = []  # (kind, start, end), time.monotonic()

    def open(self, token: str) -> None:
        self.client, self._future = self.pool.open(token)

    def close(self) -> None:
        if self._future is not None:
            self._future.cancel()

    def drawn_stamp(self) -> str | None:
        """The stamp of the scene the view shows now: the client's loop has decoded every frame that had reached it
        at this call (``ViewerPool.barrier``), so a frame the browser drew after this call would be drawn from the
        scene whose stamp node the client holds."""
        if self.client is None or not self.client.replayed.is_set():
            return None
        self.pool.barrier()
        return self.client.scene_stamp

    def moving(self, kind: str, start: float, end: float) -> None:
        self.motion.append((kind, start, end))

    def stats(self) -> dict:
        """Update rate and gaps while the robot moved (all motion, each kind alone), and the client's fate."""
        assert self.client is not None
        spans = {kind: [(s, e) for k, s, e in self.motion if k == kind] for kind in ("attempt", "teleop")}
        updates, stamps = self.client.updates, self.client.stamps
        return {"all": motion_stats(updates, [(s, e) for _, s, e in self.motion], stamps),
                **{kind: motion_stats(updates, kind_spans, stamps) for kind, kind_spans in spans.items()},
                "frames": self.client.frames, "bytes": sum(n for _, n in self.client.frame_bytes),
                "reconnects": self.client.reconnects, "error": self.client.error}


def motion_stats(updates: list[float], spans: list[tuple[float, float]], stamps: list[float] | None = None
                 ) -> dict | None:
    """Updates per second within ``spans`` (when the robot moved) and the gaps between consecutive updates
    inside one span (seconds), by arrival; with ``stamps`` (the server's, one per update) the longest gap
    between the same updates' stamps too (``max_stamp_gap_s``). None without spans.

    Two rates: ``rate`` over the whole spans, and ``moving_rate`` from each span's first update to its last
    (updates after the first per second between them): a failed attempt ends standing still for 0.3-0.6 s
    (at the demo's 2x) and the server sends only what moved, so a viewer watching failures gets a lower
    ``rate`` from a robot that did not move. A delay of the view inside the motion lowers both."""
    seconds = sum(end - start for start, end in spans)
    if seconds <= 0:
        return None
    count, gaps, stamp_gaps = 0, [], []
    for start, end in spans:
        first, last = bisect.bisect_left(updates, start), bisect.bisect_left(updates, end)
        inside = updates[first:last]
        count += len(inside)
        gaps += [b - a for a, b in itertools.pairwise(inside)]
        if stamps is not None:
            sent = stamps[first:last]
            stamp_gaps += [b - a for a, b in itertools.pairwise(sent)]
    return {"rate": count / seconds, "moving_rate": len(gaps) / sum(gaps) if gaps else 0.0,
            "max_gap_s": max(gaps, default=seconds), "gaps": gaps, "seconds": seconds,
            "max_stamp_gap_s": max(stamp_gaps, default=seconds) if stamps is not None else None}
