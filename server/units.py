"""Units of work: how the server opens a transaction, and when its commit is on disk.

Two entry points: ``run_unit`` (async; on the event loop, in the database turn) for requests, websockets and
anything else on the loop, and ``Database.begin`` (in the calling worker thread) for code that runs off the loop:
the sweeper, fits, exports and reports, a request-long session (``server.deps.SessionDep``). Both return after the
unit's commit is durable.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any, Protocol, TypeVar

from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session, sessionmaker

from server.walsync import WalSync

T = TypeVar("T")


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


class SessionFactory(Protocol):
    """What code off the event loop is given to open sessions: a ``Database`` (or, in a test, a ``sessionmaker``)."""

    def __call__(self) -> Session: ...

    def begin(self) -> contextlib.AbstractContextManager[Session]: ...


class Database:
    """The session factory that every path off the event loop uses, in place of the bare ``sessionmaker``.

    ``begin()`` opens a transaction in this thread whose commit, if it wrote, is fsynced here (which may block)
    before the block exits (SQLite; PostgreSQL's commit is durable itself); calling it gives a plain session, for
    reads. Functions that take a ``factory`` accept either (a test may pass a bare ``sessionmaker``).
    """

    def __init__(self, factory: sessionmaker[Session], wal_sync: WalSync | None):
        self.factory, self.wal_sync = factory, wal_sync

    def __call__(self) -> Session:
        return self.factory()

    @contextlib.contextmanager
    def begin(self) -> Iterator[Session]:
        with self.factory.begin() as session:
            yield session
            wrote = _wrote(self.wal_sync, session)
        if wrote:
            assert self.wal_sync is not None
            self.wal_sync.sync_now()


def durable_transaction(app: Any) -> contextlib.AbstractContextManager[Session]:
    """``Database.begin`` of the app's database."""
    return app.state.database.begin()


def _wrote(wal_sync: WalSync | None, session: Session) -> bool:
    """Whether the unit in ``session`` wrote and so must wait for the log's fsync (asked before its commit)."""
    return wal_sync is not None and session.in_transaction() and wal_sync.wrote(session.connection())


def run_unit_blocking(app: Any, work: Callable[[Session], T]) -> T:
    """A unit of work in this worker thread, outside the database turn (the pooled connection serialises it), on
    disk when it returns."""
    with durable_transaction(app) as session:
        return work(session)


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
