"""Rate limits: in-memory token buckets keyed by a string (a client address, a study, a teleoperation).

Each bucket holds ``burst`` tokens and refills continuously at ``per_second``:
a burst passes, then one more request every ``1 / per_second`` seconds. The
join limits hold a minute's allowance (``RateLimiter.minutely``). The counts
live in the process: with several server processes each counts its own.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from threading import Lock

#: Buckets kept at most; the least recently used are dropped first (a dropped bucket starts full again).
MAX_KEYS = 100_000


class RateLimiter:
    def __init__(self, per_second: float, burst: float, max_keys: int = MAX_KEYS):
        self.per_second, self.burst, self.max_keys = per_second, float(burst), max_keys
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # key -> (tokens, monotonic time)
        self._lock = Lock()

    @classmethod
    def minutely(cls, per_minute: int, max_keys: int = MAX_KEYS) -> RateLimiter:
        """``per_minute`` requests at once, then refilled over a minute."""
        return cls(per_minute / 60.0, per_minute, max_keys)

    @property
    def per_minute(self) -> float:
        return self.per_second * 60.0

    def take(self, key: str, now: float | None = None) -> float:
        """Count one request for ``key``: 0 if it is allowed, else the seconds until one would be (nothing taken)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens, then = self._buckets.pop(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - then) * self.per_second)
            wait = 0.0 if tokens >= 1 else (1 - tokens) / self.per_second
            self._buckets[key] = (tokens - 1 if wait == 0 else tokens, now)
            while len(self._buckets) > self.max_keys:
                self._buckets.popitem(last=False)
        return wait
