"""How requests are read: bodies as standard JSON only (``server.strict_json``), on every route; the admin API's
query parameters only as its routes declare them.

FastAPI reads a JSON body with Starlette's ``Request.json``, which is Python's lenient ``json.loads`` (``NaN``,
``1e309``, lone surrogates, UTF-16 bodies, nesting up to the recursion limit). Every router is built with
``StrictJsonRoute``, whose requests read their body with ``strict_json.loads`` instead; a body that is not standard
JSON within the bounds is answered 422 with the place and the reason, before any handler or model sees it.

FastAPI ignores query parameters a route does not declare: a mistyped ``include_previews=true`` would export
without the previews and say nothing. The admin API answers them with 422 and their names
(``refuse_unknown_query``). A join link carries whatever parameters its recruitment site adds, and the pages read
theirs in the browser: those stay free.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import Request, Response
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException

from server import strict_json


class UnreadableBody(StarletteHTTPException):
    """A body that is not standard JSON within the bounds. An HTTP exception, so that FastAPI passes it on while
    reading the body (any other error there becomes a bare 400)."""

    code = "invalid"

    def __init__(self, error: strict_json.StrictJsonError):
        super().__init__(422, f"body{'.' + error.where if error.where else ''}: {error.reason}")


class UnknownQueryParameters(StarletteHTTPException):
    code = "invalid"

    def __init__(self, names: list[str], known: set[str]):
        allowed = f"; this request takes {', '.join(sorted(known))}" if known else "; this request takes none"
        super().__init__(422, f"query: unknown parameter(s) {', '.join(repr(n) for n in names)}{allowed}")


class StrictJsonRequest(Request):
    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            try:
                self._json = strict_json.loads(await self.body())
            except strict_json.StrictJsonError as exc:
                raise UnreadableBody(exc) from None
        return self._json


def refuse_unknown_query(request: Request) -> None:
    """422 for a query parameter the route does not declare (the admin API's check, ``server.deps.require_admin``:
    after the token's, so that a request without the admin token is a 401 whatever its parameters)."""
    route = request.scope.get("route")
    known = _query_names(route.dependant) if isinstance(route, APIRoute) else set()
    if unknown := sorted(set(request.query_params) - known):
        raise UnknownQueryParameters(unknown, known)


class StrictJsonRoute(APIRoute):
    """A route whose JSON body is read by ``StrictJsonRequest``."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def strict_handler(request: Request) -> Response:
            return await handler(StrictJsonRequest(request.scope, request.receive))

        return strict_handler


def _query_names(dependant: Dependant) -> set[str]:
    """The query parameters a route declares, its dependencies' included."""
    names = {param.alias for param in dependant.query_params}
    for dependency in dependant.dependencies:
        names |= _query_names(dependency)
    return names
