"""Keyboard only: consent, instructions and the questionnaires with Tab, Space, Enter (and arrows in a scale);
no decision window before the trial's scene is on screen; Intervene pressed too late (or too early) is answered."""

from __future__ import annotations

import json
import re
from datetime import timedelta

from playwright.sync_api import Page, Route, expect
from sqlalchemy import select

from experiment.config import PracticeConfig
from experiment.instruments import SCHAEFER_14
from server.harness.driver import export_rows, state, wait_for
from server.models import Trial, utcnow
from tests.browser.test_participant_flow import demo_config

TOO_LATE = "Too late: the countdown had already ended, so the robot is collecting the item on its own."


def tab_to(page: Page, name: str, limit: int = 40) -> None:
    """Press Tab until the focused element's accessible text starts with ``name``."""
    for _ in range(limit):
        page.keyboard.press("Tab")
        text = page.evaluate("document.activeElement.textContent.trim()")
        if text.startswith(name):
            return
    raise AssertionError(f"Tab never reached {name!r}")


def focus_is_visible(page: Page) -> bool:
    return page.evaluate("""() => { const s = getComputedStyle(document.activeElement);
        return s.outlineStyle !== 'none' && parseFloat(s.outlineWidth) >= 2; }""")


def answer_by_keyboard(page: Page, moves: dict[str, int]) -> dict[str, float]:
    """Tab into each scale, Space picks its first point, ArrowRight moves on; Enter on Continue."""
    q = state(page)["questionnaire"]
    scale = q["scale"]
    chosen = {}
    for item in q["items"]:
        page.keyboard.press("Tab")
        assert page.evaluate("document.activeElement.name") == item["id"]
        page.keyboard.press("Space")
        for _ in range(moves.get(item["id"], 0)):
            page.keyboard.press("ArrowRight")
        chosen[item["id"]] = scale["min"] + moves.get(item["id"], 0) * scale["step"]
        expect(page.locator(f'input[name="{item["id"]}"]:checked')).to_have_value(f"{chosen[item['id']]:g}")
    page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.textContent.trim()") == "Continue"
    assert focus_is_visible(page)
    page.keyboard.press("Enter")
    wait_for(page, "!t.state.questionnaire || t.state.questionnaire.context !== arg", arg=q["context"])
    return chosen


def flush_events(page: Page) -> None:
    page.evaluate("window.__trustlab.events.flush()")
    wait_for(page, "t.events.queue.length === 0 && !t.events.sending")


def hold_viewer(page: Page) -> list[Route]:
    """The 3D view's requests wait (like a slow network) until the test answers the routes returned."""
    held: list[Route] = []
    page.route(re.compile(r"/viewer/"), lambda route: held.append(route))
    return held


def no_window_until_the_scene_is_shown(page: Page, server, held: list[Route]) -> None:
    """While the view is loading the trial is presenting: no countdown, Intervene answers 'not yet', and a reload
    presents again. When the 3D view fails the 2-D view shows the trial's scene, and then the window opens."""
    wait_for(page, "t.state.trial && t.state.trial.stage === 'presenting'")
    page.wait_for_timeout(1000)  # the view is still loading a second later: nothing has started
    for look in range(2):
        assert state(page)["trial"]["stage"] == "presenting"
        assert page.evaluate("window.__trustlab.sceneReported") is None
        expect(page.locator("#countdown-text")).to_have_text("The countdown starts once the robot is on screen.")
        expect(page.locator("#countdown-bar")).to_have_attribute("style", "width: 0%;")
        expect(page.get_by_role("button", name="Intervene")).to_be_disabled()
        page.keyboard.press("Space")
        expect(page.get_by_role("alert")).to_contain_text("The countdown has not started yet")
        if look == 0:  # a reload while presenting: presenting again (the view is held again)
            page.screenshot(path=str(server.shots / "trial-waiting-for-scene.png"))
            flush_events(page)
            page.reload()
            wait_for(page, "t.state !== null && t.state.trial !== null && t.presenting")
    while held:
        held.pop().abort()  # the 3D view fails: the 2-D view stands in
    wait_for(page, "t.state.trial.stage === 'decision'", timeout=10_000)
    expect(page.locator("#helper2d.full")).to_be_visible()
    expect(page.locator("#countdown-text")).to_contain_text("s left to intervene")
    expect(page.get_by_role("alert")).to_be_hidden()  # the 'not yet' notice went with the window opening
    page.screenshot(path=str(server.shots / "trial-2d-scene-decision.png"))


def too_late_is_answered(page: Page, server) -> None:
    """Intervene after the window: the server's 409 and the page's own clock both say 'too late'."""
    with server.app.state.services.sessionmaker.begin() as session:  # the server's window closes before the page's
        deciding = session.scalar(select(Trial).where(Trial.stage == "decision"))
        deciding.decision_deadline_at = utcnow() - timedelta(seconds=1)
    page.keyboard.press("Space")
    expect(page.get_by_role("alert")).to_have_text(TOO_LATE)
    wait_for(page, "t.state.trial && t.state.trial.stage === 'attempt'")
    page.screenshot(path=str(server.shots / "trial-too-late.png"))
    notices = page.evaluate("window.__trustlab.lateNotices")
    page.get_by_role("button", name="Intervene").click(force=True)  # looks unavailable, still answers
    wait_for(page, "t.lateNotices === arg", arg=notices + 1)
    expect(page.get_by_role("alert")).to_have_text(TOO_LATE)


def test_consent_and_surveys_with_the_keyboard_only(live_server, browser, tmp_path):
    config = demo_config(practice=PracticeConfig(enabled=False), questionnaires_before=[SCHAEFER_14.id], shelf_size=1)
    live_server.create_study("keys", config)
    live_server.shots = tmp_path
    page = browser.new_page()
    held = hold_viewer(page)
    page.goto(f"{live_server.url}/join/keys?PROLIFIC_PID=p-keys")
    page.wait_for_url(re.compile(r"/p/"))
    expect(page.get_by_role("heading", name="Consent to take part")).to_be_focused()

    tab_to(page, "I agree to take part")
    assert focus_is_visible(page)
    page.keyboard.press("Enter")
    expect(page.get_by_role("heading", name="Instructions")).to_be_focused()
    tab_to(page, "Continue")
    page.keyboard.press("Space")

    wait_for(page, "t.state.phase === 'questionnaire'")
    expect(page.get_by_role("heading", level=1)).to_have_text(state(page)["questionnaire"]["title"])
    expect(page.get_by_role("heading", level=1)).to_be_focused()
    tab_to(page, "Continue")  # nothing answered yet: the page says what is missing and goes there
    page.keyboard.press("Enter")
    expect(page.get_by_role("alert")).to_contain_text("14 are missing")
    assert page.evaluate("document.activeElement.name") == SCHAEFER_14.items[0].id
    page.keyboard.press("Shift+Tab")  # back to the heading, so that Tab walks the scales from the first
    schaefer = answer_by_keyboard(page, {"reliable": 7, "malfunction": 2, "dependable": 10})

    no_window_until_the_scene_is_shown(page, live_server, held)
    too_late_is_answered(page, live_server)
    wait_for(page, "t.state.phase === 'shelf_survey'", timeout=20_000)  # trial 1: the robot went on
    expect(page.get_by_role("heading", level=1)).to_be_focused()
    shelf = answer_by_keyboard(page, {"trust": 8, "reliance": 3})
    wait_for(page, "t.state.phase === 'trial'")

    flush_events(page)
    trial_1 = export_rows(live_server, "keys", "trials.csv")[0]
    assert (trial_1["human_action"], trial_1["window_opened_by"]) == ("rely", "2d")
    assert trial_1["scene_shown_at"] == trial_1["window_opened_at"] != ""
    events = export_rows(live_server, "keys", "events.csv")
    kinds = [e["kind"] for e in events]
    assert kinds.count("client.intervene_too_early") == 2 and kinds.count("client.scene_on_screen") == 1
    late = [json.loads(e["payload"]) for e in events if e["kind"] == "client.intervene_too_late"]
    assert [(p["known_by"], p["source"]) for p in late] == [("server", "key"), ("page", "button")]
    assert "client.decision_window_opened" in kinds and "client.intervene_pressed" in kinds

    rows = export_rows(live_server, "keys", "surveys.csv")
    assert {r["item"]: float(r["value"]) for r in rows if r["context"] == "before"} == schaefer
    assert {r["item"]: float(r["value"]) for r in rows if r["context"].startswith("shelf:")} == shelf
