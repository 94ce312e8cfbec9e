"""Screenshots of the participant's trial page from every camera preset, at 1280x720 and 1920x1080.

Starts the server as ``shots_target_marker.py`` does (``trustlab serve --port 8765``, a fresh SQLite database),
creates a study whose practice is four trials in which the robot asks for help (low, high, low, high), joins
participants until one's four practice targets are a top- and a bottom-shelf item in each complexity, and in each
teleoperation takes screenshots from the world, local and end-effector presets at both page sizes: at the start
(the gripper high above the item) and with the gripper above the item (guidance step "lower"). Then it steers
the item into the bin (``experiment.participants.teleoperator.Operator``) and goes on to the next trial.

Prints, per trial, the world camera the viewer in the page holds (position, yaw and pitch of its line of sight:
the angle must not change between trials) and, per shot, how much of the 3D view the scene fills: the bounding
box of the pixels that are not floor or background (shelf, robot, bin, items, obstacles; 1st-99th percentile) as
a share of the view's width, height and area.

    .venv/bin/python benchmarks/shots_cameras.py [--out /tmp/shots_cameras] [--tree .] [--stages start,above]

``--tree`` is the source tree the server runs from (default: this one; another checkout gives "before" shots).
"""

from __future__ import annotations

import argparse
import io
import math
import re
import sqlite3
import time
from pathlib import Path

import httpx
import numpy as np
from PIL import Image
from playwright.sync_api import Page, sync_playwright

from experiment.config import PracticeConfig, PracticeTrial, TimingConfig, TutorialConfig
from experiment.templates import demo
from experiment.world import constants as K
from experiment.world.trial import trial_scene
from server.harness.browser import BENCHMARK_ARGS, CHROMIUM
from server.harness.driver import wait_for
from server.services.trials import PRACTICE_BLOCK

# the sibling script (this script's folder is on sys.path when it runs as ``python benchmarks/shots_cameras.py``)
from shots_target_marker import DB, PORT, VIEWS, Driver, above_item, next_trial, settle, show_3d, start_server

ROOT = Path(__file__).resolve().parents[1]
SIZES = ((1280, 720), (1920, 1080))
COMPLEXITIES = ("low", "high", "low", "high")
TIERS = ("bottom", "top")  # K.SLOT_TIERS_X order: slot // columns


def practice_tiers(seed: int, public_id: str) -> list[str]:
    """The shelf tier of each practice trial's target, as the server draws them."""
    return [TIERS[trial_scene(seed, public_id, PRACTICE_BLOCK, i + 1, c).target_slot // len(K.SLOT_COLUMNS_Y)]
            for i, c in enumerate(COMPLEXITIES)]


def pick_participant(url: str, seed: int) -> tuple[str, list[str]]:
    """Join until a participant's practice has a top- and a bottom-shelf target in each complexity."""
    for n in range(60):
        r = httpx.post(f"{url}/api/studies/shots/join", params={"PROLIFIC_PID": f"shots-{n}"}, timeout=30)
        assert r.status_code == 200, r.text
        with sqlite3.connect(DB) as db:
            (public_id,) = db.execute("SELECT public_id FROM participant WHERE external_id = ?",
                                      (f"shots-{n}",)).fetchone()
        tiers = practice_tiers(seed, public_id)
        if {(c, t) for c, t in zip(COMPLEXITIES, tiers, strict=False)} == {(c, t) for c in ("low", "high")
                                                                           for t in TIERS}:
            return r.json()["participant_url"], tiers
        time.sleep(0.5)
    raise AssertionError("no participant with a top and a bottom target in each complexity")


CAMERA = """() => { const f = document.getElementById('viewer-frame'); const w = f && f.contentWindow;
  const c = w && w.__viserMutable && w.__viserMutable.camera; if (!c) return null;
  c.updateMatrixWorld(); const e = c.matrixWorld.elements;  // column-major: the camera looks down its -z
  return {position: [c.position.x, c.position.y, c.position.z], forward: [-e[8], -e[9], -e[10]],
          fov: c.fov, aspect: c.aspect}; }"""


def camera(page: Page) -> dict | None:
    """The viewer's three.js camera in world coordinates (viser's three.js scene is y-up: world = (-z, -x, y))."""
    cam = page.evaluate(CAMERA)
    if cam is None:
        return None
    (px, py, pz), (fx, fy, fz) = cam["position"], cam["forward"]
    return {**cam, "position": (-pz, -px, py), "forward": (-fz, -fx, fy)}


def world_camera(page: Page) -> str:
    cam = camera(page)
    if cam is None:
        return "no camera"
    f = cam["forward"]
    yaw = math.degrees(math.atan2(f[1], f[0]))
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, f[2]))))
    pos = ", ".join(f"{v:.2f}" for v in cam["position"])
    return (f"position ({pos}), yaw {yaw:.1f} deg, pitch {pitch:.1f} deg, fov {cam['fov']:.1f}, "
            f"aspect {cam['aspect']:.2f}")


def wait_camera(page: Page, before: dict | None, timeout_s: float = 20.0) -> None:
    """Until the viewer's camera moved away from ``before`` (if given) and holds still."""
    deadline = time.monotonic() + timeout_s
    last = camera(page)
    moved = before is None
    while time.monotonic() < deadline:
        page.wait_for_timeout(400)
        now = camera(page)
        if now is None or last is None:
            last = now
            continue
        if not moved and before is not None:  # (no camera before: moved from the start)
            moved = math.dist(now["position"], before["position"]) > 1e-3 or \
                math.dist(now["forward"], before["forward"]) > 1e-3
        elif math.dist(now["position"], last["position"]) < 1e-4 and math.dist(now["forward"], last["forward"]) < 1e-4:
            return
        last = now
    print("    (the camera did not settle)", flush=True)


def ensure_3d(page: Page) -> bool:
    """Untick the 2-D helper view if it replaces the 3D view (SwiftShader draws too slowly); True if it did."""
    helper = page.get_by_role("checkbox", name=re.compile("2-D helper"))
    if helper.count() and helper.first.is_visible() and helper.first.is_checked():
        show_3d(page)
        return True
    return False


def scene_fill(page: Page) -> str:
    """The box of the scene's pixels (not floor, grid, shadow or background) as shares of the view."""
    box = page.locator("#viewer-frame").bounding_box()
    rgb = np.asarray(Image.open(io.BytesIO(page.screenshot(clip=box))).convert("RGB"), dtype=float)
    hi, lo = rgb.max(axis=2), rgb.min(axis=2)
    saturation = (hi - lo) / np.maximum(hi, 1.0)
    scene = (saturation > 0.28) | (hi < 95)  # shelf, items, bin, obstacles, robot body; not grey floor or shadow
    ys, xs = np.nonzero(scene)
    if len(xs) < 50:
        return "no scene pixels"
    x0, x1 = np.percentile(xs, [1, 99])
    y0, y1 = np.percentile(ys, [1, 99])
    w, h = (x1 - x0) / rgb.shape[1], (y1 - y0) / rgb.shape[0]
    return f"scene box {w:.0%} x {h:.0%} of the view ({w * h:.0%} of its area)"


def shoot(page: Page, out: Path, name: str) -> None:
    """Every preset at every page size; back to the world view and the first size."""
    current = "world"
    for width, height in SIZES:
        page.set_viewport_size({"width": width, "height": height})
        page.wait_for_timeout(1500)
        for view in VIEWS:
            ensure_3d(page)
            before = camera(page)
            page.locator(f'.camera button[data-view="{view}"]').click()
            wait_camera(page, before if view != current else None)
            current = view
            settle(page, None)
            while ensure_3d(page):  # the page may put its 2-D helper back while the view is slow
                settle(page, None)
            path = out / f"{name}_{width}_{view}.png"
            page.screenshot(path=str(path))
            print(f"  {path.name}: {scene_fill(page)}", flush=True)
            if view == "world":
                print(f"    the world camera as the page's viewer holds it: {world_camera(page)}", flush=True)
        page.locator('.camera button[data-view="world"]').click()
        wait_camera(page, camera(page))
        current = "world"
    page.set_viewport_size({"width": SIZES[0][0], "height": SIZES[0][1]})
    page.wait_for_timeout(1500)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=Path("/tmp/shots_cameras"))
    parser.add_argument("--tree", type=Path, default=ROOT)
    parser.add_argument("--stages", default="start,above", help="start and/or above (the gripper over the item)")
    parser.add_argument("--trials", type=int, default=len(COMPLEXITIES), help="how many practice trials to shoot")
    args = parser.parse_args()
    stages = args.stages.split(",")
    args.out.mkdir(parents=True, exist_ok=True)
    server, token = start_server(args.tree, args.out / "serve.log")
    url = f"http://127.0.0.1:{PORT}"
    try:
        practice = PracticeConfig(trials=[PracticeTrial(complexity=c, robot_action="ask") for c in COMPLEXITIES],
                                  tutorial=TutorialConfig(time_limit_s=1800.0))  # shooting takes minutes
        timing = TimingConfig(decision_window_s=2.0, animation_speed=1.0, teleop_time_limit_s=600.0)
        config = demo().model_copy(update={"practice": practice, "timing": timing})
        r = httpx.post(f"{url}/api/admin/studies", headers={"Authorization": f"Bearer {token}"}, timeout=30,
                       json={"status": "open", "slug": "shots", "config": config.model_dump(mode="json")})
        assert r.status_code == 201, r.text
        participant_url, tiers = pick_participant(url, config.seed)
        print("practice targets:", ", ".join(f"{c}/{t}" for c, t in zip(COMPLEXITIES, tiers, strict=False)), flush=True)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=BENCHMARK_ARGS, headless=True)
            page = browser.new_page(viewport={"width": SIZES[0][0], "height": SIZES[0][1]})
            page.set_default_timeout(90_000)
            page.goto(participant_url if participant_url.startswith("http") else url + participant_url)
            page.get_by_role("button", name="I agree to take part").click()
            page.get_by_role("button", name=re.compile("^Continue")).click()
            for i, (complexity, tier) in enumerate(zip(COMPLEXITIES[:args.trials], tiers, strict=False)):
                wait_for(page, "t.state.trial && t.state.trial.stage === 'teleop' && t.teleopClient.world "
                               "&& t.state.trial.trial === arg", timeout=120_000, arg=i + 1)
                assert wait_for(page, "t.viewer", timeout=90_000) == "loaded"
                page.frame_locator("#viewer-frame").locator("canvas").first.wait_for(state="visible")
                page.wait_for_timeout(4000)
                print(f"trial {i + 1} ({complexity}, {tier} shelf: "
                      f"{page.evaluate('window.__trustlab.state.trial.target')})",
                      flush=True)
                name = f"t{i + 1}_{complexity}_{tier}"
                if "start" in stages:
                    shoot(page, args.out, f"{name}_1start")
                driver = Driver(page)
                if "above" in stages:
                    if driver.until(above_item):
                        shoot(page, args.out, f"{name}_2above")
                    else:
                        print("  the teleoperation ended before the gripper was above the item")
                driver.until(lambda w, g: False)  # deposit: the trial ends
                next_trial(page)
                page.wait_for_timeout(1000)
            browser.close()
    finally:
        server.terminate()
        server.wait(timeout=30)


if __name__ == "__main__":
    main()
