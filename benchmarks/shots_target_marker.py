"""Screenshots of the participant's 3D view: the target marker and the bin highlight, from every camera preset.

Starts ``trustlab serve --port 8765 --database-url sqlite:////tmp/viewshots.db`` (a fresh database), creates
a study whose practice is one low- and one high-complexity trial in which the robot asks for help, and in
each teleoperation takes 1280x720 screenshots in Debian's Chromium (headless, SwiftShader) from the world,
local and end-effector presets: at the start, with the gripper above the item, with the item held and
with it over the bin.
It steers with held keys (``tests/browser/driver.py``). Prints, per shot, how many pixels of the 3D view are
the highlight colour.

    .venv/bin/python benchmarks/shots_target_marker.py [--out /tmp/shots_viewer] [--tree .] [--complexities low,high]

``--tree`` is the source tree the server runs from (default: this one).
"""

from __future__ import annotations

import argparse
import io
import math
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
from PIL import Image
from playwright.sync_api import Page, sync_playwright
from playwright.sync_api import TimeoutError as PlaywrightTimeout

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from experiment.config import PracticeConfig, PracticeTrial, TimingConfig  # noqa: E402
from experiment.templates import demo  # noqa: E402
from experiment.world import build_scene  # noqa: E402
from experiment.world.robot import arm_points  # noqa: E402
from experiment.world.state import ItemMode, over_bin_opening  # noqa: E402
from server.viewer.scene import HIGHLIGHT_COLOR  # noqa: E402
from tests.browser.driver import Teleoperator, plan, wait_for, world_state  # noqa: E402

PORT = 8765
DB = "/tmp/viewshots.db"
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]
VIEWS = ("world", "local", "end_effector")


def start_server(tree: Path, log: Path) -> tuple[subprocess.Popen, str]:
    """The server (output to ``log``), once it answers; and its admin token."""
    Path(DB).unlink(missing_ok=True)
    code = ("import sys; sys.argv = ['trustlab', 'serve', '--port', '%d', '--database-url', 'sqlite:///%s']; "
            "from server.cli import app; app()" % (PORT, DB))
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-c", code], cwd=tree, stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text()
        m = re.search(r"admin token \(shown once.*\): (\S+)", log.read_text())
        if m:
            try:
                if httpx.get(f"http://127.0.0.1:{PORT}/admin", timeout=5).status_code < 500:
                    return proc, m.group(1)
            except httpx.HTTPError:
                pass
        time.sleep(0.3)
    proc.terminate()
    raise AssertionError("the server did not start:\n" + log.read_text())


def highlight_pixels(png: bytes, box: dict[str, float]) -> int:
    """Pixels of the highlight colour inside ``box`` (the 3D view's frame) of a page screenshot."""
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    x0, y0 = int(box["x"]), int(box["y"])
    rgb = rgb[y0:y0 + int(box["height"]), x0:x0 + int(box["width"])]
    r, g, b = HIGHLIGHT_COLOR
    return int(((np.abs(rgb[..., 0] - r) < 70) & (rgb[..., 1] < 90) & (np.abs(rgb[..., 2] - b) < 90)).sum())


def shoot(page: Page, out: Path, name: str) -> None:
    box = page.locator("#viewer-frame").bounding_box()
    for view in VIEWS:
        page.locator(f'.camera button[data-view="{view}"]').click()
        page.wait_for_timeout(3000)  # the camera message, viser's pacing, a few SwiftShader frames
        path = out / f"{name}_{view}.png"
        png = page.screenshot(path=str(path))
        print(f"  {path}: {highlight_pixels(png, box)} highlight pixels in the 3D view")
    page.locator('.camera button[data-view="world"]').click()


def drive_until(page: Page, done) -> None:
    """Steer like tests/browser/driver.Teleoperator until ``done(world, scene)``."""
    op = Teleoperator(page)
    wait_for(page, "t.teleopClient.open && t.teleopClient.world && t.teleopClient.scene")
    first = op._client()
    scene = build_scene(first["scene"]["complexity"], int(first["scene"]["seed"]), first["scene"]["target_slot"])
    deadline = time.monotonic() + 400
    try:
        while time.monotonic() < deadline:
            client = op._client()
            if client["world"] is None or not client["open"]:
                time.sleep(0.02)
                continue
            if client["scene"] != first["scene"] or client["stage"] not in (None, "teleop"):
                return  # this teleoperation is over
            world = world_state(client["world"])
            if done(world, scene):
                return
            todo = plan(world, scene)
            op.trace.append((todo, world.item.mode, arm_points(world.base, world.joints).tcp, client["lastAck"]))
            try:
                op._step(todo, client)
            except PlaywrightTimeout:  # a slow page (SwiftShader on a busy machine): let go and look again
                op.release()
        raise AssertionError("did not get there in time; last steps:\n" + "\n".join(map(str, op.trace)))
    finally:
        op.release()
        page.wait_for_timeout(800)


def above_item(world, scene) -> bool:
    tcp = arm_points(world.base, world.joints).tcp
    grasp = scene.target.grasp_point()
    return math.dist(tcp[:2], grasp[:2]) < 0.03 and 0.05 < tcp[2] - grasp[2] < 0.2


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=Path("/tmp/shots_viewer"))
    parser.add_argument("--tree", type=Path, default=ROOT)
    parser.add_argument("--complexities", default="low,high", help="the practice trials, in order")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    server, token = start_server(args.tree, args.out / "serve.log")
    url = f"http://127.0.0.1:{PORT}"
    try:
        complexities = args.complexities.split(",")
        practice = PracticeConfig(trials=[PracticeTrial(complexity=c, robot_action="ask") for c in complexities])
        config = demo().model_copy(update={"practice": practice, "timing": TimingConfig(
            decision_window_s=2.0, animation_speed=1.0, teleop_time_limit_s=600.0)})
        r = httpx.post(f"{url}/api/admin/studies", headers={"Authorization": f"Bearer {token}"}, timeout=30,
                       json={"slug": "shots", "config": config.model_dump(mode="json")})
        assert r.status_code == 201, r.text
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.set_default_timeout(90_000)
            page.goto(f"{url}/join/shots?PROLIFIC_PID=shots")
            page.wait_for_url(re.compile(r"/p/"))
            page.get_by_role("button", name="I agree to take part").click()
            page.get_by_role("button", name=re.compile("^Continue")).click()
            for complexity in complexities:
                wait_for(page, "t.state.trial && t.state.trial.stage === 'teleop' && t.teleopClient.world "
                               "&& t.state.trial.complexity === arg", timeout=60_000, arg=complexity)
                assert wait_for(page, "t.viewer", timeout=90_000) == "loaded"
                page.frame_locator("#viewer-frame").locator("canvas").first.wait_for(state="visible")
                page.wait_for_timeout(4000)
                print(f"{complexity}: start of the teleoperation")
                shoot(page, args.out, f"{complexity}_1start")
                drive_until(page, above_item)
                print(f"{complexity}: gripper above the item")
                shoot(page, args.out, f"{complexity}_2above")
                drive_until(page, lambda w, s: w.item.mode == ItemMode.GRASPED
                            and math.dist(w.item.position, s.target.center) > 0.1)
                print(f"{complexity}: item held")
                shoot(page, args.out, f"{complexity}_3held")
                drive_until(page, lambda w, s: w.item.mode == ItemMode.GRASPED
                            and over_bin_opening(w.base, w.item.position))
                print(f"{complexity}: item over the bin")
                shoot(page, args.out, f"{complexity}_4overbin")
                drive_until(page, lambda w, s: w.item.mode == ItemMode.IN_BIN)  # deposited: the trial ends
                for _ in range(20):  # past the feedback to the next trial
                    buttons = page.get_by_role("button", name=re.compile("^(Continue|Next)"))
                    if buttons.count() and buttons.first.is_visible():
                        buttons.first.click()
                        break
                    page.wait_for_timeout(500)
                if complexity == "low":
                    page.wait_for_timeout(1000)
            browser.close()
    finally:
        server.terminate()
        server.wait(timeout=30)


if __name__ == "__main__":
    main()
