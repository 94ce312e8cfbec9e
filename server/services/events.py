"""The client event log's budget: how often a session may post events and how much it may store in all.

A page writes a few hundred events per block (``static/js/events.js``); a hostile or broken client could write
without end, filling the database and slowing every other participant. Two limits stop that:

- a rate: ``event_rate_per_s`` requests per second per session on average, ``event_rate_burst`` at once (429 with
  Retry-After past it, answered before the database is touched);
- a budget: ``event_budget_events`` events and ``event_budget_bytes`` bytes of payload (as stored JSON) per
  session in all (413, code ``event_budget_spent``, past it). Nothing of the study (trials, answers) depends on
  events, so a session past its budget goes on; the page drops a refused batch.

What a session has stored is counted once from the database (the first time this process sees the session) and
then kept in memory, under the participant's row lock (``open_session(lock=True)``): no request sums a session's
events. With several server processes each counts its own additions on top of what was stored when it first saw
the session, so a session could store at most (processes x budget); a rolled-back batch is counted anyway (the
count errs towards refusing).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from threading import Lock

from sqlalchemy import Text, cast, func, select
from sqlalchemy.orm import Session

from experiment.events import CLIENT_KIND_PREFIX
from server.errors import RateLimited, TooLarge
from server.models import Event
from server.ratelimit import MAX_KEYS, RateLimiter
from server.settings import Settings


class EventBudgetSpent(TooLarge):
    """A session has stored as many client events (or payload bytes) as it may; more are refused, nothing else."""

    code = "event_budget_spent"


class EventBudget:
    """Per-session rate limit and storage budget of posted client events (one per app)."""

    def __init__(self, settings: Settings, max_keys: int = MAX_KEYS) -> None:
        self.max_events, self.max_bytes = settings.event_budget_events, settings.event_budget_bytes
        self.limiter = RateLimiter(settings.event_rate_per_s, settings.event_rate_burst, max_keys=max_keys)
        self._stored: OrderedDict[int, tuple[int, int]] = OrderedDict()  # participant id -> (events, bytes)
        self._lock = Lock()
        self.max_keys = max_keys

    def take_request(self, token: str) -> None:
        """Count one request of the session behind ``token``; ``RateLimited`` (429, Retry-After) past the rate."""
        if wait := self.limiter.take(token):
            raise RateLimited(f"too many event requests from this session (at most {self.limiter.per_second:g} a "
                              f"second on average); retry in {math.ceil(wait)} s", retry_after_s=math.ceil(wait))

    def spend(self, session: Session, participant_id: int, events: int, payload_bytes: int) -> None:
        """Count ``events`` events of ``payload_bytes`` bytes for the participant, or raise ``EventBudgetSpent``
        (nothing counted) if they would pass the budget. Call with the participant's row locked."""
        with self._lock:
            stored = self._stored.pop(participant_id, None)
        if stored is None:
            stored = stored_events(session, participant_id)
        n, size = stored
        if n + events > self.max_events or size + payload_bytes > self.max_bytes:
            self._keep(participant_id, stored)
            raise EventBudgetSpent(
                f"this session has stored its budget of client events ({n} events, {size} bytes of payload; at most "
                f"{self.max_events} events and {self.max_bytes} bytes): these {events} were not stored. The study "
                "goes on; events are not needed for it", events_stored=n, bytes_stored=size)
        self._keep(participant_id, (n + events, size + payload_bytes))

    def _keep(self, participant_id: int, stored: tuple[int, int]) -> None:
        with self._lock:
            self._stored[participant_id] = stored
            while len(self._stored) > self.max_keys:
                self._stored.popitem(last=False)


def stored_events(session: Session, participant_id: int) -> tuple[int, int]:
    """The participant's stored client events: how many, and their payloads' bytes as stored JSON text."""
    n, size = session.execute(
        select(func.count(), func.coalesce(func.sum(func.length(cast(Event.payload, Text))), 0))
        .where(Event.participant_id == participant_id, Event.kind.startswith(CLIENT_KIND_PREFIX))).one()
    return int(n), int(size)
