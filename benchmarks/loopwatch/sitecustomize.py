"""Event-loop watch for benchmarks: what stops a ``trustlab serve`` process's event loop, and for how long.

Loaded by Python at start-up when this directory is on ``PYTHONPATH`` (``bench_load.py --watch-loop`` puts it
there for the server only); active when ``TRUSTLAB_LOOP_WATCH`` names a file and the process is ``trustlab
serve``. It records, without touching the server's code:

- every callback of the main thread's event loop that ran longer than ``LONG_S``, with the stacks a sampling
  thread saw in it (every ``SAMPLE_S``; a callback stopped by a garbage collection or a C call holding the
  interpreter lock shows one sample, wherever it was);
- every garbage collection: per generation, how many, total and longest pause.

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
WRITE_EVERY_S = 10.0
STACK_DEPTH = 14


def _active() -> bool:
    return bool(os.environ.get("TRUSTLAB_LOOP_WATCH")) and sys.argv[1:2] == ["serve"]


def _start(out: str) -> None:
    import atexit
    import gc

    main_id = threading.main_thread().ident
    long_calls: list[tuple[float, list[tuple[str, int]]]] = []
    pauses: dict[int, list[float]] = {0: [], 1: [], 2: []}
    started = [0.0]

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
        else:
            pauses[info["generation"]].append(time.perf_counter() - started[0])

    gc.callbacks.append(on_gc)

    def stack_of(frame) -> str:
        parts = []
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
                             f"longest {ordered[-1] * 1000:.0f} ms, p90 {ordered[int(0.9 * len(ordered))] * 1000:.1f} ms")
        calls = sorted(long_calls, key=lambda c: -c[0])
        lines.append(f"event-loop callbacks over {LONG_S * 1000:.0f} ms: {len(calls)}, "
                     f"{sum(d for d, _ in calls):.2f} s in all")
        for duration, stacks in calls[:40]:
            lines.append(f"  {duration * 1000:.0f} ms")
            lines += [f"    {n}x {stack}" for stack, n in stacks]
        with open(out, "w") as fh:
            fh.write("\n".join(lines) + "\n")

    def watch() -> None:
        current, since, stacks, written = None, 0.0, collections.Counter(), time.monotonic()
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
                        long_calls.append((now - since, stacks.most_common(3)))
                    current, since, stacks = running, now, collections.Counter()
                if running is not None:
                    stacks[stack_of(frame)] += 1
            except Exception:  # another thread's frames change under us: skip this sample
                continue

    atexit.register(write)
    threading.Thread(target=watch, name="loop-watch", daemon=True).start()


if _active():
    _start(os.environ["TRUSTLAB_LOOP_WATCH"])
