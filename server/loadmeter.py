"""How the server is keeping up, in figures an experimenter and an operator can act on.

One server process serves every participant of its sessions on one event loop. When it is short of capacity,
its 30 Hz world loop starts ticks late and the 3D views skip ticks (``server.viewer.manager.ViewPacer``) before
participants' requests slow down. ``record_load_forever`` samples those counters once a second;
``GET /api/admin/server/load`` (``server.routes.admin``) reports the last minute, with a status in words, and
``benchmarks/bench_load.py`` prints it next to the client's own figures.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from server.app_services import Services
from server.faults import RECENT_S, Fault

#: How often the counters are sampled (s), and the stretch the report covers (s).
LOAD_SAMPLE_S = 1.0
LOAD_WINDOW_S = 60.0
#: Status thresholds: the share of world ticks the 3D views skipped, and of ticks that started late. From
#: ``BUSY_SKIPPED`` the dashboard warns and the log says so too (``views_skip_too_many``): below it, skipped ticks
#: are the pacer doing its job (a few tenths of a percent are usual with every view open) and not worth a warning.
BUSY_SKIPPED = 0.02
OVERLOADED_SKIPPED = 0.25
BUSY_LATE = 0.10
#: Overloaded as well when the world loop ticks below this share of its rate.
OVERLOADED_TICK_SHARE = 0.8


@dataclass(frozen=True)
class LoadSample:
    """The process's counters at one time (monotonic s); counts since the server started."""

    at: float
    ticks: int
    late_ticks: int
    view_ticks: int
    view_ticks_skipped: int
    latest_start_s: float  # the latest start of a tick since the previous sample


@dataclass(frozen=True)
class LoadFigures:
    window_s: float
    ticks_per_s: float
    late_share: float
    latest_start_s: float
    skipped_share: float


class LoadHistory:
    """The samples of the last ``LOAD_WINDOW_S`` and the figures over them (pure: no clock, no server)."""

    def __init__(self, window_s: float = LOAD_WINDOW_S):
        self.window_s = window_s
        self._samples: deque[LoadSample] = deque()

    def record(self, sample: LoadSample) -> None:
        self._samples.append(sample)
        while len(self._samples) > 2 and sample.at - self._samples[1].at >= self.window_s:
            self._samples.popleft()

    def figures(self) -> LoadFigures | None:
        """Over the samples kept (None before two samples)."""
        if len(self._samples) < 2:
            return None
        first, last = self._samples[0], self._samples[-1]
        span = last.at - first.at
        ticks = last.ticks - first.ticks
        view_ticks = last.view_ticks - first.view_ticks
        return LoadFigures(
            window_s=span, ticks_per_s=ticks / span if span > 0 else 0.0,
            late_share=(last.late_ticks - first.late_ticks) / ticks if ticks else 0.0,
            latest_start_s=max(s.latest_start_s for s in list(self._samples)[1:]),
            skipped_share=(last.view_ticks_skipped - first.view_ticks_skipped) / view_ticks if view_ticks else 0.0)


def views_skip_too_many(skipped_share: float) -> bool:
    """Whether the 3D views skipped enough of the world's ticks to warn about: the dashboard's "busy" (or worse)
    and the server log's warning (``server.viewer.manager``) use this one threshold."""
    return skipped_share >= BUSY_SKIPPED


def load_status(figures: LoadFigures | None, world_hz: float, *, world_loop: bool = True,
                faults: Sequence[Fault] = ()) -> tuple[str, str]:
    """(``fault`` | ``ok`` | ``busy`` | ``overloaded`` | ``starting`` | ``off``, what it means in words).

    Recent contained faults (``server.faults``) come first: a loop that failed and restarted also ticks slow for a
    moment, and that is a fault to report, not a reason to cap participants."""
    if faults:
        loops = sorted({fault.loop for fault in faults})
        people = len({fault.participant for fault in faults if fault.participant})
        return "fault", (
            f"The server contained {len(faults)} fault{'s' if len(faults) != 1 else ''} in the last "
            f"{RECENT_S / 60:.0f} minutes ({', '.join(loops)}"
            + (f"; {people} participant{'s' if people != 1 else ''} concerned" if people else "")
            + f"; latest: {faults[-1].what}). Every other participant went on. This is a fault, not a lack of "
            "capacity: see the server log, and tell the developers.")
    if not world_loop:
        return "off", "This server process runs no world loop (TRUSTLAB_WORLD_LOOP=false): there is nothing to measure."
    if figures is None:
        return "starting", "The server has just started: its figures come after a few seconds."
    remedy = ("Cap the study's concurrent participants (recruitment.max_active_participants) or run more server "
              "processes (serve --workers, PostgreSQL).")
    if figures.ticks_per_s < OVERLOADED_TICK_SHARE * world_hz:
        return "overloaded", (
            f"The server is short of capacity: its world loop ran {figures.ticks_per_s:.0f} times a second instead of "
            f"{world_hz:.0f} (the robot moves less smoothly in the 3D views and under teleoperation) and participants' "
            f"requests wait. {remedy}")
    if figures.skipped_share >= OVERLOADED_SKIPPED:
        return "overloaded", (
            f"The server is short of capacity: the 3D views skipped {_percent(figures.skipped_share)} of the world's "
            f"updates and participants' requests wait. {remedy}")
    if views_skip_too_many(figures.skipped_share):
        return "busy", (
            f"The server is busy: the 3D views skip some frames ({_percent(figures.skipped_share)} of the world's "
            "updates) so that participants' requests and teleoperation keep their pace.")
    if figures.late_share >= BUSY_LATE:
        return "busy", (
            f"The server is busy: {_percent(figures.late_share)} of the world's updates came late (by "
            f"{1000 * figures.latest_start_s:.0f} ms at most); the 3D views still show every one.")
    return "ok", "The server keeps up: the 3D views show every update of the world."


def _percent(share: float) -> str:
    return f"{100 * share:.0f} %"


def sample_of(services: Services, at: float) -> LoadSample:
    hub, viewers = services.hub, services.viewers
    return LoadSample(at=at, ticks=hub.ticks, late_ticks=hub.late_ticks, view_ticks=viewers.ticks_seen,
                      view_ticks_skipped=viewers.ticks_skipped, latest_start_s=hub.take_latest_start())


async def record_load_forever(services: Services) -> None:
    """Sample the counters every ``LOAD_SAMPLE_S`` into the ``load_history``."""
    loop = asyncio.get_running_loop()
    while True:
        services.load_history.record(sample_of(services, loop.time()))
        await asyncio.sleep(LOAD_SAMPLE_S)
