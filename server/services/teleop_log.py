"""The one writer of teleoperation logs: every entry an arm's ``TeleopLog`` holds reaches the event log through here.

Every open teleoperation's new entries are written together, at most ``LOG_FLUSH_S`` apart, in one unit of work (one
unit per socket took 15 % of the interpreter lock with 100 participants teleoperating: ``docs/architecture.md``). A
socket's own entries are written when it closes, when its teleoperation ends, and with the trial's completion on a
deposit; the database turn is taken in order, so entries taken earlier are written first.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from typing import Any, TypeVar

from sqlalchemy import select
from sqlalchemy.orm import Session, load_only

from experiment.events import EventKind
from server.db.units import Database
from server.faults import FaultLog
from server.models import Participant
from server.services import sessions
from server.services.audit import log_event
from server.world.teleop import LogEvent, TeleopSession

LOG_FLUSH_S = 1.0
#: A socket's entries that failed this many writes in a row on their own are dropped (a ``log_lost`` entry says how
#: many): entries that can never be written must not be retried for ever.
MAX_LOG_WRITE_FAILURES = 5

T = TypeVar("T")
Batch = tuple[str, TeleopSession, list[dict[str, Any]]]  # (session token, teleoperation, entries)


class TeleopLogWriter:
    def __init__(self, database: Database, faults: FaultLog):
        self.database, self.faults = database, faults
        self._open: dict[tuple[str, int], tuple[str, TeleopSession]] = {}
        self._task: asyncio.Task | None = None
        self._writing: asyncio.Future | None = None  # the last write: ``stop`` waits for it

    def watch(self, token: str, teleop: TeleopSession) -> None:
        self._open[(token, id(teleop))] = (token, teleop)

    def forget(self, token: str, teleop: TeleopSession) -> None:
        self._open.pop((token, id(teleop)), None)

    def start(self) -> None:
        self._task = asyncio.create_task(self._write_forever(), name="teleop-log")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._writing is not None:
            await asyncio.wait([self._writing])
        await self.flush()

    # -- one socket's entries ------------------------------------------------------------------------------------
    async def write(self, token: str, teleop: TeleopSession) -> None:
        """Write ``teleop``'s new entries now (its teleoperation ended: they must be in before the next read)."""
        if batch := teleop.log.take():
            await self._write_or_keep(teleop, batch, lambda session: _log_batches(session, [(token, teleop, batch)]))

    async def write_with(self, token: str, teleop: TeleopSession, then: Callable[[Session, Participant], T]) -> T:
        """Lock the participant, write ``teleop``'s new entries and run ``then`` in the same unit of work (a deposit
        completes the trial with its last entries)."""
        batch = teleop.log.take()

        def unit(session: Session) -> T:
            participant = sessions.participant_by_token(session, token, lock=True)
            _log_entries(session, participant, teleop, batch)
            return then(session, participant)

        return await self._write_or_keep(teleop, batch, unit)

    async def _write_or_keep(self, teleop: TeleopSession, batch: list[dict[str, Any]],
                             unit: Callable[[Session], T]) -> T:
        """Entries of a unit that fails stay in the log for the next write."""
        try:
            return await self.database.run(unit)
        except BaseException:
            teleop.log.put_back(batch)
            raise

    async def write_closing(self, token: str, teleop: TeleopSession) -> None:
        """A closed socket's last entries, in a worker thread that a cancelled socket task does not stop (the
        server's shutdown waits for it: ``Database.in_thread``)."""
        self.forget(token, teleop)
        if batch := teleop.log.take():
            await self.database.in_thread(self._write_here, [(token, teleop, batch)])

    def _write_here(self, batches: list[Batch]) -> None:
        with self.database.begin() as session:
            _log_batches(session, batches)

    # -- every open socket's entries -----------------------------------------------------------------------------
    async def _write_forever(self) -> None:
        while True:
            await asyncio.sleep(LOG_FLUSH_S)
            await self.flush()  # what fails is kept for the next round or, past the retries, recorded as a fault

    async def flush(self) -> None:
        """Write every open teleoperation's new entries in one unit; if that fails, each socket's in a unit of its
        own, so that one session's entries that cannot be written never hold back another's."""
        batches = [(token, teleop, batch) for token, teleop in list(self._open.values())
                   if (batch := teleop.log.take())]
        if not batches or (failure := await self._write(batches)) is None:
            return
        if len(batches) == 1:
            self._not_written(batches[0], failure)
            return
        for done, one in enumerate(batches):
            try:
                failure = await self._write([one])
            except asyncio.CancelledError:
                for later in batches[done + 1:]:  # not tried yet: kept for the flush that ``stop`` makes
                    self._not_written(later, None)
                raise
            if failure is not None:
                self._not_written(one, failure)

    async def _write(self, batches: list[Batch]) -> Exception | None:
        """Write ``batches`` in one unit of work; the failure, or None when written."""
        writing = self._writing = asyncio.ensure_future(
            self.database.run(lambda session: _log_batches(session, batches)))
        try:  # shielded: stopping the writer must not cut a write short (its entries would be lost or written twice)
            await asyncio.shield(writing)
        except asyncio.CancelledError:
            raise  # the write goes on by itself; ``stop`` waits for it, then flushes
        except Exception as exc:  # noqa: BLE001 -- the caller keeps the entries or, past the retries, drops them
            return exc
        return None

    def _not_written(self, batch: Batch, failure: Exception | None) -> None:
        """Keep entries that were not written, in order, for the next write; a session whose entries failed
        ``MAX_LOG_WRITE_FAILURES`` times in a row alone loses them (recorded as a fault), not everyone's loop."""
        _, teleop, entries = batch
        log = teleop.log
        if failure is not None:
            log.write_failures += 1
            if log.write_failures >= MAX_LOG_WRITE_FAILURES:
                log.write_failures = 0
                self.faults.record("teleop_log", failure, participant=teleop.participant_key)
                log.event(time.monotonic(), LogEvent.LOG_LOST, entries=len(entries))
                return
        log.put_back(entries)


# -- the database side -----------------------------------------------------------------------------------------------
_LOG_COLUMNS = load_only(Participant.token_hash, Participant.study_id, Participant.status, Participant.last_seen_at)


def _log_batches(session: Session, batches: list[Batch]) -> None:
    """Several sockets' entries, their participants read in one query (only the columns logging needs). A session
    deleted meanwhile (a preview) has nothing to log against: its entries go."""
    hashes = {token: sessions.hash_token(token) for token, _, _ in batches}
    found = session.scalars(select(Participant).where(Participant.token_hash.in_(set(hashes.values())))
                            .options(_LOG_COLUMNS))
    participants = {p.token_hash: p for p in found}
    for token, teleop, batch in batches:
        if (participant := participants.get(hashes[token])) is not None:
            _log_entries(session, participant, teleop, batch)


def _log_entries(session: Session, participant: Participant, teleop: TeleopSession,
                 batch: list[dict[str, Any]]) -> None:
    if not batch:
        return
    sessions.touch(participant)
    key = teleop.key
    log_event(session, participant.study_id, participant.id, EventKind.TELEOP_LOG, **key.ref._asdict(),
              entries=batch)
