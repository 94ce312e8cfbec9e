"""Issue 41 in the browser, the participant's rights: "Withdraw from the study" from a trial in the 2-D view with the
keyboard (the study keeps the data) and from the consent page in German (the study deletes them, and redirects as
configured);
the recruitment id in no URL after the join; "Delete data" from the dashboard. Screenshots in SCREENSHOTS."""

from __future__ import annotations

import re
from pathlib import Path

from playwright.sync_api import Page, expect
from sqlalchemy import func, select

from experiment.outcomes import CompletionConfig
from experiment.privacy import PrivacyConfig
from server.harness.driver import export_rows, wait_for
from server.i18n import catalogue
from server.models import Participant, Trial
from server.services.sessions import hash_token
from tests.browser.test_admin import log_in, row_of
from tests.browser.test_participant_flow import block_viewer, console_of, demo_config

SCREENSHOTS = Path("/tmp/trustlab-screenshots")
RECRUITMENT = "https://recruit.example"


def joined(page: Page, link: str, secret: str) -> str:
    """Open the join link; the participant's page is reached and no URL after the join page's holds ``secret``."""
    requests: list[str] = []
    page.on("request", lambda request: requests.append(request.url))
    page.goto(link)
    page.wait_for_url(re.compile(r"/p/"))
    wait_for(page, "t.state !== null")
    assert requests[0] == link and not [url for url in requests[1:] if secret in url]
    assert secret not in page.url and secret not in page.evaluate("document.referrer + location.href")
    return page.url.rsplit("/p/", 1)[1]


def keep_from_a_trial_in_the_2d_view(live_server, browser) -> str:
    page = browser.new_page()
    block_viewer(page)  # no 3D view: the 2-D view stands in
    problems = console_of(page)
    token = joined(page, f"{live_server.url}/join/wkeep?PROLIFIC_PID=secret-keep&SESSION_ID=s1", "secret-keep")
    page.get_by_role("button", name="I agree to take part").click()
    wait_for(page, "t.state.phase === 'instructions'")
    page.locator("#instructions-done").click()
    wait_for(page, "t.state.phase === 'practice' && t.state.trial !== null")
    expect(page.locator("#helper2d")).to_be_visible()

    link = page.get_by_role("button", name="Withdraw from the study")
    link.focus()
    page.keyboard.press("Enter")
    dialog = page.get_by_role("dialog", name="Withdraw from the study?")
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text("kept for the research, marked as withdrawn")
    cancel = dialog.get_by_role("button", name="No, continue the study")
    expect(cancel).to_be_focused()  # the safe choice first
    page.keyboard.press("KeyW")  # the dialog's keys are its own: no arm, no camera, no Intervene
    page.keyboard.press("Digit2")
    page.keyboard.press("Tab")
    expect(dialog.get_by_role("button", name="Yes, withdraw and end my session")).to_be_focused()
    page.screenshot(path=str(SCREENSHOTS / "withdraw-dialog-2d-trial.png"))
    page.keyboard.press("Escape")
    expect(dialog).to_be_hidden()
    expect(link).to_be_focused()
    page.keyboard.press("Enter")  # again, and Space on the focused "continue" closes it too
    expect(cancel).to_be_focused()
    page.keyboard.press("Space")
    expect(dialog).to_be_hidden()
    assert page.evaluate("window.__trustlab.state.phase") == "practice"

    link.click()
    dialog.get_by_role("button", name="Yes, withdraw and end my session").click()
    expect(page.locator("h1:focus")).to_have_text("You have withdrawn from the study")
    expect(page.locator("#end-text")).to_contain_text("recruitment ID has been erased")
    expect(link).to_be_hidden()
    page.screenshot(path=str(SCREENSHOTS / "withdraw-end-kept.png"))
    page.reload()  # the end stays, in the participant's words
    expect(page.locator("h1:focus")).to_have_text("You have withdrawn from the study")
    assert problems == []

    keys = [r for r in export_rows(live_server, "wkeep", "events.csv") if r["kind"] == "client.key_down"]
    assert [r for r in keys if '"KeyW"' in r["payload"] or '"Digit2"' in r["payload"]] == []
    with live_server.app.state.services.sessionmaker() as session:
        row = session.scalar(select(Participant).where(Participant.token_hash == hash_token(token)))
        assert row.status == "withdrawn"
        assert row.external_id is None and row.excluded
        assert session.scalar(select(func.count()).select_from(Trial).where(Trial.participant_id == row.id)) >= 1
    page.close()
    return token


def delete_from_the_consent_page(live_server, browser) -> None:
    """In German (the join link's lang): the link, the dialog and the end page in the catalogue's words."""
    german = catalogue("de").messages
    page = browser.new_page()
    block_viewer(page)
    page.route(f"{RECRUITMENT}/**", lambda route: route.fulfill(body="<h1>Returned</h1>", content_type="text/html"))
    joined(page, f"{live_server.url}/join/wdel?PROLIFIC_PID=secret-del&lang=de", "secret-del")
    expect(page.get_by_role("heading", name=german["consent.title"])).to_be_visible()
    page.get_by_role("button", name=german["withdraw.link"]).click()
    dialog = page.get_by_role("dialog")
    expect(dialog.get_by_role("heading")).to_have_text(german["withdraw.heading"])
    expect(dialog).to_contain_text(german["withdraw.delete"])
    expect(dialog.get_by_role("button", name=german["withdraw.cancel"])).to_be_focused()
    page.screenshot(path=str(SCREENSHOTS / "withdraw-dialog-delete.png"))
    dialog.get_by_role("button", name=german["withdraw.confirm"]).click()
    expect(page.locator("#end-heading")).to_have_text(german["withdraw.end_heading"])
    expect(page.locator("#end-text")).to_have_text(german["withdraw.end_deleted"])
    expect(page.locator("#end-code-value")).to_have_text("RETURNED-7")
    page.screenshot(path=str(SCREENSHOTS / "withdraw-end-deleted.png"))
    page.wait_for_url(f"{RECRUITMENT}/return?cc=RETURNED-7", timeout=10_000)  # the study's redirect
    assert live_server.admin("GET", "/api/admin/studies/wdel/participants").json() == []
    assert export_rows(live_server, "wdel", "participants.csv") == []
    page.close()


def delete_from_the_dashboard(live_server, browser) -> None:
    other = live_server.api("POST", "/api/studies/wkeep/join", json={"params": {"PROLIFIC_PID": "stays"}}).json()
    people = {p["public_id"]: p for p in live_server.admin("GET", "/api/admin/studies/wkeep/participants").json()}
    [withdrawn] = [pid for pid, p in people.items() if p["status"] == "withdrawn"]
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/wkeep/participants")
    row = row_of(page, withdrawn)
    button = row.get_by_role("button", name=f"Delete this participant's data ({withdrawn})")
    button.click()
    dialog = page.get_by_role("dialog")
    expect(dialog).to_contain_text("Only an audit line that names no one remains")
    dialog.get_by_label("Reason (kept in the audit log)").fill("asked by email")
    dialog.get_by_label(re.compile("I understand that this deletes the data")).check()
    page.screenshot(path=str(SCREENSHOTS / "dashboard-delete-dialog.png"))
    dialog.get_by_role("button", name="Delete data").click()
    expect(dialog).to_be_hidden()
    expect(row).to_have_count(0)
    remaining = live_server.admin("GET", "/api/admin/studies/wkeep/participants").json()
    assert [p["external_id"] for p in remaining] == ["stays"] and other["created"]
    page.reload()
    expect(page.locator("#study-personal-data")).to_contain_text("1 participant's data deleted")
    page.screenshot(path=str(SCREENSHOTS / "dashboard-after-delete.png"))
    page.close()


def test_withdraw_from_the_page_in_both_modes_and_delete_from_the_dashboard(live_server, browser):
    SCREENSHOTS.mkdir(exist_ok=True)
    live_server.create_study("wkeep", demo_config())  # privacy.withdrawal: keep (the default)
    live_server.create_study("wdel", demo_config(
        languages=["en", "de"], privacy=PrivacyConfig(withdrawal="delete"),
        completion=CompletionConfig(code_withdrawn="RETURNED-7",
                                    redirect_withdrawn=f"{RECRUITMENT}/return?cc={{code}}")))
    keep_from_a_trial_in_the_2d_view(live_server, browser)
    delete_from_the_consent_page(live_server, browser)
    delete_from_the_dashboard(live_server, browser)
