"""Decision windows opened on a stale scene, counted from the screen (issue 37).

Run: ``python benchmarks/bench_stale_scene.py [--trials 30] [--throttles 1 4] [--pause 0]``.

A fresh ``trustlab serve`` (subprocess, SQLite) runs a study of one block of ``--trials`` items, half low and half
high complexity in a random order, where the robot always tries by itself and no questionnaire is asked. For each
CPU throttle, back to back, a fresh Debian Chromium (``/usr/bin/chromium`` headless, software WebGL) opens the
participant page at 1280×720 (throttled through ``Emulation.setCPUThrottlingRate``), agrees, and goes through the
items without ever intervening. The "Next item" pause is ``--pause`` seconds (0 by default: the worst case, the
next item's window right after the outcome; the study's default is 2 s).

At each decision window's opening (polled every 30 ms) the benchmark screenshots the view that showed the scene
(the 3D view, or the 2-D helper where the page fell back to it) and checks, independently of the page's code, that
the screen shows this item's scene:

- red obstacles on screen exactly when the item is of high complexity (share of the obstacles' red pixels), and
- in the 3D view, the magenta "collect this" marks where this item's target projects through the World camera
  (``server.viewer.cameras``): their centroid within ``TOLERANCE_PX`` of the projected span from the item to the
  arrow's top.

A window whose screenshot fails either check counts as opened on a stale scene (target: 0 of N). It also prints
how the windows were opened (``window_opened_by``) and the time from the window's opening to the screenshot.
"""

from __future__ import annotations

import argparse
import io
import re
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from PIL import Image

from experiment.config import AlwaysAutoSpec, PracticeConfig, TimingConfig
from experiment.schedule import CountsSchedule
from experiment.templates import demo
from experiment.world.trial import trial_scene
from server.harness.browser import BENCHMARK_ARGS, CHROMIUM, VIEWPORT, red_share
from server.harness.live import free_port, start_server
from server.viewer.cameras import VIEW_FOV_DEG, project, world_camera
from server.viewer.scene import ARROW_GAP, ARROW_HEAD, ARROW_SHAFT, MARKER_HEIGHT

from results_log import append_result

SLUG = "stale-bench"
#: Share of the view in the obstacles' red above which obstacles are on screen, and below which they are not.
RED_PRESENT, RED_ABSENT = 0.004, 0.002
#: Magenta pixels needed to locate the marker, and how far (px) its centroid may lie from the projected span.
MAGENTA_MIN = 30
TOLERANCE_PX = 40


def study_config(trials: int, pause_s: float):
    base = demo()
    block = base.blocks[0].model_copy(update={
        "schedule": CountsSchedule(n_low=trials // 2, n_high=trials - trials // 2), "policy": AlwaysAutoSpec(),
        "questionnaires_after": []})
    return base.model_copy(update={
        "practice": PracticeConfig(enabled=False), "blocks": [block], "questionnaires_before": [],
        "shelf_questionnaire": None,
        "timing": TimingConfig(decision_window_s=2.0, animation_speed=4.0, next_item_pause_s=pause_s)})


def rgb(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)


def magenta_centroid(image: np.ndarray) -> tuple[float, float] | None:
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    mask = (r > 150) & (b > 150) & (g < 0.5 * np.minimum(r, b))
    if mask.sum() < MAGENTA_MIN:
        return None
    ys, xs = np.nonzero(mask)
    return float(xs.mean()), float(ys.mean())


def marker_span_px(scene, width: float, height: float) -> np.ndarray:
    """(2, 2): where the target item's centre and the top of its arrow project in a view of this size (px)."""
    aspect = width / height
    eye, look = world_camera(MARKER_HEIGHT, aspect)
    target = np.asarray(scene.target.center, dtype=float)
    top = target + [0.0, 0.0, scene.target.height / 2 + ARROW_GAP + ARROW_HEAD + ARROW_SHAFT]
    ndc = project(np.stack([target, top]), eye, look, VIEW_FOV_DEG["world"], aspect)
    return np.stack([(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height], axis=1)


def near_span(point: tuple[float, float], span: np.ndarray) -> float:
    """Distance (px) from ``point`` to the segment ``span``."""
    p, a, b = np.asarray(point), span[0], span[1]
    t = float(np.clip(np.dot(p - a, b - a) / max(np.dot(b - a, b - a), 1e-9), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * (b - a))))


def run(playwright, url: str, token: str, throttle: float, trials: int, out: Path) -> dict[str, Any]:
    context = playwright.chromium.launch_persistent_context(
        tempfile.mkdtemp(prefix="bench_stale_profile_"), executable_path=CHROMIUM, args=BENCHMARK_ARGS,
        headless=True, viewport=VIEWPORT)
    context.set_default_timeout(60_000)
    page = context.new_page()
    if throttle > 1:
        context.new_cdp_session(page).send("Emulation.setCPUThrottlingRate", {"rate": throttle})
    external = f"bench-{throttle:g}-{time.time_ns()}"
    page.goto(f"{url}/join/{SLUG}?PROLIFIC_PID={external}")
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()
    admin = {"Authorization": f"Bearer {token}"}
    study = httpx.get(f"{url}/api/admin/studies/{SLUG}", headers=admin).json()
    seed, block_name = int(study["config"]["seed"]), study["config"]["blocks"][0]["name"]
    public_id = next(p["public_id"] for p in httpx.get(f"{url}/api/admin/studies/{SLUG}/participants",
                                                       headers=admin).json() if p["external_id"] == external)
    rows: list[dict[str, Any]] = []
    seen: set[int] = set()
    deadline = time.monotonic() + 60 * trials
    while len(rows) < trials and time.monotonic() < deadline:
        state = page.evaluate("window.__trustlab.state")
        trial = (state or {}).get("trial")
        if state and state.get("phase") not in ("practice", "trial", "practice_done"):
            if state.get("phase") == "debrief":
                break
        if state and state.get("phase") == "practice_done":
            page.get_by_role("button", name="Continue").click()
        if not trial or trial["stage"] != "decision" or trial["trial"] in seen:
            page.wait_for_timeout(30)
            continue
        opened = time.monotonic()
        seen.add(trial["trial"])
        view = page.evaluate("window.__trustlab.viewer")
        helper = page.locator("#helper2d")
        on_2d = view == "failed" or helper.is_visible()
        shot = (page.locator("#helper2d-canvas") if on_2d else page.locator("#viewer-frame")).screenshot()
        taken_s = time.monotonic() - opened
        image = rgb(shot)
        red = red_share(image)
        high = trial["complexity"] == "high"
        red_ok = red > RED_PRESENT if high else red < RED_ABSENT
        marker_ok, off_px = True, None
        if not on_2d:
            scene = trial_scene(seed, public_id, block_name, trial["trial"], trial["complexity"])
            centroid = magenta_centroid(image)
            span = marker_span_px(scene, image.shape[1], image.shape[0])
            off_px = None if centroid is None else near_span(centroid, span)
            marker_ok = off_px is not None and off_px <= TOLERANCE_PX
        stale = not (red_ok and marker_ok)
        if stale:
            Image.fromarray(image.astype(np.uint8)).save(out / f"stale-{throttle:g}x-trial{trial['trial']}.png")
        rows.append({"trial": trial["trial"], "complexity": trial["complexity"], "view": "2d" if on_2d else "3d",
                     "red": red, "off_px": off_px, "stale": stale, "shot_s": taken_s})
    context.close()
    return {"throttle": throttle, "rows": rows}


def summary(result: dict[str, Any], opened_by: dict[str, int]) -> str:
    rows = result["rows"]
    stale = sum(r["stale"] for r in rows)
    views = {v: sum(r["view"] == v for r in rows) for v in ("3d", "2d")}
    shot = sorted(r["shot_s"] for r in rows)
    offs = [r["off_px"] for r in rows if r["off_px"] is not None]
    return (f"| {result['throttle']:g}× | {len(rows)} | **{stale}** | {views['3d']} / {views['2d']} | "
            f"{', '.join(f'{k} {v}' for k, v in sorted(opened_by.items()))} | "
            f"{(max(offs) if offs else float('nan')):.0f} px | "
            f"{shot[len(shot) // 2] if shot else float('nan'):.2f} s |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=30, help="items (decision windows) per throttle")
    parser.add_argument("--throttles", type=float, nargs="+", default=[1.0, 4.0])
    parser.add_argument("--pause", type=float, default=0.0, help="timing.next_item_pause_s (the study's default: 2)")
    parser.add_argument("--out", type=Path, default=None, help="where screenshots of stale windows go")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    tmp = Path(tempfile.mkdtemp(prefix="bench_stale_"))
    out = args.out or tmp
    out.mkdir(parents=True, exist_ok=True)
    port = free_port()
    lines, figures = [], []
    with open(tmp / "server.log", "w+", encoding="utf-8") as log:
        process, token = start_server(f"sqlite:///{tmp / 'bench.db'}", port, log)
        assert token is not None, "the server printed its admin token"
        url = f"http://127.0.0.1:{port}"
        try:
            response = httpx.post(f"{url}/api/admin/studies", headers={"Authorization": f"Bearer {token}"},
                                  json={"status": "open", "slug": SLUG,
                                        "config": study_config(args.trials, args.pause).model_dump(mode="json")},
                                  timeout=30)
            response.raise_for_status()
            with sync_playwright() as playwright:
                for throttle in args.throttles:
                    result = run(playwright, url, token, throttle, args.trials, out)
                    trials_csv = httpx.get(f"{url}/api/admin/studies/{SLUG}/export/trials.csv",
                                           headers={"Authorization": f"Bearer {token}"}, timeout=60).text
                    opened_by = opened_by_counts(trials_csv, len(result["rows"]))
                    lines.append(summary(result, opened_by))
                    figures.append({"throttle": throttle, "windows": len(result["rows"]),
                                    "stale": sum(r["stale"] for r in result["rows"]), "opened_by": opened_by,
                                    "row": lines[-1]})
                    print(lines[-1], flush=True)
        finally:
            process.terminate()
            process.wait(timeout=30)
    print()
    print(f"Stale-scene windows, {args.trials} items per throttle, next-item pause {args.pause:g} s "
          f"(screenshots of stale windows in {out}):")
    print("| CPU throttle | windows | opened on a stale scene | shown in 3D / 2-D | window_opened_by (the run's "
          "recorded trials) | marker offset, max | window → screenshot, median |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for line in lines:
        print(line)
    append_result("bench_stale_scene.py", {"trials": args.trials, "throttles": args.throttles, "pause_s": args.pause},
                  {"throttles": figures})


def opened_by_counts(trials_csv: str, last: int) -> dict[str, int]:
    """window_opened_by of the last participant's trials (the export lists participants in join order)."""
    import csv

    rows = list(csv.DictReader(io.StringIO(trials_csv)))
    mine = [r for r in rows if r["participant_id"] == rows[-1]["participant_id"]] if rows else []
    counts: dict[str, int] = {}
    for row in mine[-last:]:
        counts[row["window_opened_by"] or "none"] = counts.get(row["window_opened_by"] or "none", 0) + 1
    return counts


if __name__ == "__main__":
    main()
