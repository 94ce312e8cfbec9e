"""How request bodies are read: as standard JSON only (``server.strict_json``), on every route.

FastAPI reads a JSON body with Starlette's ``Request.json``, which is Python's lenient ``json.loads`` (``NaN``,
``1e309``, lone surrogates, UTF-16 bodies, nesting up to the recursion limit). Every router is built with
``StrictJsonRoute``, whose requests read their body with ``strict_json.loads`` instead; a body that is not standard
JSON within the bounds is answered 422 with the place and the reason, before any handler or model sees it.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import Request, Response
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException

from server import strict_json


class UnreadableBody(StarletteHTTPException):
    """A body that is not standard JSON within the bounds. An HTTP exception, so that FastAPI passes it on while
    reading the body (any other error there becomes a bare 400)."""

    code = "invalid"

    def __init__(self, error: strict_json.StrictJsonError):
        super().__init__(422, f"body{'.' + error.where if error.where else ''}: {error.reason}")


class StrictJsonRequest(Request):
    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            try:
                self._json = strict_json.loads(await self.body())
            except strict_json.StrictJsonError as exc:
                raise UnreadableBody(exc) from None
        return self._json


class StrictJsonRoute(APIRoute):
    """A route whose JSON body is read by ``StrictJsonRequest``."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def strict_handler(request: Request) -> Response:
            return await handler(StrictJsonRequest(request.scope, request.receive))

        return strict_handler
