"""The FastAPI application: ``create_app(settings)``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from server.db import make_engine, make_sessionmaker
from server.errors import AppError
from server.routes import admin, export, pages, participant, teleop, viewer
from server.services.studies import RuntimeCache
from server.settings import Settings
from server.sweeper import sweep_forever
from server.viewer import ViewerManager
from server.world import WorldHub

log = logging.getLogger("trustlab")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        tasks = []
        viewers = ViewerManager.of(app)
        viewers.start()
        if settings.world_loop:
            tasks = [asyncio.create_task(app.state.world.run(app)), asyncio.create_task(sweep_forever(app))]
        try:
            yield
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            await viewers.close()
            app.state.engine.dispose()

    app = FastAPI(title="trustlab", version="0.1.0", lifespan=lifespan,
                  description="Participant API (token in the path) and admin API (bearer token) of trustlab.")
    app.state.settings = settings
    app.state.engine = make_engine(settings.database_url)
    app.state.sessionmaker = make_sessionmaker(app.state.engine)
    app.state.runtimes = RuntimeCache()
    app.state.world = WorldHub(settings)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    _error_handlers(app)
    for module in (participant, admin, teleop, export, pages, viewer):
        app.include_router(module.router)
    app.mount("/static", pages.static_files(), name="static")
    return app


def _error_handlers(app: FastAPI) -> None:
    @app.exception_handler(AppError)
    async def app_error(_request: Request, exc: AppError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail, "code": exc.code, **exc.extra}, status_code=exc.status_code)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()]
        return JSONResponse({"detail": "; ".join(problems[:10]) or "invalid request", "code": "invalid",
                             "problems": problems}, status_code=422)


class BodySizeLimit:
    """Refuse request bodies over ``max_bytes`` with 413, whether or not Content-Length is sent."""

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", [])).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.max_bytes):
            await _too_large(send, self.max_bytes)
            return
        seen = 0

        async def limited() -> dict:
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.max_bytes:
                raise _BodyTooLarge
            return message

        try:
            await self.app(scope, limited, send)
        except _BodyTooLarge:
            await _too_large(send, self.max_bytes)


class _BodyTooLarge(Exception):
    pass


async def _too_large(send: Send, max_bytes: int) -> None:
    response = JSONResponse({"detail": f"request body larger than {max_bytes} bytes", "code": "too_large"}, status_code=413)
    await response({"type": "http"}, _empty_receive, send)


async def _empty_receive() -> dict:
    return {"type": "http.request", "body": b"", "more_body": False}
