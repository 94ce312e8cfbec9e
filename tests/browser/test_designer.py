"""The study designer in the real browser: a study from a template in the form, a block's policy and schedule
changed, the server's message beside a bad field, the summary following the edits, save, the raw JSON view's
round trip, the diff of the two versions, and duplicating the study. Screenshots go to TRUSTLAB_SHOTS_DIR when
that is set (to look at; nothing is asserted on them)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from playwright.sync_api import Page, expect

from experiment.iohmm import model_document, paper_params
from tests.browser.conftest import LiveServer

SHOTS = os.environ.get("TRUSTLAB_SHOTS_DIR")


def shot(page: Page, name: str) -> None:
    if SHOTS:
        page.screenshot(path=str(Path(SHOTS) / f"{name}.png"))


def field(page: Page, path: str):
    """The visible input of a form field by json-editor's path (e.g. root.blocks.1.schedule.n_low)."""
    return page.locator(f'[data-schemapath="{path}"] input:visible').first


def raw_config(page: Page) -> dict:
    return json.loads(page.get_by_label("Study configuration (JSON)").input_value())


def test_design_a_study_in_the_form(live_server: LiveServer, browser):
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.add_init_script("localStorage.setItem('trustlab.designer-author', 'Ada')")
    page.goto(f"{live_server.url}/admin")
    page.get_by_label("Admin token").fill(live_server.admin_token)
    page.keyboard.press("Enter")
    page.get_by_label("Template", exact=True).select_option("policy-evaluation")
    page.get_by_label("Slug (used in the join link)").fill("wave-1")
    # the checks are held: until the server has looked, the page does not say there is no problem (every check: the
    # form, once built, may ask again, and on a loaded machine its check comes while the first is held)
    held: list = []
    released = False

    def hold(route) -> None:
        route.continue_() if released else held.append(route)

    page.route("**/api/admin/study-config/check", hold)
    page.get_by_role("button", name="Create study").click()
    expect(page.locator("#config-problems-none")).to_have_text("Checking…")
    while not held:
        page.wait_for_timeout(50)
    expect(page.locator("#config-problems-none")).to_have_text("Checking…")
    released = True
    for route in held:
        route.continue_()
    expect(page.locator("#config-problems-none")).to_have_text("No problems found.")
    page.unroute("**/api/admin/study-config/check")

    # the form, filled with the template, and its summary
    expect(page.get_by_role("button", name="Form")).to_have_attribute("aria-pressed", "true")
    summary = page.locator("#designer-summary")
    expect(summary).to_contain_text("trust-aware: asks in high complexity when the belief of high trust ≤ 0.69")
    expect(summary).to_contain_text("80 scored + 4 practice")
    expect(summary).to_contain_text("trust_agnostic → trust_aware")
    expect(field(page, "root.title")).to_have_value("Policy evaluation (paper study 2)")
    expect(page.get_by_label("Your name")).to_have_value("Ada")
    shot(page, "designer-summary")

    # a block's policy: another kind, with a bad value the server explains beside the field
    page.get_by_label("Kind of blocks[1].policy", exact=True).select_option("random_assist")
    p_ask_high = field(page, "root.blocks.1.policy.p_ask_high")
    p_ask_high.fill("1.5")
    p_ask_high.press("Tab")
    problem = page.locator('[data-schemapath="root.blocks.1.policy.p_ask_high"] .field-problem')
    expect(problem).to_contain_text("less than or equal to 1")
    expect(p_ask_high).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#config-problems li")).to_contain_text("blocks[1].policy.p_ask_high")
    problem.scroll_into_view_if_needed()
    shot(page, "designer-validation")
    page.locator("#config-problems li").get_by_role("button").click()  # the listed problem leads to its field
    expect(p_ask_high).to_be_focused()
    p_ask_high.fill("0.5")
    p_ask_high.press("Tab")
    expect(problem).to_have_count(0)
    # … and its schedule
    n_low = field(page, "root.blocks.1.schedule.n_low")
    n_low.fill("10")
    n_low.press("Tab")
    expect(summary).to_contain_text("random: asks with probability 0.1 in low and 0.5 in high complexity")
    expect(summary).to_contain_text("70 scored + 4 practice")
    page.get_by_role("button", name="Validate and save").click()
    expect(page.locator("#config-status")).to_have_text("Saved as version 2.")
    saved = live_server.admin("GET", "/api/admin/studies/wave-1").json()["config"]
    assert saved["blocks"][1]["policy"] == {"kind": "random_assist", "p_ask_low": 0.1, "p_ask_high": 0.5}
    assert saved["blocks"][1]["schedule"] == {"kind": "counts", "n_low": 10, "n_high": 20}

    # the raw JSON view round-trips exactly, both ways
    page.get_by_role("button", name="Advanced: raw JSON").click()
    text = page.get_by_label("Study configuration (JSON)").input_value()
    assert json.loads(text) == saved
    page.get_by_role("button", name="Form").click()
    page.get_by_role("button", name="Advanced: raw JSON").click()
    assert page.get_by_label("Study configuration (JSON)").input_value() == text
    edited = json.loads(text)
    edited["shelf_size"] = 4
    edited["questionnaires"][1]["citation"] = "Schaefer (2016), edited"
    edited["texts"]["debrief"] = "Thanks — “quoted”, ünïcode"
    edited["blocks"][0]["policy"].update(model=model_document(paper_params()), p_high=0.4)  # a document in a field
    edited["blocks"].append({"name": "given", "label": "", "questionnaires_after": [],
                             "policy": {"kind": "trust_agnostic", "intervention_rate_low": None,
                                        "intervention_rate_high": 0.2, "actions": {"low": "auto", "high": "ask"}},
                             "schedule": {"kind": "bernoulli", "n_trials": 5, "p_high": 0.5}})
    edited["completion"]["redirect_url"] = "https://example.org/done?cc={code}"
    page.get_by_label("Study configuration (JSON)").fill(json.dumps(edited, indent=2))
    page.get_by_role("button", name="Form").click()
    expect(field(page, "root.shelf_size")).to_have_value("4")
    page.get_by_role("button", name="Advanced: raw JSON").click()
    assert raw_config(page) == edited
    # a problem inside a collapsed section is shown at the section
    edited["completion"]["code_completed"] = ""
    page.get_by_label("Study configuration (JSON)").fill(json.dumps(edited, indent=2))
    page.get_by_role("button", name="Form").click()
    expect(page.locator('[data-schemapath="root.completion"] .field-problem')).to_contain_text("at least 1 character")
    page.get_by_role("button", name="Discard changes").click()
    expect(page.locator(".field-problem")).to_have_count(0)
    page.get_by_role("button", name="Advanced: raw JSON").click()
    assert raw_config(page) == saved

    # versions, and the changes between them side by side
    page.get_by_role("button", name="Versions").click()
    versions = page.locator("#versions-table tbody tr")
    expect(versions).to_have_count(2)
    expect(versions.nth(1)).to_contain_text("Ada")
    page.get_by_role("button", name="Show changes").click()
    expect(page.locator("#diff-heading")).to_have_text("Changes from v1 to v2: 7")  # kind, 3 removed, 2 added, n_low
    kind = page.locator("#diff-table tr", has_text="blocks[1].policy.kind")
    expect(kind.locator("td").nth(0)).to_have_text('"trust_agnostic"')
    expect(kind.locator("td").nth(1)).to_have_text('"random_assist"')
    expect(page.locator("#diff-table tr", has_text="blocks[1].schedule.n_low")).to_contain_text("10")
    expect(page.locator("#diff-table tr", has_text="blocks[1].policy.intervention_rate_low")).to_contain_text("removed")
    shot(page, "designer-diff")

    # duplicate for the next wave
    page.get_by_role("button", name="Duplicate study…").click()
    expect(page.get_by_label("Slug of the copy (used in its join link)")).to_have_value("wave-2")
    page.get_by_role("button", name="Duplicate", exact=True).click()
    expect(page.get_by_role("heading", name="Policy evaluation (paper study 2) (copy)")).to_be_visible()
    copy = live_server.admin("GET", "/api/admin/studies/wave-2").json()
    assert copy["config"]["blocks"] == saved["blocks"]
    assert live_server.admin("GET", "/api/admin/studies/wave-2/versions").json()[0]["author"] == "Ada"
    assert errors == []


def test_the_form_fits_the_screen_and_its_fields_say_what_they_take(live_server: LiveServer, browser):
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.goto(f"{live_server.url}/admin")
    page.get_by_label("Admin token").fill(live_server.admin_token)
    page.keyboard.press("Enter")
    page.get_by_label("Template", exact=True).select_option("policy-evaluation")
    page.get_by_label("Slug (used in the join link)").fill("wave-1")
    page.get_by_role("button", name="Create study").click()
    summary = page.locator("#designer-summary")
    expect(summary).to_contain_text("80 scored + 4 practice")

    # form and summary fit one 1280×720 screen below the header, whose actions stay on it
    viewport = page.viewport_size
    assert page.evaluate("document.scrollingElement.scrollHeight") <= viewport["height"]
    for part in ("#designer-form", "#designer-summary", "#study-toggle", "#study-preview", "#config-save"):
        box = page.locator(part).bounding_box()
        assert box and box["y"] >= 0 and box["y"] + min(box["height"], 120) <= viewport["height"], part
    assert page.locator("#designer-form").bounding_box()["height"] >= 300

    # readable titles; numbers are number inputs with their bounds; enums are selects, booleans check boxes
    shelf = page.get_by_label("Trials per shelf")
    expect(shelf).to_have_attribute("type", "number")
    expect(shelf).to_have_attribute("min", "1")
    expect(shelf).to_have_attribute("max", "200")
    expect(shelf).to_have_attribute("step", "1")
    expect(page.locator('[data-schemapath="root.shelf_size"] .je-bounds')).to_have_text("whole number 1 to 200")
    window = page.get_by_label("Decision window (s)")
    expect(window).to_have_attribute("step", "any")
    expect(page.locator('[data-schemapath="root.timing.decision_window_s"] .je-bounds')).to_have_text("> 0, ≤ 60")
    assert page.get_by_label("Counterbalancing").evaluate("e => e.tagName") == "SELECT"
    enabled = page.locator('[data-schemapath="root.practice.enabled"] input')
    expect(enabled).to_have_attribute("type", "checkbox")
    expect(enabled).to_be_checked()
    expect(enabled).to_have_attribute("aria-describedby", "root[practice][enabled]-description")
    expect(page.locator('[id="undefined-description"]')).to_have_count(0)  # each check box its own description

    # every collapse button is named by its section, and says whether it is expanded
    timing = page.get_by_role("button", name="Collapse Timing", exact=True)
    expect(timing).to_have_attribute("aria-expanded", "true")
    timing.click()
    expect(page.get_by_role("button", name="Expand Timing", exact=True)).to_have_attribute("aria-expanded", "false")
    expect(window).to_be_hidden()
    expect(page.get_by_role("button", name="Expand Task", exact=True)).to_be_visible()
    names = page.locator("#designer-form button.json-editor-btntype-toggle").evaluate_all(
        "buttons => buttons.map(b => b.getAttribute('aria-label'))")
    assert None not in names and "Collapse Block 1" in names

    # a schedule switched to bernoulli starts from the model's example, valid at once
    page.get_by_label("Kind of blocks[0].schedule", exact=True).select_option("bernoulli")
    expect(field(page, "root.blocks.0.schedule.n_trials")).to_have_value("40")
    expect(field(page, "root.blocks.0.schedule.p_high")).to_have_value("0.5")
    expect(summary).to_contain_text("probability 0.5")
    expect(page.locator("#config-problems li")).to_have_count(0)
    expect(page.locator(".field-problem")).to_have_count(0)
    shot(page, "designer-fit")
    page.get_by_role("button", name="Advanced: raw JSON").click()
    assert raw_config(page)["blocks"][0]["schedule"] == {"kind": "bernoulli", "n_trials": 40, "p_high": 0.5}
    assert errors == []
