"""Durable SQLite commits without an fsync on the event loop (group commit).

SQLite runs in WAL mode with ``synchronous=NORMAL``: a commit appends to the
write-ahead log and returns without an fsync. That survives ``kill -9`` of the
server (the operating system holds the written pages) but not a power cut.
``synchronous=FULL`` would fsync the log inside every commit; the participant
units of work commit on the event loop (``server.deps.run_unit``), so that
fsync would stall every request and teleoperation for its duration, and under
load the stalls added up to most of the latency.

Instead, a unit that wrote waits, after releasing the database turn and before
its response is sent, until an fsync of the log that began after its commit
has finished (fsync of any descriptor of a file flushes all of its written
pages). Units that commit while an fsync runs share the next one, so the cost
is one fsync per batch, in a worker thread. An acknowledged write therefore
survives a power cut as with ``synchronous=FULL``.
"""

from __future__ import annotations

import asyncio
import os
import threading
from pathlib import Path
from typing import Any

from sqlalchemy import event
from sqlalchemy.engine import Engine

_READ_ONLY = ("SELECT", "PRAGMA", "BEGIN", "COMMIT", "ROLLBACK", "SAVEPOINT", "RELEASE")


class WalSync:
    def __init__(self, engine: Engine):
        database = engine.url.database
        assert engine.dialect.name == "sqlite" and database and database != ":memory:"
        self.wal_path = Path(database).resolve().with_name(Path(database).name + "-wal")
        self._local = threading.local()  # per thread: a unit's statements and its take_dirty run in one thread
        # Per event loop (tests run apps on several): the futures waiting for the next fsync, and whether a
        # task is syncing for that loop.
        self._waiters: dict[asyncio.AbstractEventLoop, list[asyncio.Future[None]]] = {}
        self._syncing: set[asyncio.AbstractEventLoop] = set()
        self.syncs = 0  # fsyncs done (batches)
        event.listen(engine, "after_cursor_execute", self._after_execute)

    @classmethod
    def for_engine(cls, engine: Engine) -> WalSync | None:
        """A WalSync for a file-backed SQLite engine; None otherwise (PostgreSQL, in-memory SQLite)."""
        database = engine.url.database
        if engine.dialect.name != "sqlite" or not database or database == ":memory:" or database.startswith("file:"):
            return None
        return cls(engine)

    def _after_execute(self, _conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        if not statement.lstrip()[:9].upper().startswith(_READ_ONLY):
            self._local.dirty = True

    def take_dirty(self) -> bool:
        """Whether this thread ran a write statement since its last call (the caller then waits for ``durable``)."""
        dirty = getattr(self._local, "dirty", False)
        self._local.dirty = False
        return dirty

    async def durable(self) -> None:
        """Return once everything committed before this call is on disk."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        self._waiters.setdefault(loop, []).append(future)
        if loop not in self._syncing:
            self._syncing.add(loop)
            loop.create_task(self._sync_batches(loop))
        await future

    def sync_now(self) -> None:
        """Fsync the log here (for units that committed in a worker thread, which may block)."""
        self._fsync()

    async def _sync_batches(self, loop: asyncio.AbstractEventLoop) -> None:
        try:
            while batch := self._waiters.pop(loop, []):
                try:
                    await asyncio.to_thread(self._fsync)
                except Exception as exc:  # noqa: BLE001 -- handed to every waiter of the batch
                    for future in batch:
                        if not future.done():
                            future.set_exception(exc)
                    continue
                for future in batch:
                    if not future.done():
                        future.set_result(None)
        finally:
            self._syncing.discard(loop)

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
