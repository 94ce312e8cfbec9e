"""A German participant's questionnaire pages (issue 41): the items, options and anchors in German, a questionnaire
without German shown in English and marked so (``lang="en"``), the answers recorded by their stable values.
Screenshots go to ``TRUSTLAB_SHOTS`` when it is set (not in CI runs)."""

from __future__ import annotations

import re

from playwright.sync_api import expect

from experiment.config import StudyConfig
from server.harness.driver import state, wait_for
from tests.browser.test_instruments_page import shot
from tests.browser.test_participant_flow import console_of, demo_config
from tests.browser.test_resume import open_page

OWN = {"id": "own", "title": "Own", "participant_title": "One more question", "instructions": "Rate it.",
       "scoring": "none", "about_robot": False, "scale": {"min": 1, "max": 5, "step": 1,
                                                          "anchors": {"1": "Poor", "5": "Good"}},
       "items": [{"id": "overall", "text": "How was the study?"}]}


def config() -> StudyConfig:
    base = demo_config().model_dump(mode="json")
    return StudyConfig.model_validate(base | {
        "languages": ["en", "de"], "practice": {"enabled": False},
        "questionnaires": [*base["questionnaires"], OWN],
        "questionnaires_before": ["demographics", "muir_trust_rating", "own"]})


def test_a_german_participant_answers_german_questionnaires(live_server, browser):
    live_server.create_study("sprachen", config())
    page = open_page(browser, f"{live_server.url}/join/sprachen?lang=de&PROLIFIC_PID=p-de")
    messages = console_of(page)
    page.wait_for_url(re.compile(r"/p/"))
    page.locator("#consent-agree").click()
    page.locator("#instructions-done").click()

    expect(page.get_by_role("heading", name="Einige Fragen zu Ihrer Person")).to_be_visible()
    expect(page.locator("#survey-items")).to_have_attribute("lang", "de")
    gender = page.get_by_role("group", name=re.compile("Welchem Geschlecht ordnen Sie sich zu"))
    gender.get_by_role("radio", name="Keine Angabe").check()
    page.get_by_role("group", name=re.compile("Wie alt sind Sie")).get_by_role("radio", name="25–34").check()
    page.get_by_role("group", name=re.compile("Erfahrung haben Sie mit Robotern")).get_by_role(
        "radio", name="Keine", exact=True).check()
    page.get_by_role("group", name=re.compile("Videospiele")).get_by_role("radio", name="Jede Woche").check()
    shot(page, "de_demographics")
    page.locator("#survey-submit").click()

    expect(page.get_by_role("heading", name="Ihr Vertrauen in den Roboter")).to_be_visible()
    trust = page.locator('fieldset[data-item="trust"]')
    expect(trust.locator("legend")).to_have_text(re.compile("Wie sehr vertrauen Sie dem Roboter"))
    expect(trust).to_contain_text("Überhaupt nicht")
    expect(trust).to_contain_text("Voll und ganz")
    trust.locator('input[value="70"]').check()
    shot(page, "de_muir")
    page.locator("#survey-submit").click()

    # No German for this one: English, marked as such for screen readers and the browser's translation.
    expect(page.get_by_role("heading", name="One more question")).to_be_visible()
    expect(page.locator("#survey-heading")).to_have_attribute("lang", "en")
    expect(page.locator("#survey-items")).to_have_attribute("lang", "en")
    page.locator('fieldset[data-item="overall"] input[value="4"]').check()
    shot(page, "de_fallback_english")
    page.locator("#survey-submit").click()
    wait_for(page, "t.state !== null && t.state.phase !== 'questionnaire'")
    assert state(page)["language"] == "de"
    assert messages == []

    answers = live_server.admin("GET", "/api/admin/studies/sprachen/export/surveys.csv").text
    assert ",demographics,gender," in answers and "prefer_not_to_say" in answers and "Keine Angabe" not in answers
