"""Background sweep: resolve trials whose deadlines passed and mark idle sessions abandoned; erase personal data due.

Requests already apply due transitions for the session they touch; the
sweep covers participants who went quiet (closed tab, lost connection), so
their data is complete and counterbalancing stops counting them.

Every ``RETENTION_SWEEP_S`` it also applies the studies' retention rules (config ``privacy``): the personal fields
of ended sessions that are due are erased (``server.services.erasure.erase_due``; idempotent).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from datetime import datetime, timedelta

from sqlalchemy import or_, select

from experiment.flow import ParticipantStatus, TrialStage
from server.app_services import Services
from server.db.units import SessionFactory
from server.faults import FaultLog
from server.models import Participant, Trial, utcnow
from server.services.erasure import erase_due
from server.services.sessions import abandon, runtime_of
from server.services.studies import RuntimeCache
from server.services.trials import AttemptPlanner, advance

log = logging.getLogger("trustlab.sweeper")
#: Below the smallest allowed idle timeout, so no candidate is missed.
MIN_IDLE_S = 30
#: Seconds between two runs of the retention rules (they count in days).
RETENTION_SWEEP_S = 60.0


async def sweep_forever(services: Services) -> None:
    faults = services.faults
    retention_due = time.monotonic()
    while True:
        await asyncio.sleep(services.settings.sweep_interval_s)
        try:
            await services.database.in_thread(functools.partial(
                sweep, services.database, services.runtimes, services.hub, faults=faults))
            if time.monotonic() >= retention_due:
                retention_due = time.monotonic() + RETENTION_SWEEP_S
                await services.database.in_thread(sweep_retention, services.database)
        except Exception as exc:  # noqa: BLE001 -- e.g. the database is unreachable: the next round retries
            faults.record("sweeper", exc)


def sweep_retention(factory: SessionFactory, now: datetime | None = None) -> int:
    """Erase the personal fields that the studies' retention rules say are due, in one transaction; returns how
    many sessions (``server.services.erasure.erase_due``)."""
    with factory.begin() as session:
        return erase_due(session, now or utcnow())


def sweep(factory: SessionFactory, runtimes: RuntimeCache, planner: AttemptPlanner,
          now: datetime | None = None, *, faults: FaultLog | None = None) -> int:
    """One sweep; returns how many participants changed.

    Each participant in a transaction of their own: one whose sweep fails (a bug, a value no check foresaw) is
    rolled back, recorded in ``faults`` (or logged) and left for the next round, and every other participant is
    still swept."""
    now = now or utcnow()
    changed = 0
    for participant_id in _candidates(factory, now):
        try:
            changed += _sweep_one(factory, runtimes, planner, participant_id, now)
        except Exception as exc:  # contained to this participant
            if faults is None:
                log.exception("sweeping participant %s failed", participant_id)
            else:
                faults.record("sweeper", exc, participant=str(participant_id))
    return changed


def _sweep_one(factory: SessionFactory, runtimes: RuntimeCache, planner: AttemptPlanner, participant_id: int,
               now: datetime) -> bool:
    with factory.begin() as session:
        participant = session.get(Participant, participant_id, with_for_update=True)
        if participant is None or participant.status != ParticipantStatus.ACTIVE:
            return False
        runtime = runtime_of(session, runtimes, participant)
        idle = timedelta(seconds=runtime.config.timing.idle_timeout_s)
        if now - participant.last_seen_at > idle:
            abandon(session, participant, now, runtime)
        else:
            advance(session, participant, runtime, now=now, planner=planner)
        return True


def _candidates(factory: SessionFactory, now: datetime) -> list[int]:
    with factory.begin() as session:
        idle = select(Participant.id).where(Participant.status == ParticipantStatus.ACTIVE,
                                            Participant.last_seen_at < now - timedelta(seconds=MIN_IDLE_S))
        due = (select(Trial.participant_id).join(Participant, Participant.id == Trial.participant_id)
               .where(Participant.status == ParticipantStatus.ACTIVE, or_(
                   (Trial.stage == TrialStage.PRESENTING) & (Trial.scene_deadline_at <= now),
                   (Trial.stage == TrialStage.DECISION) & (Trial.decision_deadline_at <= now),
                   (Trial.stage == TrialStage.ATTEMPT) & (Trial.attempt_end_at <= now),
                   (Trial.stage == TrialStage.TELEOP) & (Trial.teleop_deadline_at <= now))))
        return sorted(set(session.scalars(idle)) | set(session.scalars(due)))
