"""Event-loop watch for benchmarks: what stops a ``trustlab serve`` process's event loop, and for how long.

Loaded by Python at start-up when this directory is on ``PYTHONPATH`` (``bench_load.py --watch-loop`` puts it
there for the server only); active when ``TRUSTLAB_LOOP_WATCH`` names a file and the process is ``trustlab
serve`` or its view process (which writes to that name with ``.view`` added). It records, without touching the server's
code:

- every callback of the main thread's event loop that ran longer than ``LONG_S``, with the stacks a sampling
  thread saw in it (every ``SAMPLE_S``; a callback stopped by a garbage collection or a C call holding the
  interpreter lock shows one sample, wherever it was);
- every garbage collection: per generation, how many, total and longest pause;
- every HTTP request's time in the server, from the start of its ASGI call to its response's last byte handed to
  the socket (uvicorn's h11 cycle): set against the bots' latencies, it tells the server's share of the tail
  from the bots' own (their processes share the machine);
- every iteration of the main thread's event loop: its work, from its selector's return to its end (every
  callback ready then). A message that arrives during an iteration is read in the next one and answered in the
  one after (uvicorn's protocol wakes the handler's task), so it waits for the rest of the iteration it arrived
  in and the next one: the share of the run spent in long iterations is the share of arrivals that wait long.

The summary is written to the file every ``WRITE_EVERY_S`` and at exit. Stacks are read from frame objects,
not through ``linecache``, which would load the source of every module into the heap being measured.
"""

import collections
import os
import sys
import threading
import time

LONG_S = 0.040
SAMPLE_S = 0.005
LONG_PAUSE_S = 0.020
WRITE_EVERY_S = 10.0
STACK_DEPTH = 14


def _view_process() -> bool:
    """A server's view process (``python -m server.viewer.process``, ``server.viewer.remote``)."""
    return "server.viewer.process" in getattr(sys, "orig_argv", [])


def _active() -> bool:
    return bool(os.environ.get("TRUSTLAB_LOOP_WATCH")) and (sys.argv[1:2] == ["serve"] or _view_process())


def _start(out: str) -> None:
    import atexit
    import gc

    main_id = threading.main_thread().ident
    assert main_id is not None, "the main thread has started"
    long_calls: list[tuple[float, float, list[tuple[str, int]]]] = []  # (duration, when, stacks)
    pauses: dict[int, list[float]] = {0: [], 1: [], 2: []}
    started = [0.0]

    oldest: list[str] = []  # what the oldest generation held at its last collection
    long_pauses: list[tuple[float, int, float]] = []  # (when, generation, pause) of pauses over LONG_PAUSE_S
    born = time.perf_counter()

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
            return
        pause = time.perf_counter() - started[0]
        pauses[info["generation"]].append(pause)
        if pause > LONG_PAUSE_S:
            long_pauses.append((started[0] - born, info["generation"], pause))
        if info["generation"] == 2:
            held = collections.Counter(type(o).__name__ for o in gc.get_objects(generation=2))
            oldest[:] = [f"{sum(held.values())} objects; " + ", ".join(f"{k} {n}" for k, n in held.most_common(12))]

    gc.callbacks.append(on_gc)
    requests = _time_requests()
    iterations = _time_iterations(main_id)

    def stack_of(frame) -> str:
        parts: list[str] = []
        while frame is not None and len(parts) < STACK_DEPTH:
            code = frame.f_code
            parts.append(f"{os.path.basename(code.co_filename)}:{code.co_name}:{frame.f_lineno}")
            frame = frame.f_back
        return " < ".join(parts)

    def callback_frame(frame):
        """The frame of the event loop's callback (``Handle._run``) that ``frame`` runs in, if any."""
        while frame is not None:
            code = frame.f_code
            if code.co_name == "_run" and code.co_filename.endswith("asyncio/events.py"):
                return frame
            frame = frame.f_back
        return None

    def write() -> None:
        lines = []
        for generation, times in pauses.items():
            if times:
                ordered = sorted(times)
                lines.append(f"gc generation {generation}: {len(ordered)} collections, {sum(ordered):.2f} s in all, "
                             f"longest {ordered[-1] * 1000:.0f} ms, p90 {ordered[int(0.9 * len(ordered))] * 1000:.1f} "
                             "ms")
        if long_pauses:
            lines.append(f"gc pauses over {LONG_PAUSE_S * 1000:.0f} ms (s since start: generation, ms): " + ", ".join(
                f"{when:.0f}: {generation}, {pause * 1000:.0f}" for when, generation, pause in long_pauses[:60]))
        if oldest:
            lines.append(f"gc generation 2 at its last collection: {oldest[0]}")
        if requests:
            ordered = sorted(seconds for _, seconds in requests)

            def quantile_ms(values: list[float], q: float) -> float:
                return values[min(len(values) - 1, int(q * len(values)))] * 1000

            lines.append(f"requests in the server: {len(ordered)}, p50 {quantile_ms(ordered, 0.5):.1f} ms, p95 "
                         f"{quantile_ms(ordered, 0.95):.1f} ms, p99 {quantile_ms(ordered, 0.99):.1f} ms, longest "
                         f"{ordered[-1] * 1000:.0f} ms")
            by_route = collections.defaultdict(list)
            for route, seconds in sorted(requests, key=lambda timed: timed[1]):  # each route's times in order
                by_route[route].append(seconds)
            busiest = sorted(by_route.items(), key=lambda kv: -len(kv[1]))[:8]
            lines.append("requests in the server by route, p50 / p99 ms: " + ", ".join(
                f"{route} {quantile_ms(times, 0.5):.0f} / {quantile_ms(times, 0.99):.0f}" for route, times in busiest))
        if iterations.count:
            lines.append(iterations.summary())
        calls = sorted(long_calls, key=lambda c: -c[0])
        lines.append(f"event-loop callbacks over {LONG_S * 1000:.0f} ms: {len(calls)}, "
                     f"{sum(d for d, _, _ in calls):.2f} s in all")
        for duration, at, stacks in calls[:40]:
            lines.append(f"  {duration * 1000:.0f} ms at {at:.0f} s")
            lines += [f"    {n}x {stack}" for stack, n in stacks]
        with open(out, "w") as fh:
            fh.write("\n".join(lines) + "\n")

    def watch() -> None:
        stacks: collections.Counter[str] = collections.Counter()
        current, since, written = None, 0.0, time.monotonic()
        while True:
            time.sleep(SAMPLE_S)
            if time.monotonic() - written > WRITE_EVERY_S:
                write()
                written = time.monotonic()
            try:
                frame = sys._current_frames().get(main_id)
                running = callback_frame(frame)
                now = time.perf_counter()
                if running is not current:
                    if current is not None and now - since > LONG_S:
                        long_calls.append((now - since, since - born, stacks.most_common(3)))
                    current, since, stacks = running, now, collections.Counter()
                if running is not None:
                    stacks[stack_of(frame)] += 1
            except Exception:  # noqa: BLE001 -- another thread's frames change under us: skip this sample
                continue

    atexit.register(write)
    _write_after_shutdown(write)
    threading.Thread(target=watch, name="loop-watch", daemon=True).start()


def _write_after_shutdown(write) -> None:
    """Also write once uvicorn has shut down: after a graceful shutdown on SIGTERM uvicorn raises the signal
    again, and the process ends by it, without running ``atexit`` handlers."""
    from uvicorn import server

    shutdown = server.Server.shutdown

    async def shutdown_then_write(self, *args, **kwargs):
        try:
            return await shutdown(self, *args, **kwargs)
        finally:
            write()

    server.Server.shutdown = shutdown_then_write  # type: ignore[method-assign]  # patched to write on exit


class Iterations:
    """The event loop's iterations' work, in 1 ms bins (a list of every iteration would grow by thousands a
    second in the process being measured)."""

    BINS_MS = 1000

    def __init__(self) -> None:
        self.count, self.seconds, self.longest = 0, 0.0, 0.0
        self.first: float | None = None  # when the first iteration ended
        self.bins = [0] * (self.BINS_MS + 1)  # iterations by whole milliseconds (the last: that long or more)
        self.bin_seconds = [0.0] * (self.BINS_MS + 1)

    def add(self, seconds: float) -> None:
        index = min(self.BINS_MS, int(seconds * 1000))
        if self.first is None:
            self.first = time.perf_counter()
        self.count += 1
        self.seconds += seconds
        self.longest = max(self.longest, seconds)
        self.bins[index] += 1
        self.bin_seconds[index] += seconds

    def quantile_ms(self, q: float) -> int:
        """The iteration work's q-quantile, to the millisecond below."""
        seen, wanted = 0, q * self.count
        for ms, n in enumerate(self.bins):
            seen += n
            if seen >= wanted:
                return ms
        return self.BINS_MS

    def seconds_over(self, ms: int) -> float:
        return sum(self.bin_seconds[ms:])

    def summary(self) -> str:
        run = max(time.perf_counter() - (self.first or 0.0), 1e-9)
        shares = ", ".join(f"{over} ms {100 * self.seconds_over(over) / run:.1f} %" for over in (10, 20, 40))
        return (f"loop iterations: {self.count}, busy {100 * self.seconds / run:.0f} % of {run:.0f} s; work per "
                f"iteration p50 {self.quantile_ms(0.5)} ms, p99 {self.quantile_ms(0.99)} ms, longest "
                f"{self.longest * 1000:.0f} ms; share of the run in iterations of at least {shares}")


def _time_iterations(main_id: int) -> Iterations:
    """Wrap asyncio's loop iteration (``BaseEventLoop._run_once``) to record, for the main thread's loop, the work
    of each: from its selector's return to the iteration's end."""
    from asyncio import base_events

    iterations = Iterations()
    run_once = base_events.BaseEventLoop._run_once  # type: ignore[attr-defined]  # private: timed here

    def timed_run_once(self):
        if threading.get_ident() != main_id:
            return run_once(self)
        selector = self._selector
        if not getattr(selector, "_loop_watch", False):
            select = selector.select

            def timed_select(timeout=None):
                events = select(timeout)
                selector._loop_watch_returned = time.perf_counter()
                return events
            selector.select, selector._loop_watch = timed_select, True
        run_once(self)
        returned = getattr(selector, "_loop_watch_returned", None)
        if returned is not None:
            iterations.add(time.perf_counter() - returned)

    base_events.BaseEventLoop._run_once = timed_run_once  # type: ignore[attr-defined]  # private: timed here
    return iterations


def _time_requests() -> list[tuple[str, float]]:
    """Wrap uvicorn's h11 request cycle to record each request's route and seconds in the server (the list it
    fills)."""
    from uvicorn.protocols.http import h11_impl

    from server.harness.client import route_name

    seconds: list[tuple[str, float]] = []
    cycle = h11_impl.RequestResponseCycle
    run_asgi, send = cycle.run_asgi, cycle.send

    async def timed_run_asgi(self, app):
        self._loop_watch_start = time.perf_counter()
        return await run_asgi(self, app)

    async def timed_send(self, message):
        await send(self, message)
        if message.get("type") == "http.response.body" and not message.get("more_body", False):
            start = getattr(self, "_loop_watch_start", None)
            if start is not None:
                seconds.append((route_name(self.scope.get("method", ""), self.scope.get("path", "")),
                                time.perf_counter() - start))

    cycle.run_asgi, cycle.send = timed_run_asgi, timed_send  # type: ignore[method-assign]  # timed here
    return seconds


if _active():  # a view process writes its own file next to its server's
    _start(os.environ["TRUSTLAB_LOOP_WATCH"] + (".view" if _view_process() else ""))
