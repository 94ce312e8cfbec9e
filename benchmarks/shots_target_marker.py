"""Screenshots of the participant's 3D view: the target marker and the bin highlight, from every camera preset.

Starts ``trustlab serve --port 8765 --database-url sqlite:////tmp/viewshots.db`` (a fresh database), creates
a study whose practice is one low- and one high-complexity trial in which the robot asks for help, and in
each teleoperation takes 1280x720 screenshots in Debian's Chromium (headless, SwiftShader) from the world,
local and end-effector presets: at the start, with the gripper above the item, with the item held and
with it over the bin.
It steers with held keys as ``experiment.participants.teleoperator.Operator`` decides. Prints, per shot, how many pixels
of the 3D view are the highlight colour.

    .venv/bin/python benchmarks/shots_target_marker.py [--out /tmp/shots_viewer] [--tree .] [--complexities low,high]

``--tree`` is the source tree the server runs from (default: this one).
"""

from __future__ import annotations

import argparse
import io
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
from PIL import Image
from playwright.sync_api import FloatRect, Page, sync_playwright

from experiment.config import PracticeConfig, PracticeTrial, TimingConfig
from experiment.participants.keys import KEY_CODES, Keys
from experiment.participants.teleoperator import Operator, View
from experiment.templates import demo
from server.harness.browser import BENCHMARK_ARGS, CHROMIUM
from server.harness.driver import wait_for
from server.viewer.scene import HIGHLIGHT_COLOR

ROOT = Path(__file__).resolve().parents[1]
PORT = 8765
DB = "/tmp/viewshots.db"
VIEWS = ("world", "local", "end_effector")


def start_server(tree: Path, log: Path) -> tuple[subprocess.Popen, str]:
    """The server (output to ``log``), once it answers; and its admin token."""
    Path(DB).unlink(missing_ok=True)
    code = (f"import sys; sys.argv = ['trustlab', 'serve', '--port', '{PORT:d}', '--database-url', 'sqlite:///{DB}']; "
            "from server.cli import app; app()")
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


def highlight_pixels(png: bytes, box: FloatRect) -> int:
    """Pixels of the highlight colour inside ``box`` (the 3D view's frame) of a page screenshot."""
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    x0, y0 = int(box["x"]), int(box["y"])
    rgb = rgb[y0:y0 + int(box["height"]), x0:x0 + int(box["width"])]
    r, g, b = HIGHLIGHT_COLOR
    return int(((np.abs(rgb[..., 0] - r) < 70) & (rgb[..., 1] < 90) & (np.abs(rgb[..., 2] - b) < 90)).sum())


def show_3d(page: Page) -> None:
    """Untick the page's 2-D helper view (it replaces the 3D view when SwiftShader draws too slowly)."""
    helper = page.get_by_role("checkbox", name=re.compile("2-D helper"))
    if helper.count() and helper.first.is_visible() and helper.first.is_checked():
        helper.first.uncheck()
        page.wait_for_timeout(3000)


def view_pixels(page: Page) -> np.ndarray:
    box = page.locator("#viewer-frame").bounding_box()
    png = page.screenshot(clip=box)
    return np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=float)


def settle(page: Page, before: np.ndarray | None, timeout_s: float = 20.0) -> None:
    """Until the 3D view's picture changed from ``before`` (if given) and then holds still (SwiftShader is slow)."""
    deadline = time.monotonic() + timeout_s
    last = view_pixels(page)
    changed = before is None or last.shape != before.shape or np.abs(last - before).mean() > 0.5
    while time.monotonic() < deadline:
        page.wait_for_timeout(700)
        now = view_pixels(page)
        if before is not None and not changed:
            changed = np.abs(now - before).mean() > 0.5
        elif np.abs(now - last).mean() < 0.3:
            return
        last = now
    print("    (the picture did not settle)", flush=True)


def shoot(page: Page, out: Path, name: str) -> None:
    for view in VIEWS:
        show_3d(page)  # the page may have switched to its 2-D helper meanwhile
        before = view_pixels(page)
        page.locator(f'.camera button[data-view="{view}"]').click()
        settle(page, None if view == "world" else before)  # each stage starts in the world view
        box = page.locator("#viewer-frame").bounding_box()
        assert box is not None, "the 3D view is on the page"
        path = out / f"{name}_{view}.png"
        png = page.screenshot(path=str(path))
        print(f"  {path}: {highlight_pixels(png, box)} highlight pixels in the 3D view", flush=True)
    page.locator('.camera button[data-view="world"]').click()


CLIENT = """() => { const c = window.__trustlab.teleopClient, s = window.__trustlab.state;
  return {ready: c.ready, wanted: c.wanted, over: c.over, hellos: c.hellos, world: c.world, guidance: c.guidance,
          stage: s && s.trial ? s.trial.stage : null}; }"""
SETTLED_S = 0.3


class Driver:
    """Steers the page's teleoperation with held keys as ``experiment.participants.teleoperator.Operator`` decides
    (as ``server.harness.driver.Teleoperator`` does), stopping where a screenshot is wanted."""

    def __init__(self, page: Page):
        self.page = page
        self.held: set[str] = set()
        self.shift = False
        self.changed = time.monotonic()
        self.operator: Operator | None = None
        self.hellos = None
        self.start = self.said = time.monotonic()

    def _keys(self, keys: Keys) -> None:
        keyboard = self.page.keyboard
        wanted = {KEY_CODES[action] for action in keys.held}
        if wanted != self.held or keys.fine != self.shift:
            self.changed = time.monotonic()
        for code in sorted(self.held - wanted):
            keyboard.up(code)
        if keys.fine != self.shift:
            (keyboard.down if keys.fine else keyboard.up)("Shift")
            self.shift = keys.fine
        for code in sorted(wanted - self.held):
            keyboard.down(code)
        self.held = wanted
        if keys.gripper is not None:
            keyboard.press("KeyG")

    def until(self, done, timeout: float = 600.0) -> bool:
        """Drive until ``done(world, guidance)`` (True) or the teleoperation is over (False)."""
        wait_for(self.page, "t.teleopClient.ready || t.teleopClient.over || !t.teleopClient.wanted", timeout=60_000)
        deadline = time.monotonic() + timeout
        try:
            while time.monotonic() < deadline:
                client = self.page.evaluate(CLIENT)
                over = client["over"]
                if (over is not None and not over.get("retry")) or client["wanted"] is None \
                        or client["stage"] not in (None, "teleop"):
                    return False
                if not client["ready"] or client["world"] is None:
                    self._keys(Keys())
                    time.sleep(0.02)
                    continue
                if self.operator is None or client["hellos"] != self.hellos:
                    self.operator = Operator(self.page.evaluate("() => window.__trustlab.teleopClient.setup"))
                    self.hellos = client["hellos"]
                world, guidance = client["world"], client["guidance"]
                if done(world, guidance):
                    return True
                if time.monotonic() > self.said + 15:
                    self.said = time.monotonic()
                    print(f"    ... {guidance['step']}, item {world['item']['mode']}, tcp {world['tcp']}", flush=True)
                self.operator.see(world["tcp"], world)
                view = View.exact(world, guidance)
                view.settled = not self.held and time.monotonic() - self.changed > SETTLED_S
                self._keys(self.operator.decide(view, time.monotonic() - self.start))
                time.sleep(0.02)
            raise AssertionError(f"not there after {timeout} s")
        finally:
            self._keys(Keys())
            self.page.wait_for_timeout(1000)  # the arm stops (the server's dead-man stop) before the picture


def next_trial(page: Page) -> None:
    for _ in range(40):  # past the feedback to the next trial
        buttons = page.get_by_role("button", name=re.compile("^(Continue|Next)"))
        if buttons.count() and buttons.first.is_visible():
            buttons.first.click()
            return
        page.wait_for_timeout(500)


def above_item(world, guidance) -> bool:
    return world["item"]["mode"] == "on_shelf" and guidance["step"] == "lower"


def lifted(world, guidance) -> bool:
    return world["item"]["mode"] == "grasped" and guidance["step"] in ("turn_to_bin", "move_over_bin")


def over_bin(world, guidance) -> bool:
    return world["item"]["mode"] == "grasped" and bool(guidance["over_bin"])


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
                       json={"status": "open", "slug": "shots", "config": config.model_dump(mode="json")})
        assert r.status_code == 201, r.text
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=BENCHMARK_ARGS, headless=True)
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
                driver = Driver(page)
                for stage, done in (("2above", above_item), ("3held", lifted), ("4overbin", over_bin)):
                    if not driver.until(done):
                        print(f"{complexity}: the teleoperation ended before {stage}")
                        break
                    print(f"{complexity}: {stage}")
                    shoot(page, args.out, f"{complexity}_{stage}")
                driver.until(lambda w, g: False)  # deposit: the trial ends
                next_trial(page)
                if complexity == "low":
                    page.wait_for_timeout(1000)
            browser.close()
    finally:
        server.terminate()
        server.wait(timeout=30)


if __name__ == "__main__":
    main()
