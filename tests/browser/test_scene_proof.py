"""The decision window opens only once the screen is proven to show the trial's scene (issue 37).

A slow or loaded client can still show the previous trial's scene when the next trial starts. Here the frames of
the page's 3D view (held by the server's socket writer) or the 2-D helper view's scene (held by the browser's
router) are held back for the second trial, a high-complexity one after a low-complexity one: the window must wait
for them, the screen must show the second trial's red obstacles when it opens (pixels of a screenshot), and the
trial's recorded times must come after the held scene was let through. On the page before the stamp (a frame counted as
the scene 300 ms after the server's viewer held it), the window opened over the first trial's scene.
"""

from __future__ import annotations

import asyncio
import re
import time
from datetime import datetime
from typing import Any

import pytest
from sqlalchemy import select

from experiment.config import PracticeConfig, PracticeTrial
from experiment.world.trial import trial_scene_stamp
from server.harness.browser import red_share
from server.models import Participant, Trial, utcnow
from server.viewer.live import ViewerSink
from server.viewer.scene import STAMP_PREFIX
from server.viewer.wire import unpack
from tests.browser.conftest import serving
from tests.browser.test_participant_flow import TIMING, block_viewer, demo_config

#: How long the view's messages (or the helper's scene) are held back for the second trial.
HOLD_S = 3.0
LOW_THEN_HIGH = PracticeConfig(trials=[
    PracticeTrial(complexity="low", robot_action="auto", human_action_hint="rely"),
    PracticeTrial(complexity="high", robot_action="auto", human_action_hint="rely")])
#: The wait's bound well past the hold (the page falls back to the 2-D view 3 s before it): the window must be
#: opened by the page's proof, never by the bound.
PROOF_TIMING = TIMING.model_copy(update={"scene_wait_s": 90.0, "decision_window_s": 3.0, "animation_speed": 4.0,
                                         "next_item_pause_s": 1.0})


class DelayLine:
    """The 3D view's frames held back by the server's socket writer (``ViewerSink.next``) for ``hold_s``, as a slow
    network or a loaded client would receive them: each frame leaves ``hold_s`` after it was ready, in order."""

    def __init__(self, monkeypatch) -> None:
        self.hold_s = 0.0
        #: stamp -> when the frame creating its node left the server (server clock)
        self.released: dict[str, datetime] = {}
        original = ViewerSink.next
        lines: dict[int, asyncio.Queue] = {}
        line = self

        async def delayed(sink: ViewerSink) -> bytes | None:
            if id(sink) not in lines:
                queue = lines[id(sink)] = asyncio.Queue()

                async def fill() -> None:
                    while True:
                        data = await original(sink)
                        await queue.put((time.monotonic() + line.hold_s, data))
                        if data is None:
                            return
                sink._delay_task = asyncio.create_task(fill())  # (kept with the sink)
            due, data = await lines[id(sink)].get()
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            if data is not None:
                for stamp in _stamps(data):
                    line.released.setdefault(stamp, utcnow())
            return data

        monkeypatch.setattr(ViewerSink, "next", delayed)


def _stamps(frame: bytes) -> list[str]:
    payload, _ = unpack(frame)
    return [m["name"][len(STAMP_PREFIX):] for m in payload.get("messages", [])
            if m.get("type") == "FrameMessage" and str(m.get("name", "")).startswith(STAMP_PREFIX)]


@pytest.fixture
def views_here(sqlite_template, tmp_path):
    """Views served in the server's own process, so that the test can hold their frames back."""
    with serving(sqlite_template, tmp_path, view_process=False) as live:
        yield live


def join_and_start(live_server, browser, slug: str, throttle: float):
    live_server.create_study(slug, demo_config(practice=LOW_THEN_HIGH, timing=PROOF_TIMING))
    page = browser.new_page()
    if throttle > 1:
        page.context.new_cdp_session(page).send("Emulation.setCPUThrottlingRate", {"rate": throttle})
    return page


def begin(page, live_server, slug: str) -> None:
    page.goto(f"{live_server.url}/join/{slug}?PROLIFIC_PID=p-{slug}")
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()


def trial_of(page) -> dict[str, Any] | None:
    return page.evaluate("(window.__trustlab.state || {}).trial || null")


def second_trial_rows(live_server) -> tuple[Trial, str]:
    with live_server.app.state.services.sessionmaker() as session:
        public_id = session.scalar(select(Participant.public_id))
        second = session.scalars(select(Trial).where(Trial.trial == 2)).one()
    return second, public_id


def study_seed(live_server, slug: str) -> int:
    return int(live_server.admin("GET", f"/api/admin/studies/{slug}").json()["config"]["seed"])


@pytest.mark.parametrize("throttle", [1.0, 4.0])
def test_a_window_waits_for_the_3d_view_to_draw_the_trials_scene(views_here, browser, tmp_path, monkeypatch,
                                                                   throttle):
    live_server = views_here
    delay = DelayLine(monkeypatch)
    slug = f"proof3d{int(throttle)}"
    page = join_and_start(live_server, browser, slug, throttle)
    begin(page, live_server, slug)
    deadline = time.monotonic() + 240
    # The first trial (low complexity: no obstacles) goes as usual; from its window on, the view's frames wait.
    while not ((t := trial_of(page)) and t["trial"] == 1 and t["stage"] != "presenting"):
        page.wait_for_timeout(50)
        assert time.monotonic() < deadline, "the first trial's window never opened"
    assert page.evaluate("window.__trustlab.viewer") == "loaded"
    delay.hold_s = HOLD_S

    stale_red = presenting_ms = None
    while True:
        t = trial_of(page)
        if t and t["trial"] == 2 and t["stage"] == "presenting" and stale_red is None:
            # The trial has started but its scene is held back: the view still shows the first trial's.
            presenting_ms = page.evaluate("performance.now()")
            stale_red = red_share(page.locator("#viewer-frame").screenshot())
            page.screenshot(path=str(tmp_path / f"presenting-held-{throttle:g}x.png"))
        if t and t["trial"] == 2 and t["stage"] != "presenting":
            break
        page.wait_for_timeout(30)
        assert time.monotonic() < deadline, "the second trial's window never opened"
    opened_red = red_share(page.locator("#viewer-frame").screenshot())  # what the screen shows as it opens
    page.screenshot(path=str(tmp_path / f"window-opened-{throttle:g}x.png"))
    assert stale_red is not None and stale_red < 0.002, f"the first trial's scene shows red ({stale_red:.4f})"
    assert opened_red > 0.004, (f"the window opened over a scene without the trial's obstacles (red share "
                                f"{opened_red:.4f}; see {tmp_path})")

    second, public_id = second_trial_rows(live_server)
    stamp = trial_scene_stamp(study_seed(live_server, slug), public_id, second.block_name, 2, "high")
    assert stamp in delay.released, "the second trial's scene never left the server"
    assert (second.window_opened_by, second.scene_shown_view) == ("3d", "3d")
    # (the server's view may show the next trial's scene as soon as it is known, before the trial's start: the
    # hold counts from then, so the times are compared with the scene's release, not with the start)
    released = delay.released[stamp]
    assert second.scene_shown_at >= released and second.window_opened_at >= released
    assert second.scene_shown_client_ms > presenting_ms  # the page's frame, drawn after the stale screenshot


def test_a_window_waits_for_the_2d_helper_to_draw_the_trials_scene(live_server, browser, tmp_path):
    """Without the 3D view the 2-D helper view shows the scene: the window waits until it has drawn the scene
    fetched for this trial (held back here), and the helper's canvas then shows the trial's obstacles."""
    slug = "proof2d"
    page = join_and_start(live_server, browser, slug, 1.0)
    block_viewer(page)
    held_routes: list[tuple[float, Any]] = []
    holding = {"on": False}

    def scene_request(route) -> None:
        held_routes.append((time.monotonic() + (HOLD_S if holding["on"] else 0.0), route))

    page.route(re.compile(r"/trials/scene$"), scene_request)

    def pump() -> None:
        while held_routes and held_routes[0][0] <= time.monotonic():
            held_routes.pop(0)[1].continue_()

    begin(page, live_server, slug)
    deadline = time.monotonic() + 180
    while not ((t := trial_of(page)) and t["trial"] == 1 and t["stage"] != "presenting"):
        pump()
        page.wait_for_timeout(30)
        assert time.monotonic() < deadline, "the first trial's window never opened"
    assert page.evaluate("window.__trustlab.viewer") == "failed"
    holding["on"] = True
    messages = set()
    while not ((t := trial_of(page)) and t["trial"] == 2 and t["stage"] != "presenting"):
        pump()
        message = page.locator("#robot-message").text_content()
        if message == "Next item…" and message not in messages:
            page.screenshot(path=str(tmp_path / "next-item-pause.png"))
        messages.add(message)
        page.wait_for_timeout(30)
        assert time.monotonic() < deadline, "the second trial's window never opened"
    assert "Next item…" in messages  # the visible pause between the first outcome and the next item
    shot = page.locator("#helper2d-canvas").screenshot()
    page.screenshot(path=str(tmp_path / "window-opened-2d.png"))
    assert red_share(shot) > 0.004, f"the 2-D view shows no obstacles when the window opened (see {tmp_path})"
    second, _ = second_trial_rows(live_server)
    with live_server.app.state.services.sessionmaker() as session:
        first = session.scalars(select(Trial).where(Trial.trial == 1)).one()
    # the outcome on screen (1.5 s), then the pause (timing.next_item_pause_s), then the next item
    assert (second.started_at - first.completed_at).total_seconds() >= 1.5 + PROOF_TIMING.next_item_pause_s
    assert (second.window_opened_by, second.scene_shown_view) == ("2d", "2d")
    assert (second.window_opened_at - second.started_at).total_seconds() >= HOLD_S * 0.9
