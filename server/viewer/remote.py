"""The 3D view in a process of its own (``Settings.view_process``): the server's side.

Why: every participant's page keeps the 3D view open, and drawing a moving robot for each took about half of the
server's event loop at 100 participants, while requests, decisions and teleoperation waited behind it. In a process
of its own the view runs on another core and holds no lock the server's loop needs (docs/architecture.md, "The 3D
view").

How:

- The browser still connects to the server's own origin (``WS /viewer/{token}``): uvicorn hands the upgrade to
  ``ViewerHandoffProtocol``, which passes the connection itself (its file descriptor) and the request's bytes to
  the view process, which answers the handshake and serves it (``server.viewer.process``). Other websockets (the
  teleoperation socket) stay here.
- The view process reads the database itself (read only) for what each session shows, as the in-process viewer
  did; the server tells it what only the server knows: each attempt played back (once, as it starts), the worlds of
  watched teleoperations (each tick), trials just started (so their scene shows at once), camera presets.
- It tells the server what the participants' requests need: whose views hold which scene (a 3D report of the
  scene on screen counts only then), viewers per session, and its ticks seen and skipped (the load report).

If the view process ends, the server starts another; the pages' viewers reconnect (viser's client does).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import signal
import socket
import subprocess
import sys
import time

from uvicorn.protocols.utils import is_ssl
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from server.app_services import Services
from server.settings import Settings
from server.viewer.link import MessageLink, hand_off, socket_pairs
from server.viewer.manager import SessionViews, ViewStatus, _on_loop, cancel_and_wait
from server.viewer.targets import Target
from server.world.playback import LiveWorld, Playback

log = logging.getLogger("trustlab.viewer")

#: The environment variables that hand the view process its settings and its ends of the link.
SETTINGS_ENV = "TRUSTLAB_VIEW_PROCESS_SETTINGS"
LINK_ENV = "TRUSTLAB_VIEW_PROCESS_LINK"
#: How long a trial's start waits for the view process to show its scene (then the page reports again later).
STARTED_REPLY_S = 0.5
#: After the view process ended, the next one starts this much later at the earliest (s).
RESTART_DELAY_S = 1.0
#: A view process that does not end this long after its link closed is killed (s). It ignores SIGINT and SIGTERM
#: (``server.viewer.process.main``): it ends when its server closes the link, or when its server is gone.
STOP_TIMEOUT_S = 5.0

class ViewerHandoffProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websocket protocol, except that a ``/viewer/`` connection goes to the view process."""

    _decided = False

    def data_received(self, data: bytes) -> None:
        if not self._decided:
            self._decided = True
            if self._hand_off(data):
                return
        super().data_received(data)

    def _hand_off(self, request: bytes) -> bool:
        services = getattr(getattr(self.config.app, "state", None), "services", None)
        views = getattr(services, "viewers", None)  # this server's app's views
        path = request.split(b" ", 2)[1] if request.count(b" ") >= 2 else b""
        if not isinstance(views, RemoteViewers) or not path.startswith(b"/viewer/") or is_ssl(self.transport):
            return False
        sock = self.transport.get_extra_info("socket")
        if sock is None or not views.hand_off(request, sock.fileno()):
            return False
        # The view process has its own descriptor of the connection: closing this one leaves it open there.
        self.connections.discard(self)
        self.transport.set_protocol(_Gone())
        self.transport.close()
        return True


class _Gone(asyncio.Protocol):
    """A handed-off connection's end in this process, closing."""


class RemoteViewers(SessionViews):
    """The sessions' 3D views, served by a view process that this object starts, feeds and restarts."""

    def __init__(self, services: Services):
        super().__init__(services.hub, services.database.run, services.runtimes)
        self.settings: Settings = services.settings
        self.status = ViewStatus(frozenset(), {}, {}, 0, 0)
        self._link: MessageLink | None = None
        self._handoffs: socket.socket | None = None  # this end of the hand-off socket pair
        self._process: subprocess.Popen | None = None
        self._task: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._replies: dict[int, asyncio.Future] = {}
        self._request_ids = itertools.count(1)
        self._sent_worlds = False
        self._closing = False
        self._ended = "exit status unknown"  # how the last view process ended, for the log
        self.restarts = 0

    # -- SessionViews ------------------------------------------------------------------------------------
    def start(self) -> None:
        self._closing = False
        self._loop = asyncio.get_running_loop()
        self._task = asyncio.create_task(self._run_forever(), name="view-process")
        self.hub.add_tick_listener(self._on_tick, self._wanted)
        self.hub.playbacks.listener = self._on_playback

    async def close(self) -> None:
        """Stop the view process for good (the server is shutting down): no other is started."""
        self._closing = True
        self.hub.remove_tick_listener(self._on_tick)
        self.hub.playbacks.listener = None
        await cancel_and_wait(self._task)
        await asyncio.to_thread(self._stop_process)
        if self._task is not None:
            log.warning("3D view process stopped (the server is shutting down)")
            self._task = None

    def viewer_count(self) -> int:
        return sum(self.status.viewers.values())

    @property
    def ticks_seen(self) -> int:  # type: ignore[override]  # the view process's count, read-only here
        return self.status.ticks_seen

    @property
    def ticks_skipped(self) -> int:  # type: ignore[override]  # the view process's count, read-only here
        return self.status.ticks_skipped

    async def show_started(self, participant_id: int, target: Target) -> bool:
        if self._link is None or target.scene is None:
            return False
        request = next(self._request_ids)
        reply = self._replies[request] = asyncio.get_running_loop().create_future()
        try:
            if not self._link.send(("started", request, participant_id, target)):
                return False
            async with asyncio.timeout(STARTED_REPLY_S):
                return bool(await reply)
        except TimeoutError:
            return False
        finally:
            self._replies.pop(request, None)

    def holds_scene(self, participant_id: int, seed: object, complexity: str) -> bool:
        return self.status.holds.get(participant_id) == (seed, complexity)

    def set_view(self, participant_id: int, view: str) -> int:
        if self._link is not None:
            self._link.send(("view", participant_id, view))
        return self.status.viewers.get(participant_id, 0)

    # -- the connection hand-off (uvicorn's protocol, on the event loop) ----------------------------------
    def hand_off(self, request: bytes, fd: int) -> bool:
        return self._handoffs is not None and hand_off(self._handoffs, request, fd)

    # -- what the server tells the view process ----------------------------------------------------------
    def _wanted(self) -> set[str]:
        """The hub computes only the worlds of watched teleoperations for it (attempts are played there)."""
        return self.hub.arms.teleoperated(self.status.watched)

    def _on_tick(self, worlds: dict[str, LiveWorld]) -> None:
        if self._link is None:
            return
        teleops = {key: world for key, world in worlds.items() if key in self.status.watched}
        if teleops or self._sent_worlds:  # (one empty message after the last: the view process forgets them)
            self._link.send(("worlds", teleops), droppable=True)
            self._sent_worlds = bool(teleops)

    def _on_playback(self, participant_key: str, playback: Playback | None) -> None:
        loop = self._loop
        if loop is None:
            return
        if _on_loop(loop):
            self._send_playback(participant_key, playback)
        else:  # a unit of work in a worker thread (PostgreSQL) started it
            loop.call_soon_threadsafe(self._send_playback, participant_key, playback)

    def _send_playback(self, participant_key: str, playback: Playback | None) -> None:
        if self._link is not None:
            self._link.send(("playback", participant_key, playback))

    # -- the view process --------------------------------------------------------------------------------
    async def _run_forever(self) -> None:
        """Serve through a view process; when one ends while the server runs, start another (``close`` cancels this:
        a server shutting down says the process stopped and starts none)."""
        while not self._closing:
            started = time.monotonic()
            try:
                await self._serve_one()
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("3D view process link failed")
            if self._closing:
                return
            self.status = ViewStatus(frozenset(), {}, {}, self.status.ticks_seen, self.status.ticks_skipped)
            await asyncio.sleep(max(0.0, RESTART_DELAY_S - (time.monotonic() - started)))
            if self._closing:  # (close() cancels this task; a shutdown that began meanwhile starts nothing)
                return
            self.restarts += 1
            log.warning("3D view process ended (%s); starting another (the pages' views reconnect)", self._ended)

    async def _serve_one(self) -> None:
        (messages, theirs), (handoffs, their_handoffs) = socket_pairs()
        try:
            handoffs.setblocking(False)
            self._process = await asyncio.to_thread(self._spawn, theirs.fileno(), their_handoffs.fileno())
        finally:
            theirs.close()
            their_handoffs.close()
        link = await MessageLink.over(messages)
        self._link, self._handoffs = link, handoffs
        try:
            while True:
                message = await link.receive()
                kind = message[0]
                if kind == "status":
                    self.status = message[1]
                elif kind == "reply" and (future := self._replies.get(message[1])) is not None and not future.done():
                    future.set_result(message[2])
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self._link = self._handoffs = None
            link.close()
            handoffs.close()
            await asyncio.to_thread(self._stop_process)

    def _spawn(self, messages_fd: int, handoffs_fd: int) -> subprocess.Popen:
        env = os.environ | {SETTINGS_ENV: self.settings.model_dump_json(), LINK_ENV: f"{messages_fd},{handoffs_fd}"}
        # A process group of its own: a Ctrl-C in the terminal (sent to the foreground group) is the server's to
        # handle; the server ends the view process when it shuts down.
        return subprocess.Popen([sys.executable, "-m", "server.viewer.process"], env=env,
                                pass_fds=(messages_fd, handoffs_fd), process_group=0)

    def _stop_process(self) -> None:
        """Wait for the view process to end after its link closed (it ignores SIGTERM), killing it if it does not."""
        process, self._process = self._process, None
        if process is None:
            return
        try:
            process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        code = process.returncode
        self._ended = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit status {code}"


__all__ = ["RemoteViewers", "ViewerHandoffProtocol"]
