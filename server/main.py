"""The FastAPI application: ``create_app(settings)``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator, Mapping
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from experiment.config_problems import PATTERNS_IN_WORDS, place, plain_message
from server.app_services import JoinLimits, Services, services_of
from server.db.engine import make_engine, make_sessionmaker
from server.db.units import Database
from server.db.walsync import WalSync
from server.deps import AdminDep
from server.errors import AppError, RateLimited, StudyFull, TooLarge, Unauthorized
from server.faults import FaultLog, supervised
from server.http_headers import NoStoreByDefault, WorkerHeader
from server.loadmeter import LoadHistory, record_load_forever
from server.logs import redact_server_logs
from server.ratelimit import RateLimiter
from server.routes import admin, designer, export, messages, models, pages, participant, replay, report, teleop, viewer
from server.schemas import SLUG_REGEX, error_responses
from server.services.events import EventBudget
from server.services.fits import FitWorker
from server.services.studies import RuntimeCache
from server.services.teleop_log import TeleopLogWriter
from server.settings import Settings
from server.sweeper import sweep_forever
from server.viewer import ViewerManager
from server.world.hub import WorldHub

log = logging.getLogger("trustlab")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    redact_server_logs()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services = services_of(app)  # the view process's views, if ``server.launch`` set them after this was built
        tasks = []
        services.database.attach()  # requests and worker threads take turns at the database (server.db.units)
        services.viewers.start()
        services.teleop_log.start()
        if settings.world_loop:
            # Supervised: a loop that fails as a whole is logged, counted in the load report and started again
            loops = {"world": services.hub.run, "load": lambda: record_load_forever(services)}
            if settings.primary:  # one sweeper per database (server.workers)
                loops["sweeper"] = lambda: sweep_forever(services)
            tasks = [asyncio.create_task(supervised(name, run, services.faults), name=name)
                     for name, run in loops.items()]
        try:
            yield
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            await services.viewers.close()
            await services.teleop_log.stop()
            await services.database.settle()  # before the pool is disposed of: its threads hold connections
            services.database.detach()
            services.hub.close()
            services.engine.dispose()

    app = FastAPI(title="trustlab", version="0.1.0", lifespan=lifespan, docs_url=None, redoc_url=None,  # pages.api_docs
                  description=("Participant API (token in the path) and admin API (bearer token) of trustlab. The "
                               "teleoperation websocket `/api/p/{token}/teleop` is not an HTTP route: its messages, "
                               "both ways, are published as JSON Schema at "
                               "[/api/schema/teleop.json](/api/schema/teleop.json)."))
    app.state.services = build_services(settings)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(NoStoreByDefault)  # server.http_headers: no participant or admin data in any cache
    if settings.worker_index is not None:
        app.add_middleware(WorkerHeader, index=settings.worker_index)
    _error_handlers(app)
    _database_error_handler(app)
    for module in (participant, messages, admin, designer, teleop, export, pages, viewer, models, report, replay):
        responses = error_responses(400, 413, 422)  # any request may be unreadable, too large or invalid
        if AdminDep in module.router.dependencies:
            responses |= error_responses(401)
        app.include_router(module.router, responses=responses)
    app.mount("/static", pages.static_files(), name="static")
    return app


def build_services(settings: Settings) -> Services:
    engine = make_engine(settings.database_url)
    factory = make_sessionmaker(engine)
    database = Database(factory, WalSync.for_engine(engine))  # SQLite: acknowledged writes fsynced off the loop
    runtimes, faults = RuntimeCache(), FaultLog()
    hub = WorldHub(settings, faults)
    return Services(
        settings=settings, engine=engine, sessionmaker=factory, database=database, runtimes=runtimes, faults=faults,
        hub=hub, viewers=ViewerManager(hub, database.run, runtimes), teleop_log=TeleopLogWriter(database, faults),
        fits=FitWorker(database), load_history=LoadHistory(),
        join_limits=JoinLimits(RateLimiter.minutely(settings.join_rate_limit_per_ip),
                               RateLimiter.minutely(settings.join_rate_limit_per_study)),
        event_budget=EventBudget(settings))


#: The participant API (its pages read an error's ``message``, a catalogue key; the admin API's clients need none).
PARTICIPANT_PATHS = ("/api/p/", "/api/studies/")


def _error_handlers(app: FastAPI) -> None:
    @app.exception_handler(AppError)
    async def app_error(request: Request, exc: AppError) -> JSONResponse:
        headers = {}
        if isinstance(exc, Unauthorized):
            headers["WWW-Authenticate"] = "Bearer"
        if isinstance(exc, RateLimited | StudyFull) and "retry_after_s" in exc.extra:
            headers["Retry-After"] = str(math.ceil(exc.extra["retry_after_s"]))
        # jsonable_encoder: the extras may be models (a session's step), written out as JSON only here
        body = {"detail": exc.detail, "code": exc.code, **exc.extra}
        if request.url.path.startswith(PARTICIPANT_PATHS):  # the participant pages show the sentence of this key
            body |= {"message": exc.message} | ({"message_params": exc.message_params} if exc.message_params else {})
        return JSONResponse(jsonable_encoder(body),
                            status_code=exc.status_code, headers=headers)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        """Framework errors (unknown path, wrong method, unreadable body) in the same shape as ours."""
        headers = dict(exc.headers or {})
        if exc.status_code == 405:  # Starlette names only the first route's methods; the path may have more
            headers["Allow"] = ", ".join(_allowed_methods(request))
        code = getattr(exc, "code", None) or HTTPStatus(exc.status_code).phrase.lower().replace(" ", "_")
        return JSONResponse({"detail": exc.detail, "code": code}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = [_request_problem(exc.body, e) for e in exc.errors()]
        return JSONResponse({"detail": "; ".join(problems[:10]) or "invalid request", "code": "invalid",
                             "problems": problems}, status_code=422)


def _database_error_handler(app: FastAPI) -> None:
    @app.exception_handler(OperationalError)
    async def database_unavailable(_request: Request, exc: OperationalError) -> JSONResponse:
        """The database cannot take the request now (a full disk, a lost connection, a lock held too long): 503 with
        Retry-After in the usual shape, not a bare 500. The request's unit of work was rolled back."""
        full = getattr(exc.orig, "sqlstate", None) == DISK_FULL_SQLSTATE or "database or disk is full" in str(exc.orig)
        log.error("database unavailable: %s: %s", type(exc.orig).__name__, (str(exc.orig).splitlines() or [""])[0])
        detail = "the server's disk is full" if full else "the database is unavailable"
        return JSONResponse({"detail": f"{detail}: nothing was saved; please try again in a minute",
                             "code": "disk_full" if full else "database_unavailable"},
                            status_code=503, headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)})


#: PostgreSQL's disk_full (class 53, insufficient resources); SQLite says "database or disk is full".
DISK_FULL_SQLSTATE = "53100"
#: Seconds a client is asked to wait after the database could not take its request.
DATABASE_RETRY_AFTER_S = 30


def _request_problem(body: Any, error: Mapping[str, Any]) -> str:
    """A problem as "place: message", e.g. "body.config.blocks.1.schedule.n_low: …"; a study config's problem is
    placed as the designer's check places it (``experiment.config_problems``: no union tags), so the two agree."""
    loc = tuple(error["loc"])
    message = plain_message(error, _PATTERNS_IN_WORDS)
    if loc[:2] == _CONFIG_IN_BODY and isinstance(body, dict):
        loc = _CONFIG_IN_BODY + tuple(place(body.get("config"), loc[2:], message).loc)
    return f"{'.'.join(str(p) for p in loc)}: {message}"


_PATTERNS_IN_WORDS = {**PATTERNS_IN_WORDS, SLUG_REGEX: "use 2 to 63 lower-case letters, digits and '-', starting "
                                                       "with a letter or digit (it is part of the join link)"}


_CONFIG_IN_BODY = ("body", "config")
_HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def _allowed_methods(request: Request) -> list[str]:
    """The methods some route of the app takes at this path."""
    return [method for method in _HTTP_METHODS
            if any(route.matches({**request.scope, "method": method})[0] == Match.FULL for route in request.app.routes)]


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

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.max_bytes:
                raise BodyTooLarge(self.max_bytes)
            return message

        try:
            await self.app(scope, limited, send)
        except BodyTooLarge:  # raised where no handler turned it into the response
            await _too_large(send, self.max_bytes)


class BodyTooLarge(StarletteHTTPException):
    """An HTTP exception, so that FastAPI passes it on while reading a body (any other error there becomes a 400)."""

    code = TooLarge.code

    def __init__(self, max_bytes: int):
        super().__init__(413, f"request body larger than {max_bytes} bytes")


async def _too_large(send: Send, max_bytes: int) -> None:
    response = JSONResponse({"detail": BodyTooLarge(max_bytes).detail, "code": TooLarge.code}, status_code=413)
    await response({"type": "http"}, _empty_receive, send)


async def _empty_receive() -> dict:
    return {"type": "http.request", "body": b"", "more_body": False}
