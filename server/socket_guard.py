"""What every websocket checks before and while it serves: where the page that opened it comes from, and how fast
its client sends.

A browser sends the ``Origin`` of the page that opens a websocket, and unlike HTTP no CORS rule stops a page on
another site from opening one to this server. A socket is accepted when its Origin is this server as the browser
reached it (the ``Host`` it asked for), the public URL (``TRUSTLAB_PUBLIC_URL``) or one of
``TRUSTLAB_ALLOWED_ORIGINS``; a client that is not a browser (a bot, a protocol client) sends no Origin and is
accepted. A refused socket is closed before it is accepted: the client gets an HTTP 403.
"""

from __future__ import annotations

import time
from urllib.parse import urlsplit

from starlette.websockets import WebSocket

from server.ratelimit import RateLimiter
from server.settings import Settings

#: Close code for a socket refused by policy: another origin, or far too many messages.
CLOSE_POLICY = 1008


def _origin_of(url: str) -> str:
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}".lower()


def allowed_origins(settings: Settings) -> set[str]:
    return {_origin_of(settings.base_url()), *(_origin_of(o) for o in settings.allowed_origins)}


def origin_allowed(websocket: WebSocket, settings: Settings) -> bool:
    """Whether the page that opened ``websocket`` may use it (see the module's docstring)."""
    origin = websocket.headers.get("origin")
    if origin is None:
        return True
    origin = origin.strip().lower()
    host = websocket.headers.get("host", "").lower()
    if host and origin in (f"http://{host}", f"https://{host}"):
        return True
    return origin in allowed_origins(settings)


class FrameBudget:
    """A socket's allowance of client messages: ``per_second`` on average, ``burst`` at once (one token bucket)."""

    def __init__(self, per_second: float, burst: float):
        self._limiter = RateLimiter(per_second, burst, max_keys=1)

    def take(self, now: float | None = None) -> bool:
        """Count one message; False when the client is over its allowance."""
        return self._limiter.take("", time.monotonic() if now is None else now) == 0
