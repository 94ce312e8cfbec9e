"""What a simulated participant's clients share below the session: errors, measurements and websockets.

A bot (``server.harness.bots``) talks to the server over HTTP (``httpx``) and teleoperates over the teleoperation
websocket; ``Socket`` is what it needs of a websocket, so that it runs the same against a real server
(``remote_sockets``: the ``websockets`` sync client) and in process (FastAPI's ``TestClient``).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

#: Longest a bot waits for the server to move on before it calls it an error.
STALL_TIMEOUT_S = 120.0


class BotError(RuntimeError):
    pass


class Refused(BotError):
    """The server answered a request with a 4xx or 5xx (``status``)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


class StudyFull(Refused):
    """The join was refused: the study is at its cap on active participants (503, code ``study_full``). A person
    is told to come back later; for a run it is a refusal, not an error."""

    def __init__(self, message: str):
        super().__init__(message, 503)


class Socket(Protocol):
    def send_text(self, data: str) -> None: ...
    def receive_text(self) -> str: ...


SocketFactory = Callable[[str], AbstractContextManager[Socket]]


def route_name(method: str, path: str) -> str:
    """A request's method and route without the session's token ("POST trials/shown"; "POST join" for a join): the
    bots' and the benchmarks' loop watch's name for it."""
    _, participant, rest = path.partition("/api/p/")
    return f"{method} {rest.partition('/')[2] if participant else path.rsplit('/', 1)[-1]}"


@dataclass
class BotStats:
    latencies_ms: list[float] = field(default_factory=list)
    teleop_ack_ms: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    completed: int = 0
    trials: int = 0
    rate_limited: int = 0  # 429 responses waited out
    refused: int = 0  # joins refused because the study was full
    #: Each request's latency by method and route ("POST trials/shown"; a 429 and its repeat count twice): where the
    #: load comes from, and which step a person waits on.
    route_latencies_ms: defaultdict[str, list[float]] = field(default_factory=lambda: defaultdict(list))


def remote_sockets(url: str) -> SocketFactory:
    """Websockets to the server at ``url`` (http(s)://host:port) for bots."""
    from websockets.sync.client import connect

    base = url.rstrip("/")
    ws_base = "ws" + base[4:] if base.startswith("http") else base

    @contextmanager
    def socket(path: str) -> Iterator[Socket]:
        with connect(ws_base + path, open_timeout=10, max_size=2**20) as ws:
            yield _SyncSocket(ws)

    return socket


class _SyncSocket:
    def __init__(self, ws: Any):
        self.ws = ws

    def send_text(self, data: str) -> None:
        self.ws.send(data)

    def receive_text(self) -> str:
        message = self.ws.recv(timeout=30)
        return message if isinstance(message, str) else message.decode()


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    array = np.asarray(values)
    return {"n": float(array.size), "p50": float(np.percentile(array, 50)), "p95": float(np.percentile(array, 95)),
            "p99": float(np.percentile(array, 99)), "max": float(array.max())}
