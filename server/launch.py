"""Serving the app with uvicorn: ``trustlab serve`` and ``worker`` and each worker of a group (``server.workers``).

Outside the command line, so that a worker process of a group starts the server without importing it.
"""

from __future__ import annotations

import asyncio
import gc
import sys
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from server.app_services import services_of

#: Seconds an idle HTTP connection is kept open (uvicorn's default is 5).
KEEP_ALIVE_S = 65
#: The largest websocket message a client may send (uvicorn's default is 16 MiB, buffered before any handler sees
#: it). The largest legitimate one is a teleoperation message (4 KiB at most, ``server.services.teleop``); the 3D
#: view's client sends its camera, a few hundred bytes. A larger one closes the socket (1009).
WS_MAX_BYTES = 64 * 1024
#: The largest request head (request line and headers) read before answering 400: h11's default, stated here.
MAX_REQUEST_HEAD_BYTES = 16 * 1024
#: The collector's thresholds (Python's default: 700, 10, 10). Young objects get ten times longer to die before a
#: collection keeps them, and a full collection waits for 100 collections of the middle generation instead of 10:
#: far fewer full collections stopping the whole server, the same memory (measured: docs/results.jsonl, ec9c544).
GC_THRESHOLDS = (7_000, 10, 100)
#: Longest the event loop waits for the interpreter lock held by a busy worker thread (Python's default: 5 ms).
SWITCH_INTERVAL_S = 0.001


def forwarded_trust(proxies: str | Sequence[str]) -> dict[str, object]:
    """uvicorn's options for a worker behind nginx: the client address from X-Forwarded-For, believed only from
    ``proxies`` (``"*"`` for a unix socket, which only nginx reaches)."""
    return {"proxy_headers": True, "forwarded_allow_ips": proxies if isinstance(proxies, str) else list(proxies)}


def build_routes(app) -> int:
    """Build how every route handles its requests now; returns the routers built.

    FastAPI (0.16x) builds an included router's routes (their fields and validators) on the router's first request:
    76 ms for trustlab's routers in a quiet process, and 70-100 ms event-loop stalls when participants already
    active made the first requests (loop watch, 100 participants). A FastAPI that builds them when they are
    included has nothing to build here. The routers' caches follow the app's routes: one added later is built on
    its first request, as before.
    """
    built = 0
    pending = list(app.router.routes)
    while pending:
        route = pending.pop()
        for build in ("effective_candidates", "effective_low_priority_routes"):
            method = getattr(route, build, None)
            if callable(method):
                pending += method()
                built += build == "effective_candidates"
    return built


def websocket_protocol(app) -> Any:
    """uvicorn's websocket protocol for ``app``: with ``view_process`` set, the one that hands the 3D view's sockets
    to a view process (and the app's views are that process's, ``server.viewer.remote``); else uvicorn's own."""
    services = services_of(app)
    if not services.settings.view_process:
        return "websockets-sansio"
    from server.viewer.remote import RemoteViewers, ViewerHandoffProtocol

    app.state.services = replace(services, viewers=RemoteViewers(services))
    return ViewerHandoffProtocol


def run_server(app, *, host: str | None = None, port: int | None = None, uds: str | None = None,
               trusted_proxies: Sequence[str] | None = None) -> None:
    """Serve ``app`` with uvicorn until SIGTERM/SIGINT: on ``host``:``port``, or on unix socket ``uds`` behind nginx.

    ``trusted_proxies``: on ``host``:``port``, the addresses whose X-Forwarded-For names the client (nginx's, for
    a worker of a group across machines); None leaves uvicorn's default (127.0.0.1).
    """
    import uvicorn

    ws = websocket_protocol(app)
    build_routes(app)  # before the freeze: what it builds lives as long as the app
    tune_process()
    # No per-message deflate: teleoperation acks are small and viser's frames are compressed already, so it
    # would only spend the server's CPU (one process serves every participant). Idle connections are kept
    # longer than uvicorn's 5 s: a page waiting out a decision window or an attempt sends its next request after
    # about that long, and a request that meets the server closing its connection has to be sent again.
    # The standard asyncio loop and h11 parser, even where uvloop/httptools are installed (uvicorn would pick them
    # up): those are what the load figures were measured with, and two 200-participant runs with them failed.
    # Behind nginx the client address comes from its X-Forwarded-For: from anyone on a unix socket (only nginx
    # reaches it), from nginx's addresses alone on TCP (anyone else could forge addresses and dodge the join limits).
    # Alone on TCP, X-Forwarded-For is believed only from the proxies the settings name (forwarded_allow_ips): none
    # by default, where uvicorn would believe anyone on the loopback (a local process could forge addresses).
    settings = services_of(app).settings
    bind: dict[str, Any]
    if uds:
        bind = {"uds": uds} | forwarded_trust("*")
    elif trusted_proxies is not None:
        bind = {"host": host, "port": port} | forwarded_trust(trusted_proxies)
    else:
        bind = {"host": host, "port": port} | (forwarded_trust(settings.forwarded_allow_ips)
                                               if settings.forwarded_allow_ips else {"proxy_headers": False})
    uvicorn.run(app, log_level="warning", ws_per_message_deflate=False, ws_max_size=WS_MAX_BYTES,
                timeout_keep_alive=KEEP_ALIVE_S,
                h11_max_incomplete_event_size=MAX_REQUEST_HEAD_BYTES,
                loop="asyncio", http=bounded_h11(settings.request_head_timeout_s), ws=ws, **bind)


def bounded_h11(timeout_s: float) -> type:
    """uvicorn's h11 protocol with a deadline for each request's head (request line and headers).

    uvicorn (0.55) bounds only the wait between requests (``timeout_keep_alive``): a connection that sends nothing,
    or half a head, is held for ever, and a few thousand of them hold the server's sockets and memory. A head not
    complete ``timeout_s`` after the connection opened (or after the first byte of a kept-alive connection's next
    request) closes the connection.
    """
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class BoundedHeadH11Protocol(H11Protocol):
        head_deadline: asyncio.TimerHandle | None = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._await_head()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)  # cancels the keep-alive timer, handles what is complete
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                if self.head_deadline is None:  # the next request's head began
                    self._await_head()
            elif self.head_deadline is not None:  # the head is in (a body, an upgrade, the app's turn)
                self.head_deadline.cancel()
                self.head_deadline = None

        def connection_lost(self, exc: Exception | None) -> None:
            if self.head_deadline is not None:
                self.head_deadline.cancel()
            super().connection_lost(exc)

        def _await_head(self) -> None:
            self.head_deadline = self.loop.call_later(timeout_s, self._head_too_slow)

        def _head_too_slow(self) -> None:
            self.head_deadline = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                self.transport.close()

    return BoundedHeadH11Protocol


def tune_process() -> None:
    """The collector and the interpreter lock's switch interval, for a server's process (once it has started)."""
    # The modules, the app and the demo study live as long as the process: out of the collector's sight, a full
    # collection no longer walks their ~200,000 objects, which stalled the event loop for 130-250 ms each time.
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)
    # A worker thread that computes (an export, a fit) keeps the interpreter lock for up to a switch interval
    # whenever the event loop lets go of it (every socket and database call): 1 ms instead of 5 ms.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
