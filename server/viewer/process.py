"""The 3D view process: ``python -m server.viewer.process``, started by its server (``server.viewer.remote``).

It serves the participants' 3D views exactly as a server process does in itself (``server.viewer.manager``: each
session's scene, its DB poll, the frames of what moves, the viewer sockets), on connections its server
hands it (``server.viewer.link``), with a world hub of its own that plays back the attempts its server plays and
shows the teleoperations its server sends each tick. It only reads the database. It ends when its server does
(the link closes; a watch thread covers a server killed with -9), and only then: it ignores SIGINT and SIGTERM.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import os
import signal
import socket
from collections.abc import Callable
from typing import TypeVar

import uvicorn
from fastapi import FastAPI
from sqlalchemy.orm import Session
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from uvicorn.server import ServerState

from server.app_services import JoinLimits, Services, services_of
from server.db.engine import make_engine, make_sessionmaker
from server.db.units import Database
from server.faults import FaultLog
from server.http_headers import WorkerHeader
from server.launch import WS_MAX_BYTES, tune_process
from server.loadmeter import LoadHistory
from server.logs import redact_server_logs
from server.ratelimit import RateLimiter
from server.routes import viewer as viewer_routes
from server.services.events import EventBudget
from server.services.fits import FitWorker
from server.services.studies import RuntimeCache
from server.services.teleop_log import TeleopLogWriter
from server.settings import Settings
from server.viewer.link import MessageLink, take_handoffs
from server.viewer.manager import ViewerManager, cancel_and_wait
from server.viewer.remote import LINK_ENV, SETTINGS_ENV
from server.world.hub import WorldHub
from server.world.processes import exit_with_parent

log = logging.getLogger("trustlab.viewer")
T = TypeVar("T")

#: The view process's niceness: when the machine's cores are short, the server's requests, decisions and
#: teleoperation get them first and the views skip frames (issue 15's order of priority).
NICENESS = 5
#: How long after an attempt begins its playback may still be on its way from the server (s): a link message, so a
#: fraction of a second even when this process is short of CPU; the poll after it plays back one that never came
#: (another worker of a group started it).
ANNOUNCED_PLAYBACK_S = 2.0
#: How often the view process reads every session's trial (s; a server's own views: ``manager.POLL_S``). Its server
#: tells it each trial's start and attempt at once; the poll catches the rest (the next trial's scene between trials,
#: finished sessions). 2 s against 1 s: less of its loop's time in long iterations, no worse view (docs/results.jsonl).
POLL_S = 2.0


def create_view_app(settings: Settings) -> FastAPI:
    """The view process's app: the viewer's routes on a read-only database, and a world hub of its own."""
    app = FastAPI(title="trustlab 3D view")
    engine = make_engine(settings.database_url, read_only=True)
    factory = make_sessionmaker(engine)
    database = Database(factory, None)  # it never writes
    runtimes, faults = RuntimeCache(), FaultLog()
    hub = WorldHub(settings, faults)
    manager = ViewerManager(hub, functools.partial(read_in_a_worker_thread, database), runtimes, poll_s=POLL_S)
    # The server sends each attempt's playback as it begins; a poll that reads the attempt first (the message is on
    # its way) would plan it again here: a long callback for the views, measured at 100 participants.
    manager.announced_playback_s = ANNOUNCED_PLAYBACK_S
    # The server's parts this process does not use are made but never started (no thread, no task).
    app.state.services = Services(
        settings=settings, engine=engine, sessionmaker=factory, database=database, runtimes=runtimes, faults=faults,
        hub=hub, viewers=manager, teleop_log=TeleopLogWriter(database, faults), fits=FitWorker(database),
        load_history=LoadHistory(), join_limits=JoinLimits(RateLimiter.minutely(1), RateLimiter.minutely(1)),
        event_budget=EventBudget(settings))
    app.include_router(viewer_routes.router)
    if settings.worker_index is not None:  # a worker's view process names the worker, as the worker does
        app.add_middleware(WorkerHeader, index=settings.worker_index)
    return app


async def read_in_a_worker_thread(database: Database, work: Callable[[Session], T]) -> T:
    """The view process's units of work (reads only) run in a worker thread, not on the event loop as the server's do.

    The server runs its units on its loop, in turns, because SQLite takes one writer at a time; these only read,
    under WAL, beside the server's writes. On the loop, a poll's read of 20 sessions was this process's longest
    callback (70-130 ms at 100 participants, loop watch): every frame waited for it. In a thread the loop keeps
    sending frames between the read's steps (the interpreter lock changes hands every millisecond at most)."""
    result, _ = await database.in_thread(database.run_here, work)
    return result


class ViewProcess:
    """The view process's event loop side: the link to its server, the handed-off connections, the views."""

    def __init__(self, app: FastAPI, link: MessageLink, handoffs: socket.socket):
        self.app, self.link, self.handoffs = app, link, handoffs
        self.services = services_of(app)
        assert isinstance(self.services.viewers, ViewerManager)
        self.manager = self.services.viewers
        self.hub: WorldHub = self.services.hub
        self.config = uvicorn.Config(app, ws="websockets-sansio", ws_per_message_deflate=False, lifespan="off",
                                     log_level="warning", proxy_headers=False, ws_max_size=WS_MAX_BYTES)
        self.config.load()
        self.server_state = ServerState()
        self._status_due = False
        self._tasks: set[asyncio.Task] = set()

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        self.services.database.attach()
        self.manager.start()
        self.manager.on_change = self._status_changed
        hub_task = asyncio.create_task(self.hub.run(), name="view-world-loop")
        loop.add_reader(self.handoffs.fileno(), self._take_handoffs)
        try:
            while True:
                await self._handle(await self.link.receive())
        except (asyncio.IncompleteReadError, ConnectionError):
            pass  # the server has gone
        finally:
            loop.remove_reader(self.handoffs.fileno())
            for protocol in list(self.server_state.connections):
                protocol.shutdown()
            await self.manager.close()
            await cancel_and_wait(hub_task)
            self.hub.close()
            await self.services.database.settle()
            self.services.engine.dispose()

    async def _handle(self, message: tuple) -> None:
        kind = message[0]
        if kind == "worlds":
            self.manager.remote_worlds = message[1]
            self.manager.show_worlds(message[1])
        elif kind == "playback":
            _, key, playback = message
            if playback is None:
                self.hub.stop(key)
            else:
                self.hub.play(key, playback.attempt, playback.start, playback.speed)
        elif kind == "started":
            _, request, participant_id, target = message
            held = False
            try:
                held = await self.manager.show_started(participant_id, target)
            finally:
                self.link.send(("reply", request, held))
        elif kind == "view":
            self.manager.set_view(message[1], message[2])
        else:
            log.warning("view process: unknown message %r", kind)

    def _status_changed(self) -> None:
        """Report what the views hold once the current callbacks are done (one report for many changes)."""
        if not self._status_due:
            self._status_due = True
            asyncio.get_running_loop().call_soon(self._send_status)

    def _send_status(self) -> None:
        self._status_due = False
        self.link.send(("status", self.manager.status()))

    def _take_handoffs(self) -> None:
        taken = take_handoffs(self.handoffs)
        if taken is None:  # the server has gone; the link's end stops the loop
            asyncio.get_running_loop().remove_reader(self.handoffs.fileno())
            return
        for sock, request in taken:
            task = asyncio.create_task(self._accept(sock, request))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _accept(self, sock: socket.socket, request: bytes) -> None:
        """Serve a browser's connection from its upgrade request on, as uvicorn would have."""
        protocol = WebSocketsSansIOProtocol(config=self.config, server_state=self.server_state, app_state={})
        try:
            await asyncio.get_running_loop().connect_accepted_socket(lambda: protocol, sock=sock)
        except OSError:
            sock.close()
            return
        protocol.data_received(request)


async def serve_views(settings: Settings, messages_fd: int, handoffs_fd: int) -> None:
    link = await MessageLink.over(socket.socket(fileno=messages_fd))
    handoffs = socket.socket(fileno=handoffs_fd)
    handoffs.setblocking(False)
    process = ViewProcess(create_view_app(settings), link, handoffs)
    tune_process()
    await process.run()


def main() -> None:
    settings = Settings(**json.loads(os.environ[SETTINGS_ENV]))
    messages_fd, handoffs_fd = (int(fd) for fd in os.environ[LINK_ENV].split(","))
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: view process: %(message)s")
    redact_server_logs()
    # Its server ends it (by closing the link; the watch below if the server is killed). A Ctrl-C reaches the whole
    # foreground process group and a service manager's SIGTERM the whole group too: were this process to end on
    # them, its server, still shutting down, would take it for a crash and start another.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    exit_with_parent(os.getppid())
    os.nice(NICENESS)
    asyncio.run(serve_views(settings, messages_fd, handoffs_fd))


if __name__ == "__main__":
    main()
