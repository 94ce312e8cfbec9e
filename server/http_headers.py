"""Headers every response gets unless its route set them: nothing but the vendored scripts and styles is cached.

Participant and admin responses carry participants' data and tokens (a join answers with the session's token, the
admin API with everything); a shared or browser cache would keep them on disk, under URLs that hold a token.
An HTML response that no route gave a policy (one added later, a framework page) gets the pages' headers
(``PAGE_HEADERS``), so no page is served without them.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: Same-origin only: scripts, styles, fetch/websocket and the 3D view's iframe.
PAGE_HEADERS = {
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Content-Security-Policy": ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
                                "connect-src 'self'; frame-src 'self'; media-src 'self'; object-src 'none'; "
                                "base-uri 'none'; form-action 'self'; frame-ancestors 'self'"),
}

#: Paths whose files may be cached (the pages' scripts and styles carry no data).
CACHEABLE_PREFIX = "/static/"


class NoStoreByDefault:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"].startswith(CACHEABLE_PREFIX):
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("Cache-Control", "no-store")
                if headers.get("content-type", "").startswith("text/html") and "content-security-policy" not in headers:
                    for name, value in PAGE_HEADERS.items():
                        headers.setdefault(name, value)
            await send(message)

        await self.app(scope, receive, with_headers)


class WorkerHeader:
    """Name the worker that answered (``X-Trustlab-Worker``) in a group started by ``serve --workers``.

    It shows which worker a session is routed to, to an operator tracing a problem and to the tests of the
    routing.
    """

    def __init__(self, app: ASGIApp, index: int):
        self.app, self.header = app, (b"x-trustlab-worker", str(index).encode())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return

        async def named(message: Message) -> None:
            if message["type"] in ("http.response.start", "websocket.accept"):
                message["headers"] = [*message.get("headers", []), self.header]
            await send(message)

        await self.app(scope, receive, named)
