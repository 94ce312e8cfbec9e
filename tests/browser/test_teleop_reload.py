"""A reload in the middle of a teleoperation (issue 37): the page comes back with the view it had (the 2-D helper at
once where the 3D view was judged too slow), and the time limit waits while the page has no usable view (the 3D
view still loading), bounded and recorded."""

from __future__ import annotations

import re
import time

import pytest
from playwright.sync_api import expect
from sqlalchemy import select

from experiment.config import PracticeConfig, PracticeTrial
from server.harness.driver import wait_for
from server.models import Event, Trial
from tests.browser.test_participant_flow import TIMING, demo_config

ASKS_FIRST = PracticeConfig(trials=[PracticeTrial(complexity="low", robot_action="ask")])
#: How long the 3D view's page is held back after the reload.
VIEW_HELD_S = 3.0


def steering_with_the_3d_view(live_server, browser, slug: str):
    """A new participant of a new study, teleoperating in the practice, the 3D view loaded."""
    live_server.create_study(slug, demo_config(practice=ASKS_FIRST, timing=TIMING))
    page = browser.new_page()
    page.goto(f"{live_server.url}/join/{slug}?PROLIFIC_PID=p-{slug}")
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()
    wait_for(page, "t.state.trial && t.state.trial.stage === 'teleop' && t.teleopClient.world", timeout=60_000)
    wait_for(page, "t.viewer === 'loaded'", timeout=60_000)
    return page


def teleop_row(live_server) -> Trial:
    with live_server.app.state.services.sessionmaker() as session:
        return session.scalars(select(Trial).where(Trial.trial == 1)).one()


def test_a_reload_mid_teleoperation_keeps_the_view_and_the_time_limit_waits_for_it(live_server, browser):
    page = steering_with_the_3d_view(live_server, browser, "reload")
    # (the view may have loaded after the teleoperation began: that wait has ended once the page says so)
    wait_for(page, "t.teleopClient.viewUsable === true && t.teleopClient.viewSent !== false", timeout=30_000)
    page.wait_for_timeout(300)
    before = teleop_row(live_server)
    deadline, waited_before = before.teleop_deadline_at, before.teleop_view_wait_ms or 0.0
    # This tab's 3D view was judged too slow to steer by (as the page records it), then the participant reloads,
    # and the 3D view's page comes slowly.
    token = page.url.split("/p/")[1].split("/")[0].split("?")[0]
    page.evaluate("token => sessionStorage.setItem(`trustlab.viewerSlow.${token}`, '1')", token)
    held: list = []
    page.route(re.compile(r"/viewer/[^/]+/$"), lambda route: held.append(route))
    page.reload(wait_until="domcontentloaded")
    wait_for(page, "t.teleopClient && t.teleopClient.setup", timeout=30_000)
    start = time.monotonic()
    while time.monotonic() - start < VIEW_HELD_S:
        page.wait_for_timeout(100)
    assert held, "the 3D view's page was not requested"
    for route in held:
        route.continue_()
    wait_for(page, "t.viewer === 'loaded'", timeout=60_000)
    # the 2-D helper stands in at once, without the view being judged again
    expect(page.locator("#helper2d.full")).to_be_visible(timeout=5_000)
    wait_for(page, "t.teleopClient.viewSent === true", timeout=10_000)  # the page said its view is usable again
    with live_server.app.state.services.sessionmaker() as session:
        waits = [e.payload["waited_ms"] for e in session.scalars(select(Event).where(Event.kind == "teleop_view_wait"))]
    row = teleop_row(live_server)
    waited = row.teleop_view_wait_ms - waited_before
    assert VIEW_HELD_S * 1000 * 0.8 <= waited and row.teleop_view_wait_ms <= 30_000
    assert sum(waits) == pytest.approx(row.teleop_view_wait_ms, abs=0.5), waits
    assert (row.teleop_deadline_at - deadline).total_seconds() * 1000 == pytest.approx(waited, abs=5)


def test_the_3d_view_shows_no_stale_frame_after_the_2d_view_covered_it(live_server, browser):
    """While the 2-D view stands in for a slow 3D view, the 3D view pauses on its last frame; when it comes back it
    stays invisible until it has drawn anew, so the arm is never shown where it was before."""
    page = steering_with_the_3d_view(live_server, browser, "fresh")
    page.evaluate("window.__trustlab.teleopPanel.setHelperReason('slow')")
    expect(page.locator("#helper2d.full")).to_be_visible()
    assert page.evaluate("window.__trustlab.viewerPace.paused")
    page.keyboard.down("KeyD")  # the arm moves while the 3D view is paused
    page.wait_for_timeout(800)
    page.keyboard.up("KeyD")
    page.evaluate("""() => {
      const frame = document.getElementById('viewer-frame'), pace = window.__trustlab.viewerPace;
      window.__fresh = { at: pace.renderCount(), seen: [] };
      new MutationObserver(() => window.__fresh.seen.push([frame.style.opacity, pace.renderCount()]))
        .observe(frame, { attributes: true, attributeFilter: ['style'] });
    }""")
    page.get_by_role("checkbox", name="2-D helper view").uncheck()
    wait_for(page, "window.__fresh.seen.some(([opacity]) => opacity === '')", timeout=10_000)
    fresh = page.evaluate("window.__fresh")
    assert fresh["seen"][0][0] == "0", fresh  # hidden at once
    shown_at = next(renders for opacity, renders in fresh["seen"] if opacity == "")
    assert shown_at > fresh["at"], fresh  # shown again only after a new render
