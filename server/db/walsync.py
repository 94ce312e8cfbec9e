"""Durable SQLite commits without an fsync on the event loop (group commit).

SQLite runs in WAL mode with ``synchronous=NORMAL``: a commit appends to the
write-ahead log and returns without an fsync. That survives ``kill -9`` of the
server (the operating system holds the written pages) but not a power cut.
``synchronous=FULL`` would fsync the log inside every commit; the participant
units of work commit on the event loop (``server.db.units.Database.run``), so that
fsync would stall every request and teleoperation for its duration, and under
load the stalls added up to most of the latency.

Instead, a unit that wrote waits, after releasing the database turn and before
its response is sent, until an fsync of the log that began after its commit
has finished (fsync of any descriptor of a file flushes all of its written
pages). One thread does the fsyncs: it takes every waiter queued so far,
fsyncs, and hands the batch back to the waiters' event loops in one callback
(the fewest trips through a busy event loop). Units that commit while an fsync
runs share the next one. An acknowledged write therefore survives a power cut
as with ``synchronous=FULL``.
"""

from __future__ import annotations

import asyncio
import os
import threading
from pathlib import Path
from typing import Any

from sqlalchemy import Connection, event
from sqlalchemy.engine import Engine

_READ_ONLY = ("SELECT", "PRAGMA", "BEGIN", "COMMIT", "ROLLBACK", "SAVEPOINT", "RELEASE")
#: Set in a database connection's ``info`` by a write statement; taken by ``WalSync.wrote``.
_WROTE = "trustlab_wrote"
#: The fsync thread ends after this long without work (and starts again when needed).
IDLE_EXIT_S = 30.0

Waiter = tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]


class WalSync:
    def __init__(self, engine: Engine):
        database = engine.url.database
        assert engine.dialect.name == "sqlite" and database and database != ":memory:"
        self.wal_path = Path(database).resolve().with_name(Path(database).name + "-wal")
        self._pending: list[Waiter] = []
        self._wake = threading.Condition()
        self._thread: threading.Thread | None = None
        self.syncs = 0  # fsyncs done (batches)
        event.listen(engine, "after_cursor_execute", self._after_execute)

    @classmethod
    def for_engine(cls, engine: Engine) -> WalSync | None:
        """A WalSync for a file-backed SQLite engine; None otherwise (PostgreSQL, in-memory SQLite)."""
        database = engine.url.database
        if engine.dialect.name != "sqlite" or not database or database == ":memory:" or database.startswith("file:"):
            return None
        return cls(engine)

    @staticmethod
    def _after_execute(conn: Connection, _cursor: Any, statement: str, *_args: Any) -> None:
        if not statement.lstrip()[:9].upper().startswith(_READ_ONLY):
            conn.info[_WROTE] = True

    @staticmethod
    def wrote(connection: Connection) -> bool:
        """Whether a write statement ran on this database connection since the last call (call it before the
        transaction ends, then wait for ``durable``/``sync_now`` after the commit)."""
        return connection.info.pop(_WROTE, False)

    async def durable(self) -> None:
        """Return once everything committed before this call is on disk."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        with self._wake:
            self._pending.append((loop, future))
            if self._thread is None:
                self._thread = threading.Thread(target=self._sync_batches, name="trustlab-walsync", daemon=True)
                self._thread.start()
            self._wake.notify()
        await future

    def sync_now(self) -> None:
        """Fsync the log in this thread (a worker thread's unit, which may block)."""
        self._fsync()

    def _sync_batches(self) -> None:
        while True:
            with self._wake:
                if not self._pending and not self._wake.wait_for(lambda: self._pending, timeout=IDLE_EXIT_S):
                    self._thread = None
                    return
                batch, self._pending = self._pending, []
            error: BaseException | None = None
            try:
                self._fsync()
            except Exception as exc:  # noqa: BLE001 -- handed to every waiter of the batch
                error = exc
            by_loop: dict[asyncio.AbstractEventLoop, list[asyncio.Future[None]]] = {}
            for loop, future in batch:
                by_loop.setdefault(loop, []).append(future)
            for loop, futures in by_loop.items():
                try:
                    loop.call_soon_threadsafe(_release, futures, error)
                except RuntimeError:  # that event loop has closed: nobody is waiting there any more
                    pass

    def _fsync(self) -> None:
        try:
            fd = os.open(self.wal_path, os.O_RDONLY)
        except FileNotFoundError:  # no log: everything is in the database file, which SQLite synced
            return
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        self.syncs += 1


def _release(futures: list[asyncio.Future[None]], error: BaseException | None) -> None:
    for future in futures:
        if not future.done():
            if error is None:
                future.set_result(None)
            else:
                future.set_exception(error)
