"""Many bots at once: against a server in process or at a URL, every error counted, the measurements summed up.

``run_remote_bots`` is what ``trustlab bots`` and the load benchmark (``benchmarks/bench_load.py``) run.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import httpx

from experiment.iohmm import IOHMMParams
from server.harness.bots import Bot, SceneDisplay
from server.harness.client import BotStats, SocketFactory, StudyFull, percentiles, remote_sockets


@dataclass
class BotRunSummary:
    participants: int
    completed: int
    errors: list[str]
    trials: int
    latency_ms: dict[str, float]
    teleop_ack_ms: dict[str, float]
    seconds: float
    rate_limited: int = 0
    stats: BotStats | None = None  # the raw measurements (not in to_dict)
    refused: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"participants": self.participants, "completed": self.completed, "errors": self.errors,
                "trials": self.trials, "latency_ms": self.latency_ms, "teleop_ack_ms": self.teleop_ack_ms,
                "seconds": self.seconds, "rate_limited": self.rate_limited, "refused": self.refused}


def run_bots(make_http: Callable[[], httpx.Client], sockets: SocketFactory, slug: str, model: IOHMMParams, *,
             participants: int, concurrency: int = 4, seed: int = 0, ramp_s: float = 0.0,
             progress: Callable[[int, int], None] | None = None,
             displays: Callable[[int], SceneDisplay] | None = None) -> BotRunSummary:
    """Run ``participants`` bots, ``concurrency`` at a time; every error is counted, none is raised.

    ``ramp_s`` spreads the arrivals: bot i starts ``i * ramp_s / participants`` seconds in (people do not all
    open the link in the same millisecond). ``displays(i)``, if given, is bot i's 3D view.
    """
    stats = BotStats()
    start = time.perf_counter()
    done = 0

    def one(index: int) -> None:
        nonlocal done
        time.sleep(max(0.0, start + index * ramp_s / participants - time.perf_counter()))
        with make_http() as http:
            bot = Bot(http, sockets, slug, model, seed, stats, external_id=f"bot-{seed}-{index:05d}",
                      display=displays(index) if displays is not None else None)
            try:
                bot.run()
            except StudyFull:
                stats.refused += 1
            except Exception as exc:  # noqa: BLE001 -- a bot's failure is data for the summary
                where = traceback.extract_tb(exc.__traceback__)[-1]
                stats.errors.append(f"bot {index}: {type(exc).__name__}: {exc} ({where.filename}:{where.lineno})")
        done += 1
        if progress:
            progress(done, participants)

    with ThreadPoolExecutor(max_workers=concurrency) as pool:
        list(pool.map(one, range(participants)))
    return BotRunSummary(participants, stats.completed, stats.errors, stats.trials, percentiles(stats.latencies_ms),
                         percentiles(stats.teleop_ack_ms), time.perf_counter() - start, stats.rate_limited, stats,
                         stats.refused)


def run_remote_bots(url: str, slug: str, model: IOHMMParams, *, participants: int, concurrency: int = 4,
                    seed: int = 0, ramp_s: float = 0.0, progress: Callable[[int, int], None] | None = None,
                    displays: Callable[[int], SceneDisplay] | None = None) -> BotRunSummary:
    """``run_bots`` against a running server at ``url`` (HTTP with httpx, websockets for teleoperation)."""
    base = url.rstrip("/")
    return run_bots(lambda: httpx.Client(base_url=base, timeout=30), remote_sockets(base), slug, model,
                    participants=participants, concurrency=concurrency, seed=seed, ramp_s=ramp_s, progress=progress,
                    displays=displays)
