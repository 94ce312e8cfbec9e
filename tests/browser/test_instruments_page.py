"""The participant page with choice and free-text items, an attention check, and the screened-out and timed-out
pages (issue 17). Screenshots go to ``TRUSTLAB_SHOTS`` when it is set (not in CI runs)."""

from __future__ import annotations

import os
import re
import time
from datetime import timedelta
from pathlib import Path

from playwright.sync_api import Page, expect

from experiment.config import StudyConfig
from server.harness.driver import state, wait_for
from server.models import utcnow
from server.sweeper import sweep
from tests.browser.test_participant_flow import console_of, demo_config
from tests.browser.test_resume import draft_size, open_page

CHECKS = {"id": "checks", "title": "Attention", "participant_title": "How you see robots",
          "instructions": "Rate each statement.", "scoring": "none",
          "scale": {"min": 1, "max": 5, "step": 1, "anchors": {"1": "Strongly disagree", "5": "Strongly agree"}},
          "items": [{"id": "liking", "text": "I enjoy working with robots."},
                    {"id": "strongly_agree", "text": "To show you are reading, select 'Strongly agree' (5) here.",
                     "instructed_response": 5}]}
SHOTS = os.environ.get("TRUSTLAB_SHOTS")


def config() -> StudyConfig:
    base = demo_config().model_dump(mode="json")
    return StudyConfig.model_validate(base | {
        "practice": {"enabled": False}, "questionnaires": [*base["questionnaires"], CHECKS],
        "questionnaires_before": ["demographics", "comments", "checks"],
        "attention": {"rule": "screen_out", "max_failures": 1},
        "completion": {"redirect_url": "https://recruit.example/done?cc={code}&o={outcome}",
                       "code_timed_out": "TIMED-OUT-7"}})


def shot(page: Page, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(SHOTS) / f"{name}.png"))


def wait_draft(server, external_id: str, n: int) -> None:
    deadline = time.monotonic() + 10
    while draft_size(server, external_id) < n and time.monotonic() < deadline:
        time.sleep(0.1)
    assert draft_size(server, external_id) == n


def test_choice_text_and_attention_items_then_screened_out(live_server, browser):
    live_server.create_study("items", config())
    page = open_page(browser, f"{live_server.url}/join/items?PROLIFIC_PID=p-items")
    messages = console_of(page)
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()

    # Demographics: labelled radio buttons, usable from the keyboard; a missing answer is named.
    expect(page.get_by_role("heading", name="A few questions about you")).to_be_visible()
    gender = page.get_by_role("group", name=re.compile("What is your gender"))
    expect(gender.get_by_role("radio", name="Prefer not to say")).to_be_visible()
    page.get_by_role("group", name=re.compile("How old are you")).get_by_role("radio", name="25–34").check()
    gender.get_by_role("radio", name="Woman").focus()
    page.keyboard.press("ArrowDown")  # a radio group: the arrow keys choose the next option
    expect(gender.get_by_role("radio", name="Man", exact=True)).to_be_checked()
    wait_draft(live_server, "p-items", 2)
    page.reload()  # the draft comes back with the page
    wait_for(page, "t.state !== null && t.state.phase === 'questionnaire'")
    gender = page.get_by_role("group", name=re.compile("What is your gender"))
    expect(gender.get_by_role("radio", name="Man", exact=True)).to_be_checked()
    shot(page, "demographics")
    page.get_by_role("button", name="Continue").click()
    expect(page.locator("#survey-error")).to_have_text(re.compile(r"2 are missing \(questions 3, 4\)"))
    experience = page.get_by_role("group", name=re.compile("experience do you have with robots"))
    experience.get_by_role("radio", name="None", exact=True).check()
    page.get_by_role("group", name=re.compile("play video games")).get_by_role("radio", name="Every week").check()
    page.get_by_role("button", name="Continue").click()

    # Comments: an optional text area with its limit on screen; the draft keeps the text through a reload.
    comments = page.get_by_role("textbox", name=re.compile("Your comments"))
    expect(page.locator("#item-comments-count")).to_have_text("0 of 2000 characters")
    comments.fill("The robot was slow on the top shelf.")
    expect(page.locator("#item-comments-count")).to_have_text("36 of 2000 characters")
    wait_draft(live_server, "p-items", 1)
    page.reload()
    wait_for(page, "t.state !== null && t.state.phase === 'questionnaire'")
    expect(page.get_by_role("textbox", name=re.compile("Your comments"))).to_have_value(
        "The robot was slow on the top shelf.")
    shot(page, "comments")
    page.get_by_role("button", name="Continue").click()

    # The attention check looks like any other item; answering it otherwise ends the session (max_failures 1).
    expect(page.get_by_role("heading", name="How you see robots")).to_be_visible()
    assert "instructed" not in str(state(page)["questionnaire"])
    page.locator('fieldset[data-item="liking"] input[value="4"]').check()
    page.locator('fieldset[data-item="strongly_agree"] input[value="2"]').check()
    shot(page, "attention_item")
    page.get_by_role("button", name="Continue").click()
    expect(page.get_by_role("heading", name="Thank you for your time")).to_be_visible()
    code = live_server.admin("GET", "/api/admin/studies/items").json()["config"]["completion"]["code_screened_out"]
    expect(page.locator("#end-code-value")).to_have_text(code)  # the study's own (the default is public)
    expect(page.get_by_role("link", name="Return to the recruitment site")).to_have_attribute(
        "href", f"https://recruit.example/done?cc={code}&o=screened_out")
    assert state(page)["status"] == "screened_out"
    shot(page, "screened_out")
    assert messages == []

    # The researcher's participants table: the status and the attention flag.
    admin = browser.new_page()
    admin.goto(f"{live_server.url}/admin")
    admin.get_by_label("Admin token").fill(live_server.admin_token)
    admin.keyboard.press("Enter")
    expect(admin.get_by_role("heading", name="Studies")).to_be_visible()
    expect(admin.locator('#studies-body tr[data-slug="items"]')).to_contain_text("1 screened out")  # words, not keys
    admin.goto(f"{live_server.url}/admin#/study/items/participants")
    row = admin.locator("#participants-body tr").first
    expect(row.locator(".badge-screened_out")).to_have_text("screened out")
    expect(row.locator(".flag-attention_failed")).to_have_attribute("title", "failed 1 attention check")
    shot(admin, "admin_participants")


def test_a_timed_out_session_shows_its_code_when_the_participant_comes_back(live_server, browser):
    live_server.create_study("items", config())
    page = open_page(browser, f"{live_server.url}/join/items?PROLIFIC_PID=p-late")  # the browser keeps its resume key
    page.wait_for_url(re.compile(r"/p/"))
    app = live_server.app
    assert sweep(app.state.services.sessionmaker, app.state.services.runtimes, app.state.services.hub,
                 now=utcnow() + timedelta(hours=2)) == 1
    page.goto(f"{live_server.url}/join/items?PROLIFIC_PID=p-late")  # the same person, from the recruitment link again
    page.wait_for_url(re.compile(r"/p/"))
    expect(page.get_by_role("heading", name="This session has ended")).to_be_visible()
    expect(page.locator("#end-code-value")).to_have_text("TIMED-OUT-7")
    expect(page.get_by_role("link", name="Return to the recruitment site")).to_have_attribute(
        "href", "https://recruit.example/done?cc=TIMED-OUT-7&o=timed_out")
    shot(page, "timed_out")
