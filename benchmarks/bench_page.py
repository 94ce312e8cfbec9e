"""The participant page's responsiveness while the 3D view draws, in Chromium with software rendering and the CPU
throttled (issue 13 item 7; SPEC §8).

Run: ``python benchmarks/bench_page.py [--throttle 4] [--seconds 20] [--presses 16] [--modes paced unpaced blocked]``.

A fresh ``trustlab serve`` (subprocess, SQLite) runs a study whose first practice trial is a request for help,
so the page goes straight to teleoperation. For each mode, back to back, a fresh Debian Chromium
(``/usr/bin/chromium`` headless, ``--disable-gpu``: WebGL drawn by SwiftShader, the compositor in software) opens
the participant page, the CPU is throttled ``--throttle``× through the DevTools protocol
(``Emulation.setCPUThrottlingRate``), the page reaches the teleoperation and, once the 3D view has loaded (or
failed to), the page is measured for ``--seconds`` while a key is pressed and released ``--presses`` times:

- ``unpaced``: the 3D view as viser draws it (pacing off: every animation frame), on screen;
- ``paced-3d``: the 3D view kept to a share of the main thread and held back while a key is held or just changed
  (``static/js/viewerpace.js``), and kept on screen (as for a participant who unticks the 2-D view);
- ``paced``: the page as shipped: as ``paced-3d``, and where the view's frames are too slow to steer by, the 2-D
  helper view replaces it during teleoperation and the 3D view pauses behind it;
- ``blocked``: the 3D view's URL refused, so the page shows its 2-D fallback view.

Measured in the page: how often a ``setInterval(…, 33)`` timer actually runs (Hz); the latency from a key event
(its ``timeStamp``) and from the moment the benchmark sent the key (wall clock, through the DevTools protocol) to
the page's ``input`` message leaving on the teleoperation socket (ms, key-down and key-up); the 3D view's frame
rate (frames it drew per second) and what a frame costs the main thread; long tasks (PerformanceObserver
``longtask``: count, share of the time, longest).
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from experiment.config import PracticeConfig, PracticeTrial, TimingConfig
from experiment.templates import demo
from server.harness.browser import BENCHMARK_ARGS, CHROMIUM, VIEWPORT
from server.harness.live import free_port, start_server

from results_log import append_result

KEYS = ("KeyA", "KeyD")  # left / right: the arm moves sideways, back and forth, and stays clear of the shelf
HOLD_S, GAP_S = 0.35, 0.45
MODES = ("unpaced", "paced-3d", "paced", "blocked")

#: Installed before the page's scripts: timestamps of key events and of every message sent on the teleop socket,
#: a 33 ms timer and a long-task observer. Everything is in performance.now() of the page (and its wall clock).
INSTRUMENT = """
(() => {
  if (window.top !== window) return;  // the viewer iframe is measured from the page
  const m = window.__bench = { keys: [], sends: [], ticks: 0, long: [], t0: performance.now() };
  addEventListener("keydown", (e) => {
    if (!e.repeat) m.keys.push(["down", e.code, e.timeStamp, performance.now()]);
  }, true);
  addEventListener("keyup", (e) => m.keys.push(["up", e.code, e.timeStamp, performance.now()]), true);
  const send = WebSocket.prototype.send;
  WebSocket.prototype.send = function (data) {
    if (this.url.endsWith("/teleop")) {
      const now = performance.now();
      try {
        const msg = JSON.parse(data);
        m.sends.push([msg.type, msg.seq, now, performance.timeOrigin + now]);
      } catch (_e) {}
    }
    return send.call(this, data);
  };
  setInterval(() => { m.ticks += 1; }, 33);
  new PerformanceObserver((list) => { for (const e of list.getEntries()) m.long.push([e.startTime, e.duration]); })
    .observe({ type: "longtask", buffered: true });
})();
"""

WINDOW = """(since) => { const m = window.__bench, p = window.__trustlab.viewerPace || null;
  return { now: performance.now(), ticks: m.ticks, long: m.long.filter(([s]) => s >= since),
           frames: p ? p.totalFrames : null, cost: p ? p.costMs : null,
           recent: p ? p.recent.slice() : null,
           viewer: window.__trustlab.viewer }; }"""


def study_config():
    practice = PracticeConfig(trials=[PracticeTrial(complexity="high", robot_action="ask")])
    timing = TimingConfig(decision_window_s=4.0, animation_speed=2.0, teleop_time_limit_s=300.0)
    return demo().model_copy(update={"practice": practice, "timing": timing})


def measure(playwright, url: str, slug: str, mode: str, args: argparse.Namespace, n: int) -> dict[str, Any]:
    browser = playwright.chromium.launch(executable_path=CHROMIUM, args=BENCHMARK_ARGS, headless=True)
    try:
        page = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.add_init_script(INSTRUMENT)
        if mode == "blocked":
            page.route(re.compile(r"/viewer/"), lambda route: route.abort())
        cdp = page.context.new_cdp_session(page)
        cdp.send("Emulation.setCPUThrottlingRate", {"rate": args.throttle})
        page.goto(f"{url}/join/{slug}?PROLIFIC_PID=bench-{mode}-{n}")
        page.get_by_role("button", name="I agree to take part").click(timeout=60_000)
        page.get_by_role("button", name=re.compile("^Continue")).click(timeout=60_000)
        page.wait_for_function("() => window.__trustlab.teleopClient && window.__trustlab.teleopClient.world",
                               timeout=120_000, polling=200)
        page.wait_for_function("() => window.__trustlab.viewer", timeout=120_000, polling=200)
        if args.no_helper:  # leave the 2-D helper view out (to tell its cost from the 3D view's)
            page.evaluate("() => { const p = window.__trustlab.teleopPanel; p.helper.draw = () => {}; "
                          "p.setHelperReason = () => {}; p.helperWanted = false; p.layoutHelper(); }")
        if mode in ("unpaced", "paced-3d"):  # the 3D view stays on screen while steering (never replaced)
            page.evaluate("() => { const p = window.__trustlab.teleopPanel; p.setHelperReason = () => {}; "
                          "p.helperReason = null; p.layoutHelper(); window.__trustlab.viewerPace.setPaused(false); }")
        if mode == "unpaced":
            page.evaluate("() => window.__trustlab.viewerPace.configure({budget: 1, maxFps: 0, busy: () => false})")
        time.sleep(args.settle)  # the view's first frames (and, paced, its resolution steps)
        if args.profile:
            cdp.send("Profiler.enable")
            cdp.send("Profiler.start")
        start = page.evaluate("() => performance.now()")
        before = page.evaluate(WINDOW, start)
        pressed: list[tuple[str, str, float]] = []
        end = time.monotonic() + args.seconds
        i = 0
        while time.monotonic() < end:
            if i < args.presses:
                key = KEYS[i % 2]
                pressed.append(("down", key, time.time()))
                page.keyboard.down(key)
                time.sleep(HOLD_S)
                pressed.append(("up", key, time.time()))
                page.keyboard.up(key)
                i += 1
            time.sleep(GAP_S)
        after = page.evaluate(WINDOW, start)
        if args.profile:
            print_profile(mode, cdp.send("Profiler.stop")["profile"])
        if args.verbose:
            print(f"  {mode}: frame costs (ms) {after['recent']}", flush=True)
        bench = page.evaluate("() => ({keys: window.__bench.keys, sends: window.__bench.sends})")
        return summarise(mode, before, after, bench, pressed, start, errors)
    finally:
        browser.close()


def print_profile(mode: str, profile: dict[str, Any], top: int = 15) -> None:
    """Self time of the page's main thread by function (sampled), the heaviest first."""
    nodes = {n["id"]: n["callFrame"] for n in profile["nodes"]}
    self_us: dict[tuple, float] = {}
    for sample, dt in zip(profile["samples"], profile["timeDeltas"], strict=True):
        frame = nodes[sample]
        key = (frame["functionName"] or "(anonymous)", frame["url"].rsplit("/", 1)[-1][:30], frame["lineNumber"])
        self_us[key] = self_us.get(key, 0.0) + dt
    total = sum(self_us.values()) or 1.0
    print(f"  {mode}: main-thread profile, self time")
    for key, us in sorted(self_us.items(), key=lambda kv: -kv[1])[:top]:
        print(f"    {100 * us / total:5.1f} %  {key[0]}  {key[1]}:{key[2]}")


def summarise(mode: str, before: dict, after: dict, bench: dict, pressed: list, start: float,
              errors: list[str]) -> dict[str, Any]:
    span_s = (after["now"] - before["now"]) / 1000
    inputs = [s for s in bench["sends"] if s[0] == "input" and s[2] >= start]
    keys = [k for k in bench["keys"] if k[3] >= start and k[1] in KEYS]
    # Each key event is followed by one input message (its new input state): pair them in order.
    event_ms, wall_ms = [], []
    for n, key in enumerate(keys):
        after_key = [s for s in inputs if s[2] >= key[3]]
        if not after_key:
            continue
        event_ms.append(after_key[0][2] - key[2])
        if n < len(pressed):
            wall_ms.append(after_key[0][3] - pressed[n][2] * 1000)
    long = after["long"]
    frames = (after["frames"] - before["frames"]) if after["frames"] is not None else None
    return {
        "mode": mode, "viewer": after["viewer"], "timer_hz": (after["ticks"] - before["ticks"]) / span_s,
        "key_event_ms": event_ms, "key_wall_ms": wall_ms, "key_events": len(keys), "inputs": len(inputs),
        "view_fps": frames / span_s if frames is not None else None, "frame_ms": after["cost"],
        "long_n": len(long), "long_share": sum(d for _, d in long) / (span_s * 1000),
        "long_max": max((d for _, d in long), default=0.0), "errors": errors,
    }


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    values = sorted(values)
    return values[min(len(values) - 1, round(q * (len(values) - 1)))]


def table(rows: list[dict[str, Any]], throttle: float) -> str:
    head = ("| 3D view | timer 33 ms: runs/s | key → input sent, p50 / p95 / max (ms) | same from the key sent "
            "(wall) p50 / max | view frames/s | view frame cost (ms) | long tasks: n, share, longest |")
    lines = [f"CPU throttled {throttle:g}×, Chromium software rendering, 1280×720", "", head,
             "|" + "---|" * 7]
    for r in rows:
        ev, wall = r["key_event_ms"], r["key_wall_ms"]
        fps = "—" if r["view_fps"] is None else f"{r['view_fps']:.1f}"
        cost = "—" if r["frame_ms"] is None else f"{r['frame_ms']:.0f}"
        lines.append(
            f"| {r['mode']} ({r['viewer']}) | {r['timer_hz']:.1f} | {pct(ev, .5):.0f} / {pct(ev, .95):.0f} / "
            f"{max(ev, default=float('nan')):.0f} ({len(ev)}/{r['key_events']}) | {pct(wall, .5):.0f} / "
            f"{max(wall, default=float('nan')):.0f} | {fps} | {cost} | {r['long_n']}, {100 * r['long_share']:.0f} %, "
            f"{r['long_max']:.0f} ms |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throttle", type=float, default=4.0)
    parser.add_argument("--seconds", type=float, default=20.0, help="measured time per mode")
    parser.add_argument("--settle", type=float, default=8.0, help="seconds after the view loaded, before measuring")
    parser.add_argument("--presses", type=int, default=16)
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--repeat", type=int, default=1, help="rounds over the modes, back to back")
    parser.add_argument("--json", type=Path, help="also write the raw results here")
    parser.add_argument("--verbose", action="store_true", help="print the view's last frame costs per mode")
    parser.add_argument("--no-helper", action="store_true", help="never draw the 2-D helper view")
    parser.add_argument("--profile", action="store_true", help="print where the page's main thread spent its time")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    tmp = Path(tempfile.mkdtemp(prefix="bench_page_"))
    port = free_port()
    with open(tmp / "server.log", "w+", encoding="utf-8") as log:
        process, token = start_server(f"sqlite:///{tmp / 'bench.db'}", port, log)
        url = f"http://127.0.0.1:{port}"
        rows = []
        try:
            response = httpx.post(f"{url}/api/admin/studies", headers={"Authorization": f"Bearer {token}"},
                                  json={"status": "open", "slug": "page-bench",
                                        "config": study_config().model_dump(mode="json")},
                                  timeout=30)
            response.raise_for_status()
            with sync_playwright() as playwright:
                for n in range(args.repeat):
                    for mode in args.modes:
                        row = measure(playwright, url, "page-bench", mode, args, n)
                        rows.append(row)
                        print(f"{mode}: timer {row['timer_hz']:.1f}/s, key p50 {pct(row['key_event_ms'], .5):.0f} ms,"
                              f" view {row['view_fps']} fps, long {100 * row['long_share']:.0f} %"
                              + (f", page errors: {row['errors']}" if row["errors"] else ""), flush=True)
        finally:
            process.terminate()
            process.wait(timeout=30)
    print()
    print(table(rows, args.throttle))
    append_result("bench_page.py", {"throttle": args.throttle, "seconds": args.seconds, "modes": args.modes,
                                    "repeat": args.repeat, "no_helper": args.no_helper}, {"rows": rows})
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
