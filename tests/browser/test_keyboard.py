"""Keyboard only: consent, instructions and the questionnaires with Tab, Space, Enter (and arrows in a scale)."""

from __future__ import annotations

import re

from playwright.sync_api import Page, expect

from experiment.config import PracticeConfig
from experiment.questionnaires import SCHAEFER_14
from tests.browser.driver import export_rows, state, wait_for
from tests.browser.test_participant_flow import block_viewer, demo_config


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


def test_consent_and_surveys_with_the_keyboard_only(live_server, browser):
    config = demo_config(practice=PracticeConfig(enabled=False), questionnaires_before=[SCHAEFER_14.id], shelf_size=1)
    live_server.create_study("keys", config)
    page = browser.new_page()
    block_viewer(page)
    page.goto(f"{live_server.url}/join/keys?PROLIFIC_PID=p-keys")
    page.wait_for_url(re.compile(r"/p/"))
    expect(page.get_by_role("heading", name="Consent to take part")).to_be_focused()

    tab_to(page, "I agree to take part")
    assert focus_is_visible(page)
    page.keyboard.press("Enter")
    expect(page.get_by_role("heading", name="Instructions")).to_be_focused()
    tab_to(page, "Continue")
    page.keyboard.press("Space")

    expect(page.get_by_role("heading", level=1)).to_have_text(SCHAEFER_14.title)
    expect(page.get_by_role("heading", level=1)).to_be_focused()
    tab_to(page, "Continue")  # nothing answered yet: the page says what is missing and goes there
    page.keyboard.press("Enter")
    expect(page.get_by_role("alert")).to_contain_text("14 are missing")
    assert page.evaluate("document.activeElement.name") == SCHAEFER_14.items[0].id
    page.keyboard.press("Shift+Tab")  # back to the heading, so that Tab walks the scales from the first
    schaefer = answer_by_keyboard(page, {"reliable": 7, "malfunction": 2, "dependable": 10})

    wait_for(page, "t.state.phase === 'shelf_survey'", timeout=20_000)  # trial 1: the countdown runs out
    expect(page.get_by_role("heading", level=1)).to_be_focused()
    shelf = answer_by_keyboard(page, {"trust": 8, "reliance": 3})
    wait_for(page, "t.state.phase === 'trial'")

    rows = export_rows(live_server, "keys", "surveys.csv")
    assert {r["item"]: float(r["value"]) for r in rows if r["context"] == "before"} == schaefer
    assert {r["item"]: float(r["value"]) for r in rows if r["context"].startswith("shelf:")} == shelf
