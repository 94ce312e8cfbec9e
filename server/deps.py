"""FastAPI dependencies: one lookup each, so handlers stay short."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Header, Path, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import select
from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from server.errors import Invalid
from server.models import IdempotentResponse, Participant, Study, utcnow
from server.services import admin as admin_service
from server.services.sessions import open_session, touch
from server.services.studies import RuntimeCache
from server.services.trials import AttemptPlanner, advance
from server.settings import Settings
from server.walsync import WalSync


@contextlib.asynccontextmanager
async def database_turn(app: Any, owner: Any = None) -> AsyncIterator[bool]:
    """One unit of work at a time uses the database, first come first served.

    Every SQLite transaction takes the write lock (``server.db``), so units of
    work run one after another anyway; PostgreSQL units run on the event loop
    (``run_unit``), one at a time too. Waiting for the turn here, on the event
    loop, instead of in a worker thread keeps the worker threads free. The turn
    is reentrant for one ``owner`` (a request's state). Yields whether this
    call took the turn (False: no turn needed, or the owner already holds it).
    """
    turn: asyncio.Lock | None = getattr(app.state, "database_turn", None)
    if turn is None or getattr(owner, "has_database_turn", False):
        yield False
        return
    async with turn:
        if owner is not None:
            owner.has_database_turn = True
        try:
            yield True
        finally:
            if owner is not None:
                owner.has_database_turn = False


async def _turn_dependency(request: Request) -> AsyncIterator[None]:
    async with database_turn(request.app, request.state):
        yield


def get_session(request: Request, _turn: Annotated[None, Depends(_turn_dependency, scope="function")]) -> Iterator[Session]:
    """One unit of work per request, committed (and on disk) before the response is sent."""
    with _durable_session(request.app) as session:
        yield session


@contextlib.contextmanager
def _durable_session(app: Any) -> Iterator[Session]:
    """A transaction in this worker thread; if it wrote, its commit is fsynced here (which may block) on exit."""
    wal_sync = app.state.wal_sync
    with app.state.sessionmaker.begin() as session:
        yield session
        wrote = _wrote(wal_sync, session)
    if wrote:
        wal_sync.sync_now()


def _wrote(wal_sync: WalSync | None, session: Session) -> bool:
    """Whether the unit in ``session`` wrote and so must wait for the log's fsync (asked before its commit)."""
    return wal_sync is not None and session.in_transaction() and wal_sync.wrote(session.connection())


def run_unit_here(app: Any, work: Callable[[Session], T]) -> T:
    """A unit of work in this worker thread, outside the database turn (the pooled connection serialises it), on
    disk when it returns."""
    with _durable_session(app) as session:
        return work(session)


SessionDep = Annotated[Session, Depends(get_session, scope="function")]


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_runtimes(request: Request) -> RuntimeCache:
    return request.app.state.runtimes


RuntimesDep = Annotated[RuntimeCache, Depends(get_runtimes)]


def get_planner(request: Request) -> AttemptPlanner:
    return request.app.state.world


PlannerDep = Annotated[AttemptPlanner, Depends(get_planner)]


Token = Annotated[str, Path(min_length=16, max_length=128, description="The participant's session token")]
T = TypeVar("T")


async def run_unit(app: Any, work: Callable[[Session], T], owner: Any = None) -> T:
    """Run ``work`` in one transaction, in the database turn.

    With SQLite the unit runs right here, on the event loop, once the turn is
    taken: a participant's unit of work is a few queries on a local file
    (about a millisecond), while handing it to a worker thread made it compete
    for the interpreter lock with the event loop between every query; under
    load (many teleoperations) that stretched each turn to tens of
    milliseconds and queued every request behind it. A unit that wrote returns
    once its commit is on disk (``server.walsync``).

    PostgreSQL units run the same way, on the loop in the turn (a query on a
    local server takes tens of microseconds; a commit waits for its log flush).
    Measured back to back with 50 participants, every 3D view open (the README):
    units in worker threads, which held their transactions open while waiting
    for the interpreter lock between queries, left 25 of 50 participants stalled
    (p99 2.5 s); on psycopg's async connections, each query a trip through the
    busy loop, 25 stalled (p99 3.8 s); on the loop with only the commit of a
    writing unit in a worker thread, 29 stalled (p99 4.4 s); all on the loop,
    every participant finished (p99 0.56 s).
    """
    factory, wal_sync = app.state.sessionmaker, app.state.wal_sync

    def run() -> tuple[T, bool]:
        with factory.begin() as session:
            result = work(session)
            wrote = _wrote(wal_sync, session)
        return result, wrote

    async with database_turn(app, owner) as took_turn:
        result, wrote = run() if took_turn else await run_in_threadpool(run)
    if wrote:  # on disk before the response, in a batch with whatever else committed meanwhile; the turn is free
        await wal_sync.durable()
    return result


async def unit_of_work(request: Request, work: Callable[[Session], T]) -> T:
    """``run_unit`` for a request: one transaction, one trip, instead of ``SessionDep``'s dependency, handler and
    commit each taking a separate trip between the event loop and the worker threads."""
    return await run_unit(request.app, work, request.state)


async def in_participant_session(request: Request, token: str, work: Callable[[ParticipantContext], T]) -> T:
    """``unit_of_work`` for the session behind ``token`` (see ``open_participant``)."""
    app = request.app
    return await unit_of_work(request, lambda session: work(open_participant(session, app.state.runtimes,
                                                                             app.state.world, token)))


@dataclass
class ParticipantContext:
    session: Session
    study: Study
    participant: Participant
    runtime: StudyRuntime
    planner: AttemptPlanner
    now: datetime


def open_participant(session: Session, runtimes: RuntimeCache, planner: AttemptPlanner, token: str) -> ParticipantContext:
    """The session behind a token, with its due time-based transitions applied."""
    participant, study, runtime = open_session(session, runtimes, token, lock=True)
    now = utcnow()
    touch(participant, now)
    advance(session, participant, runtime, now, planner)
    return ParticipantContext(session, study, participant, runtime, planner, now)


def participant_context(session: SessionDep, runtimes: RuntimesDep, planner: PlannerDep, token: Token) -> ParticipantContext:
    return open_participant(session, runtimes, planner, token)


ParticipantDep = Annotated[ParticipantContext, Depends(participant_context)]


#: Documents the admin API's bearer token in the OpenAPI schema; a missing or malformed header is a 401 with a reason.
_admin_bearer = HTTPBearer(auto_error=False, scheme_name="adminToken",
                           description="The admin token printed by 'trustlab serve' or 'trustlab admin-token'")
#: The same, for routes that accept other credentials too (the report page: ``server.routes.report``).
admin_bearer = _admin_bearer


async def require_admin(request: Request,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_admin_bearer)]) -> None:
    """Checks the token in a short transaction of its own: a long admin request (a report, an export) must not
    keep the database from participants."""
    token = credentials.credentials.strip() if credentials else None
    await unit_of_work(request, lambda session: admin_service.verify_admin(session, token))


AdminDep = Depends(require_admin)

IdempotencyKey = Annotated[str | None, Header(alias="Idempotency-Key", min_length=1, max_length=128,
                                              description="Repeat a request safely: the same key returns the stored response.")]


def idempotent(ctx: ParticipantContext, key: str | None, body: Any, produce: Callable[[], Any]) -> Any:
    """Run ``produce`` once per key: a repeat with the same key and body returns the stored response."""
    if key is None:
        return produce()
    body_json = json.dumps(body.model_dump(mode="json") if hasattr(body, "model_dump") else body, sort_keys=True)
    digest = hashlib.sha256(body_json.encode()).hexdigest()
    stored = ctx.session.scalar(select(IdempotentResponse).where(IdempotentResponse.participant_id == ctx.participant.id,
                                                                 IdempotentResponse.key == key))
    if stored is not None:
        if stored.request_hash != digest:
            raise Invalid(f"Idempotency-Key {key!r} was already used for a different request")
        return stored.response
    response = produce()
    payload = response.model_dump(mode="json") if hasattr(response, "model_dump") else response
    ctx.session.add(IdempotentResponse(participant_id=ctx.participant.id, key=key, request_hash=digest, response=payload))
    return response


async def idempotent_step(request: Request, token: str, key: str | None, body: Any,
                          act: Callable[[ParticipantContext], T]) -> T:
    """``act`` on the session behind ``token``, once per Idempotency-Key (``in_participant_session`` + ``idempotent``)."""
    return await in_participant_session(request, token, lambda ctx: idempotent(ctx, key, body, lambda: act(ctx)))
