"""Faults contained in the server's background loops, and the supervisor that keeps those loops running.

A failure in one participant's part of a loop (their arm's step in the world loop, their row in the sweep, their
teleoperation log's write) is caught where it happens, logged, and recorded here; the loop goes on with everyone
else. A failure of a loop as a whole restarts it (``supervised``). The load report (``server.loadmeter``) shows
recent faults as a status of their own, so an experimenter does not read them as the server being short of
capacity.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

log = logging.getLogger("trustlab.faults")

#: Faults kept for the load report (the oldest go first), and how long one counts as recent (s).
MAX_FAULTS = 200
RECENT_S = 300.0
#: The same fault (loop, participant, exception type) is logged with its traceback at most once this often (s); it
#: is still counted each time. A fault that repeats every tick must not flood the log.
LOG_REPEAT_S = 60.0
#: A loop that failed as a whole starts again after this long (s), so a fault that repeats at once cannot spin.
RESTART_DELAY_S = 1.0


@dataclass(frozen=True)
class Fault:
    loop: str  # "world", "sweeper", "teleop_log", "load"
    at: float  # monotonic s
    what: str  # the exception's type and message, shortened
    participant: str | None  # the participant's public id when one participant's part failed


class FaultLog:
    """The recent contained faults of this process (thread-safe enough: appends and reads of a deque)."""

    def __init__(self, max_faults: int = MAX_FAULTS):
        self._faults: deque[Fault] = deque(maxlen=max_faults)
        self._logged: dict[tuple[str, str | None, str], float] = {}
        self.total = 0

    def record(self, loop: str, exc: BaseException, *, participant: str | None = None) -> None:
        """Keep ``exc`` for the load report, and log it with its traceback (once a minute for a repeating one)."""
        now = time.monotonic()
        self.total += 1
        self._faults.append(Fault(loop, now, f"{type(exc).__name__}: {str(exc)[:200]}", participant))
        key = (loop, participant, type(exc).__name__)
        if now - self._logged.get(key, -LOG_REPEAT_S) >= LOG_REPEAT_S:
            if len(self._logged) > MAX_FAULTS:
                self._logged.clear()
            self._logged[key] = now
            who = f" (participant {participant})" if participant else ""
            log.error("%s: contained a fault%s; the loop goes on", loop, who, exc_info=exc)

    def recent(self, within_s: float = RECENT_S, now: float | None = None) -> list[Fault]:
        now = time.monotonic() if now is None else now
        return [fault for fault in list(self._faults) if now - fault.at <= within_s]


async def supervised(loop: str, run: Callable[[], Awaitable[None]], faults: FaultLog,
                     restart_delay_s: float = RESTART_DELAY_S) -> None:
    """Run ``run()`` until it returns or is cancelled, starting it again (after ``restart_delay_s``) whenever it
    fails: a loop that every participant depends on never stops silently."""
    while True:
        try:
            await run()
            return
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # noqa: BLE001 -- recorded and logged; the loop starts again
            faults.record(loop, exc)
        await asyncio.sleep(restart_delay_s)
