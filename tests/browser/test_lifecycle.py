"""A draft study on the admin page: its join page says it has not started, a preview opens the participant's page
in a new tab in one click and shows in the table as a preview, deletable; the study is opened from the page."""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path

from playwright.sync_api import Page, expect

from tests.browser.test_admin import download, log_in
from tests.browser.test_participant_flow import demo_config

#: Where the screenshots go when TRUSTLAB_SHOTS names a directory (they are looked at, not compared).
SHOTS = os.environ.get("TRUSTLAB_SHOTS")


def shot(page: Page, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(SHOTS) / f"{name}.png"))


def test_draft_preview_and_open_from_the_admin_page(live_server, browser, tmp_path):
    browser.route(re.compile(r"/viewer/"), lambda route: route.abort())  # no 3D view: it is not what this tests
    config = demo_config()
    assert live_server.admin("POST", "/api/admin/studies", json={
        "slug": "pilot", "config": config.model_dump(mode="json")}).json()["status"] == "draft"
    live_server.create_study("running", config)  # created open
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))

    page.goto(f"{live_server.url}/join/pilot?PROLIFIC_PID=early")
    expect(page.get_by_role("heading", name="This study has not started yet")).to_be_visible()
    expect(page.locator("#join-message")).to_contain_text("have not opened this study to participants yet")
    shot(page, "join-draft")

    log_in(page, live_server)
    draft_row = page.locator('#studies-body tr[data-slug="pilot"]')
    expect(draft_row.locator(".badge")).to_have_text("draft")
    expect(page.locator('#studies-body tr[data-slug="running"] .badge')).to_have_text("open")
    expect(page.get_by_role("button", name="Close study running")).to_be_visible()
    shot(page, "admin-list-draft")

    draft_row.get_by_role("link").click()
    expect(page.locator("#study-status")).to_have_text("draft")
    expect(page.locator("#study-draft-note")).to_be_visible()
    expect(page.get_by_role("button", name="Open study")).to_be_visible()
    shot(page, "admin-study-draft")

    with browser.expect_page() as opened:
        page.get_by_role("button", name="Preview as participant").click()
    participant = opened.value
    participant.wait_for_url(re.compile(r"/p/[A-Za-z0-9_-]+$"))
    expect(participant.get_by_role("button", name="I agree to take part")).to_be_visible()
    expect(participant.locator("#preview-badge")).to_have_text("Preview session · left out of the data")
    shot(participant, "participant-preview")
    [preview] = live_server.admin("GET", "/api/admin/studies/pilot/participants").json()
    assert preview["preview"] is True
    row = page.locator(f'#participants-body tr[data-participant="{preview["public_id"]}"]')
    expect(row.locator(".badge-preview")).to_have_text("preview")
    expect(page.locator("#participants-summary")).to_have_text(
        "0 participants: no participants yet · 1 preview session")
    expect(row.get_by_role("button", name=re.compile("^Exclude"))).to_be_hidden()  # a preview is deleted, not excluded

    page.get_by_role("button", name="Open study").click()
    expect(page.locator("#study-status")).to_have_text("open")
    expect(page.locator("#study-draft-note")).to_be_hidden()
    assert live_server.admin("GET", "/api/admin/studies/pilot").json()["status"] == "open"
    joined = live_server.api("POST", "/api/studies/pilot/join", params={"PROLIFIC_PID": "first"})
    assert joined.status_code == 200 and joined.json()["state"]["preview"] is False
    joined_id = next(p["public_id"] for p in live_server.admin("GET", "/api/admin/studies/pilot/participants").json()
                     if not p["preview"])
    expect(page.locator("#participants-body tr")).to_have_count(2)
    participant.bring_to_front()
    participant.get_by_role("button", name="I agree to take part").click()  # the preview goes on as any session
    # At its end a preview shows the outcome's redirect but does not take the experimenter away to the recruitment
    # site; a participant's page counts down to it.
    debrief = ("([preview, url]) => import('/static/js/views.js').then((views) => { views.renderDebrief("
               "{preview, text: 'Thanks', completion: {outcome: 'completed', code: 'C1', redirect_url: url}}); "
               "return document.getElementById('redirect-countdown').textContent; })")
    elsewhere = f"{live_server.url}/static/css/participant.css?cc=C1"
    assert participant.evaluate(debrief, [True, elsewhere]).startswith("Preview session: a participant would be taken")
    expect(participant.locator("#redirect-link")).to_have_attribute("href", elsewhere)  # (its section is hidden here)
    participant.evaluate(debrief, [False, elsewhere])
    expect(participant.locator("#redirect-countdown")).to_contain_text("Taking you back in")
    participant.evaluate("() => import('/static/js/views.js').then((views) => views.cancelRedirect())")
    assert "/p/" in participant.url
    page.bring_to_front()
    shot(page, "admin-study-open-with-preview")

    page.get_by_role("tab", name="Data & report").click()
    people = download(page, "participants.csv", tmp_path).read_text(encoding="utf-8")
    assert preview["public_id"] not in people and people.count("\n") == 2  # the header and the real participant
    page.get_by_role("checkbox", name=re.compile("^Include my preview sessions")).check()
    shot(page, "admin-data-include-preview")
    people = csv.DictReader(io.StringIO(download(page, "participants.csv", tmp_path).read_text(encoding="utf-8")))
    assert {p["participant_id"]: p["preview"] for p in people} == {preview["public_id"]: "1", joined_id: "0"}
    expect(page.get_by_role("link", name="Open the report")).to_have_attribute(
        "href", "/api/admin/studies/pilot/report.html?include_preview=true")
    page.get_by_role("tab", name="Participants").click()

    row.get_by_role("button", name=f"Delete preview session {preview['public_id']}").click()
    expect(row).to_have_count(0)
    expect(page.locator("#participants-summary")).to_have_text("1 participant: 1 active")
    assert [p["preview"] for p in live_server.admin("GET", "/api/admin/studies/pilot/participants").json()] == [False]

    # closing says what it means: no new joins, running sessions go on
    page.get_by_role("button", name="Close study").click()
    expect(page.locator("#study-status")).to_have_text("closed")
    expect(page.locator("#study-closed-note")).to_contain_text(
        "nobody new can join, and sessions already running go on")
    expect(page.locator("#study-draft-note")).to_be_hidden()
    shot(page, "admin-study-closed")
    assert errors == []
