"""Units of work: how the server opens a transaction, and when its commit is on disk.

Two entry points, both of ``Database``: ``run`` (async; on the event loop, in the database turn) for requests,
websockets and anything else on the loop, and ``begin`` (in the calling worker thread) for code that runs off the
loop: the sweeper, fits, exports and reports, an admin request's session (``server.deps.SessionDep``). Both return
after the unit's commit is durable. ``docs/architecture.md`` ("Units of work") says why they run where they do.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import contextvars
import threading
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any, Protocol, TypeVar

from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session, sessionmaker

from server.db.walsync import WalSync

T = TypeVar("T")

#: How often a worker thread waiting for the turn checks that the server is still running.
TURN_CHECK_S = 1.0
#: Whether this task or worker thread holds the database turn (a worker thread inherits its caller's context: a
#: request's session, opened in a worker thread while the request's dependency holds the turn, must not ask again).
_holds_turn: contextvars.ContextVar[bool] = contextvars.ContextVar("holds_database_turn", default=False)


#: What code that only reads is given: opens a session (a ``SessionFactory``, or the caller's session in a
#: ``nullcontext``).
SessionOpener = Callable[[], contextlib.AbstractContextManager[Session]]


class SessionFactory(Protocol):
    """What code off the event loop is given to open sessions: a ``Database`` (or, in a test, a ``sessionmaker``)."""

    def __call__(self) -> contextlib.AbstractContextManager[Session]: ...

    def begin(self) -> contextlib.AbstractContextManager[Session]: ...


class Database:
    """The session factory that every path off the event loop uses, in place of the bare ``sessionmaker``.

    ``begin()`` opens a transaction in this thread whose commit, if it wrote, is fsynced here (which may block)
    before the block exits (SQLite; PostgreSQL's commit is durable itself); calling it gives a plain session, for
    reads. Functions that take a ``factory`` accept either (a test may pass a bare ``sessionmaker``).

    Both first wait for the database turn (``turn``) of the running server (``attach``), from this
    thread, and hold it until the session closes. Without it, a worker thread (the sweeper, an export page, a
    fit) took SQLite's one pooled connection while the event loop's units queued on the turn alone; the next unit
    then blocked the whole event loop in the pool until the thread, competing for the interpreter lock, was done:
    stalls of 170-220 ms under load (50 participants, every 3D view open). Now the loop's units wait for the turn
    without blocking the loop.
    """

    def __init__(self, factory: sessionmaker[Session], wal_sync: WalSync | None):
        self.factory, self.wal_sync = factory, wal_sync
        self._turn: asyncio.Lock | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._in_threads: set[asyncio.Future] = set()

    def attach(self) -> None:
        """The server started (on this event loop): from now on units take turns at the database."""
        self._turn = asyncio.Lock()
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()

    def detach(self) -> None:
        """The server stops: threads still running go ahead without the turn."""
        self._turn = None
        self._loop = None
        self._loop_thread = None

    @contextlib.asynccontextmanager
    async def turn(self, owner: Any = None) -> AsyncIterator[bool]:
        """One unit of work at a time uses the database, first come first served.

        Every SQLite transaction takes the write lock (``server.db.engine``), so units of work run one after another
        anyway; PostgreSQL units run on the event loop (``run``), one at a time too. Waiting for the turn here, on
        the event loop, instead of in a worker thread keeps the worker threads free. The turn is reentrant for one
        ``owner`` (a request's state). Yields whether this call took the turn (False: no turn needed, or the owner
        already holds it).
        """
        turn = self._turn
        if turn is None or getattr(owner, "has_database_turn", False):
            yield False
            return
        async with turn:
            if owner is not None:
                owner.has_database_turn = True
            held = _holds_turn.set(True)
            try:
                yield True
            finally:
                _holds_turn.reset(held)
                if owner is not None:
                    owner.has_database_turn = False

    async def run(self, work: Callable[[Session], T], owner: Any = None) -> T:
        """Run ``work`` in one transaction, in the database turn, on the event loop; returns once a commit that
        wrote is on disk (``server.db.walsync``). ``owner``: the request whose turn this is (``turn``)."""
        async with self.turn(owner) as took_turn:
            result, wrote = self.run_here(work) if took_turn else await run_in_threadpool(self.run_here, work)
        if wrote:  # on disk before the response, in a batch with whatever else committed meanwhile; the turn is free
            assert self.wal_sync is not None
            await self.wal_sync.durable()
        return result

    async def in_thread(self, work: Callable[..., T], *args: Any) -> T:
        """``work(*args)`` (which opens its own units) in a worker thread, to its end: a worker thread cannot be
        stopped, so a cancelled caller waits for it before it is cancelled, and ``settle`` waits for it too. Left
        running, it would return its connection after the server's shutdown had disposed of the pool, into a pool
        no one closes (and SQLite's log would miss its fsync)."""
        future = asyncio.get_running_loop().run_in_executor(None, work, *args)
        self._in_threads.add(future)
        future.add_done_callback(self._in_threads.discard)
        try:
            return await asyncio.shield(future)
        except asyncio.CancelledError:
            await asyncio.wait([future])
            raise

    async def settle(self) -> None:
        """Wait for the work every ``in_thread`` started (the server's shutdown, before it disposes of the pool)."""
        while self._in_threads:
            await asyncio.wait(list(self._in_threads))

    @contextlib.contextmanager
    def __call__(self) -> Iterator[Session]:
        with self._in_turn(), self.factory() as session:
            yield session

    def run_here(self, work: Callable[[Session], T]) -> tuple[T, bool]:
        """``work`` in one transaction in this thread, for a caller that holds the turn and waits for the fsync
        itself (``run``); returns its result and whether it wrote (so must wait for the log's fsync)."""
        with self.factory.begin() as session:
            result = work(session)
            wrote = _wrote(self.wal_sync, session)
        return result, wrote

    @contextlib.contextmanager
    def begin(self) -> Iterator[Session]:
        with self._in_turn():
            with self.factory.begin() as session:
                yield session
                wrote = _wrote(self.wal_sync, session)
        if wrote:  # the turn is free while the log is fsynced
            assert self.wal_sync is not None
            self.wal_sync.sync_now()

    @contextlib.contextmanager
    def _in_turn(self) -> Iterator[None]:
        turn, loop = self._turn, self._loop
        # On the loop's own thread a unit already holds the turn (``run``); waiting here would deadlock.
        if turn is None or loop is None or _holds_turn.get() or threading.get_ident() == self._loop_thread:
            yield
            return
        if not self._wait_for(turn, loop):  # the server stopped meanwhile
            yield
            return
        held = _holds_turn.set(True)
        try:
            yield
        finally:
            _holds_turn.reset(held)
            with contextlib.suppress(RuntimeError):  # a closed loop holds no one waiting
                loop.call_soon_threadsafe(turn.release)

    def _wait_for(self, turn: asyncio.Lock, loop: asyncio.AbstractEventLoop) -> bool:
        """Take ``turn`` from this thread; False if the server detached it (stopping) before it came."""
        try:
            taken = asyncio.run_coroutine_threadsafe(turn.acquire(), loop)
        except RuntimeError:  # the loop is closed
            return False
        while True:
            try:
                taken.result(timeout=TURN_CHECK_S)
                return True
            except concurrent.futures.TimeoutError:
                if self._turn is turn and not loop.is_closed():
                    continue
                if taken.cancel():
                    return False
                # it came just now: taken, so it must be given back
                taken.result()
                return True


def _wrote(wal_sync: WalSync | None, session: Session) -> bool:
    """Whether the unit in ``session`` wrote and so must wait for the log's fsync (asked before its commit)."""
    return wal_sync is not None and session.in_transaction() and wal_sync.wrote(session.connection())
