"""The designer shows the server's warnings (issue 41: a questionnaire asked without a translation for a language
the study offers) apart from its problems: the study stays valid, the warning names the questionnaire's place."""

from __future__ import annotations

import json

from playwright.sync_api import expect

from tests.browser.conftest import LiveServer
from tests.browser.test_designer import raw_config


def test_the_designer_warns_of_a_questionnaire_without_a_language_the_study_offers(live_server: LiveServer,
                                                                                   browser, tmp_path):
    page = browser.new_page()
    page.goto(f"{live_server.url}/admin")
    page.get_by_label("Admin token").fill(live_server.admin_token)
    page.keyboard.press("Enter")
    page.get_by_label("Template", exact=True).select_option("policy-evaluation")
    page.get_by_label("Slug (used in the join link)").fill("wave-de")
    page.get_by_role("button", name="Create study").click()
    expect(page.locator("#config-problems-none")).to_have_text("No problems found.")
    expect(page.locator("#config-warnings li")).to_have_count(0)

    page.get_by_role("button", name="Advanced: raw JSON").click()
    config = raw_config(page)
    config["languages"] = ["en", "de"]
    config["questionnaires"].append({
        "id": "own", "title": "Our question", "instructions": "One more.", "scale": {"min": 1, "max": 5, "step": 1},
        "scoring": "none", "items": [{"id": "note", "kind": "text", "text": "Anything else?", "required": False}]})
    config["questionnaires_before"] = [*config["questionnaires_before"], "own"]
    page.get_by_label("Study configuration (JSON)").fill(json.dumps(config, indent=2))

    warnings = page.locator("#config-warnings li")
    expect(warnings).to_have_count(1)
    expect(page.locator("#config-warnings-detail")).to_have_text(
        "1 warning (the study can still be saved and run):")
    own = [q["id"] for q in config["questionnaires"]].index("own")
    expect(warnings.locator("code")).to_have_text(f"questionnaires[{own}]")
    expect(warnings).to_contain_text("questionnaire 'own' has no translation for de")
    expect(page.locator("#config-problems-none")).to_have_text("No problems found.")
    expect(page.locator("#config-problems li")).to_have_count(0)
    page.screenshot(path=str(tmp_path / "designer-warning.png"))
