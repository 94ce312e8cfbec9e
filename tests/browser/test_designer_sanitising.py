"""Study config strings in the designer are text: markup in a title, a block's name or an item's text is shown as
written, and nothing in it runs or makes a request (json-editor turns titles into text through a detached
element's ``innerHTML``, which loads an ``<img>``'s source and runs its ``onerror``)."""

from __future__ import annotations

import json

from playwright.sync_api import expect

from tests.browser.conftest import LiveServer
from tests.browser.test_designer import raw_config, shot

#: Markup an experimenter (or whoever got hold of a study's config) could put in any text of a study.
HOSTILE = '<img src="/hostile-image" onerror="window.__ran=(window.__ran||0)+1"><b>x</b>'


def _with_markup(config: dict) -> dict:
    """The config with the hostile markup in its free texts: title, description, page texts, block labels, items."""
    marked = json.loads(json.dumps(config))
    for key in ("title", "description"):
        marked[key] += HOSTILE
    for key in ("title", "block_label", "consent", "instructions", "debrief"):
        marked["texts"][key] += HOSTILE
    for block in marked["blocks"]:
        block["label"] += HOSTILE
    for questionnaire in marked["questionnaires"]:
        for item in questionnaire["items"]:
            item["text"] += HOSTILE
    return marked


def test_markup_in_config_strings_is_shown_as_text_and_never_runs(live_server: LiveServer, browser):
    page = browser.new_page()
    requested: list[str] = []
    page.on("request", lambda request: requested.append(request.url))
    page.goto(f"{live_server.url}/admin")
    page.get_by_label("Admin token").fill(live_server.admin_token)
    page.keyboard.press("Enter")
    page.get_by_label("Template", exact=True).select_option("policy-evaluation")
    page.get_by_label("Slug (used in the join link)").fill("wave-1")
    page.get_by_role("button", name="Create study").click()
    expect(page.locator("#designer-summary")).to_contain_text("80 scored + 4 practice")
    page.get_by_role("button", name="Advanced: raw JSON").click()
    hostile = _with_markup(raw_config(page))
    page.get_by_label("Study configuration (JSON)").fill(json.dumps(hostile, indent=2))
    page.get_by_role("button", name="Form").click()
    expect(page.locator("#designer-summary")).to_contain_text("80 scored + 4 practice")
    title = page.locator('[data-schemapath="root.title"] input')
    expect(title).to_have_value(hostile["title"])  # the text as written, markup and all
    shot(page, "designer-markup-as-text")
    # nothing was parsed as HTML: no element from a config string, no request for its image, no handler run
    assert page.locator("#designer-form img").count() == 0
    assert page.evaluate("[...document.querySelectorAll('#designer-form b')].every(b => b.textContent !== 'x')")
    assert page.evaluate("window.__ran") is None
    assert not [url for url in requested if "hostile-image" in url]
    # and the form keeps every string exactly: saving it would not drop a text's markup
    page.get_by_role("button", name="Advanced: raw JSON").click()
    assert raw_config(page) == hostile
