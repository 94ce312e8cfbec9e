"""Clear pages for an unknown or closed study, an invalid link, declining, and a withdrawn session."""

from __future__ import annotations

import re

from playwright.sync_api import expect

from experiment.config import CompletionConfig
from tests.browser.driver import wait_for
from tests.browser.test_participant_flow import block_viewer, demo_config


def test_join_errors_decline_and_withdrawal(live_server, browser):
    config = demo_config(completion=CompletionConfig(code_declined="NO-THANKS"))
    live_server.create_study("open", config)
    live_server.create_study("shut", config)
    assert live_server.admin("POST", "/api/admin/studies/shut/close").status_code == 200
    page = browser.new_page()
    block_viewer(page)

    page.goto(f"{live_server.url}/join/nope?PROLIFIC_PID=a")
    expect(page.get_by_role("heading", name="Study not found")).to_be_visible()
    page.goto(f"{live_server.url}/join/shut?PROLIFIC_PID=a")
    expect(page.get_by_role("heading", name="This study is closed")).to_be_visible()
    page.goto(f"{live_server.url}/p/{'x' * 32}")
    expect(page.get_by_role("heading", name="This link is not valid")).to_be_visible()

    page.goto(f"{live_server.url}/join/open?PROLIFIC_PID=decliner")
    page.wait_for_url(re.compile(r"/p/"))
    participant_url = page.url
    page.go_back()  # the join link was replaced in the history: Back does not join again
    assert "/join/" not in page.url
    page.goto(participant_url)
    page.get_by_role("button", name="I do not agree").click()
    expect(page.get_by_role("heading", name="You chose not to take part")).to_be_visible()
    expect(page.locator("#end-code-value")).to_have_text("NO-THANKS")
    page.reload()  # still declined, with the same code
    expect(page.locator("#end-code-value")).to_have_text("NO-THANKS")

    page.goto(f"{live_server.url}/join/open?PROLIFIC_PID=withdrawn")
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("button", name="I agree to take part").click()
    expect(page.get_by_role("heading", name="Instructions")).to_be_visible()
    public_id = next(p["public_id"] for p in live_server.admin("GET", "/api/admin/studies/open/participants").json()
                     if p["status"] == "active")
    response = live_server.admin("POST", f"/api/admin/studies/open/participants/{public_id}/withdraw",
                                 json={"reason": "test"})
    assert response.status_code == 200, response.text
    page.get_by_role("button", name=re.compile("^Continue")).click()  # refused: the page shows why
    wait_for(page, "t.state.phase === 'withdrawn'")
    expect(page.get_by_role("heading", name="This session was withdrawn")).to_be_visible()
