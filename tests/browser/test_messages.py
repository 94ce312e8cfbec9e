"""Clear pages for an unknown, closed or full study, an invalid link, declining (asked twice), a withdrawn session,
and a payment shown only by a study that pays."""

from __future__ import annotations

import re

from playwright.sync_api import expect
from sqlalchemy import select

from experiment.config import CompensationConfig, CompletionConfig, RecruitmentConfig
from experiment.flow import QuestionnaireStep
from experiment.instruments import SCHAEFER_14
from server.harness.driver import wait_for
from server.models import Participant
from tests.browser.test_participant_flow import block_viewer, console_of, demo_config

#: The browser's own note of a request the server refused, which these pages are about (nothing else may be logged).
REFUSED = re.compile(r"^error: Failed to load resource: the server responded with a status of (404|410|503) ")


def test_join_errors_decline_and_withdrawal(live_server, browser):
    config = demo_config(completion=CompletionConfig(code_declined="NO-THANKS"))
    live_server.create_study("open", config)
    live_server.create_study("shut", config)
    live_server.create_study("paid", demo_config(compensation=CompensationConfig(base=5.0, currency="GBP")))
    assert live_server.admin("POST", "/api/admin/studies/shut/close").status_code == 200
    page = browser.new_page()
    block_viewer(page)
    console = console_of(page)

    page.goto(f"{live_server.url}/join/nope?PROLIFIC_PID=a")
    expect(page.get_by_role("heading", name="Study not found")).to_be_visible()
    page.goto(f"{live_server.url}/join/shut?PROLIFIC_PID=a")
    expect(page.get_by_role("heading", name="This study is closed")).to_be_visible()
    page.goto(f"{live_server.url}/p/{'x' * 32}")
    expect(page.get_by_role("heading", name="This link is not valid")).to_be_visible()
    assert len(console) == 3 and all(REFUSED.match(m) for m in console), console
    console.clear()

    # A full study (its cap on active participants reached) says so at once, and lets the participant try again.
    live_server.create_study("full", demo_config(recruitment=RecruitmentConfig(max_active_participants=1)))
    holder = live_server.api("POST", "/api/studies/full/join", params={"PROLIFIC_PID": "holder"}).json()["token"]
    page.goto(f"{live_server.url}/join/full?PROLIFIC_PID=late")
    expect(page.get_by_role("heading", name="This study is full right now")).to_be_visible()
    expect(page.locator("#join-message")).to_have_text(re.compile(r"^Please try again in a few minutes"))
    expect(page.locator("#connection")).to_be_hidden()  # told, not retried behind "reconnecting…"
    page.get_by_role("button", name="Try again").click()
    expect(page.locator("#join-message")).to_contain_text("It was still full at")
    assert live_server.api("POST", f"/api/p/{holder}/consent", json={"agree": False}).status_code == 200  # frees it
    page.get_by_role("button", name="Try again").click()
    expect(page.get_by_role("button", name="I agree to take part")).to_be_visible()
    assert len(console) == 2 and all(REFUSED.match(m) for m in console), console  # the two refused joins
    console.clear()

    page.goto(f"{live_server.url}/join/open?PROLIFIC_PID=decliner")
    page.wait_for_url(re.compile(r"/p/"))
    participant_url = page.url
    page.go_back()  # the join link was replaced in the history: Back does not join again
    assert "/join/" not in page.url
    assert all(REFUSED.match(m) for m in console), console  # Back showed the invalid link's page (404) again
    page.goto(participant_url)
    console.clear()
    # "I do not agree" asks again; "No" keeps the session, "Yes" ends it.
    page.get_by_role("button", name="I do not agree").click()
    expect(page.locator("#decline-confirm")).to_contain_text("Do you really not want to take part?")
    page.get_by_role("button", name="No, go back").click()
    expect(page.locator("#decline-confirm")).to_be_hidden()
    expect(page.get_by_role("button", name="I agree to take part")).to_be_visible()
    assert live_server.admin("GET", "/api/admin/studies/open/participants").json()[0]["status"] == "active"
    page.get_by_role("button", name="I do not agree").click()
    page.get_by_role("button", name="Yes, I do not want to take part").click()
    expect(page.get_by_role("heading", name="You chose not to take part")).to_be_visible()
    expect(page.locator("#end-code-value")).to_have_text("NO-THANKS")
    page.reload()  # still declined, with the same code
    expect(page.locator("#end-code-value")).to_have_text("NO-THANKS")
    assert console == []  # the consent and declined pages log nothing

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
    assert console and all(REFUSED.match(m) for m in console), console  # the refused step (410), nothing else
    console.clear()

    # A study that pays shows the payment on the debrief (the demo, which does not, shows none: the flow test).
    page.goto(f"{live_server.url}/join/paid?PROLIFIC_PID=paid")
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("button", name="I agree to take part").click()
    expect(page.get_by_role("heading", name="Instructions")).to_be_visible()
    with live_server.app.state.services.sessionmaker.begin() as session:  # straight to the last questionnaire
        participant = session.scalar(select(Participant).where(Participant.external_id == "paid"))
        participant.block_order = ["trust_aware", "trust_agnostic"]
        participant.step = QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id)
    page.reload()
    wait_for(page, "t.state && t.state.phase === 'questionnaire'")
    for item in SCHAEFER_14.items:
        page.locator(f'fieldset[data-item="{item.id}"] input[value="50"]').check()
    page.get_by_role("button", name="Continue").click()
    expect(page.get_by_role("heading", name="Thank you!")).to_be_visible()
    expect(page.locator("#compensation")).to_have_text("Your payment: 5.00 GBP")
    assert console == []
