"""Issue 36 in the browser: the join link reopened in the same browser resumes; the same id in another browser gets a
session of its own (flagged); a join whose answer was lost resumes when the page retries it."""

from __future__ import annotations

import re
from pathlib import Path

from playwright.sync_api import Page, Route

from experiment.config import RecruitmentConfig
from server.harness.browser import browser_session
from server.harness.driver import wait_for
from tests.browser.conftest import serving
from tests.browser.test_participant_flow import block_viewer, console_of, demo_config

SCREENSHOTS = Path("/tmp/trustlab-screenshots")


def joined(browser, url: str) -> tuple[Page, str]:
    """A new tab of ``browser`` on the join link ``url``: the tab and the session token it was sent to."""
    page = browser.new_page()
    block_viewer(page)
    page.goto(url)
    page.wait_for_url(re.compile(r"/p/"))
    wait_for(page, "t.state !== null")
    return page, page.url.rsplit("/p/", 1)[1]


def test_the_join_link_resumes_in_its_browser_and_not_in_another(live_server, browser, playwright, tmp_path):
    live_server.create_study("claims", demo_config())
    link = f"{live_server.url}/join/claims?PROLIFIC_PID=p-owner&STUDY_ID=st"
    page, token = joined(browser, link)
    problems = console_of(page)
    page.get_by_role("button", name="I agree to take part").click()
    wait_for(page, "t.state.phase === 'instructions'")
    page.close()

    page, again = joined(browser, link)  # the tab closed, the link opened again in the same browser
    assert again == token and page.evaluate("window.__trustlab.state.phase") == "instructions"
    page.goto(link)  # a reload of the join link itself
    page.wait_for_url(re.compile(r"/p/"))
    assert page.url.endswith(f"/p/{token}")

    with browser_session(tmp_path / "other-profile", playwright=playwright) as other:  # another browser, the owner's id
        intruder, theirs = joined(other, link)
        assert theirs != token and intruder.evaluate("window.__trustlab.state.phase") == "consent"
    people = live_server.admin("GET", "/api/admin/studies/claims/participants").json()
    assert len(people) == 2 and all([f["code"] for f in p["flags"]] == ["duplicate_id"] for p in people)
    assert problems == []


def test_a_first_join_whose_answer_is_lost_resumes_when_the_page_retries(live_server, browser):
    live_server.create_study("claims", demo_config())
    page = browser.new_page()
    block_viewer(page)
    lost: list[str] = []

    def lose_answer(route: Route) -> None:
        if not lost:
            lost.append(route.request.post_data or "")
            route.fetch()  # the server starts the session ...
            route.abort("connectionreset")  # ... and the page never hears back
        else:
            assert route.request.post_data == lost[0]  # the same resume key again
            route.continue_()

    page.route(re.compile(r"/api/studies/claims/join"), lose_answer)
    page.goto(f"{live_server.url}/join/claims?pid=3")
    page.wait_for_url(re.compile(r"/p/"), timeout=30_000)
    people = live_server.admin("GET", "/api/admin/studies/claims/participants").json()
    assert len(lost) == 1 and "resume_key" in lost[0] and len(people) == 1 and people[0]["flags"] == []


def test_the_join_page_says_when_a_network_holds_too_many_unconsented_places(sqlite_template, tmp_path, browser):
    with serving(sqlite_template, tmp_path, max_unconsented_per_address=1) as live:
        live.create_study("claims", demo_config(recruitment=RecruitmentConfig(max_active_participants=10)))
        assert live.api("POST", "/api/studies/claims/join").status_code == 200  # one unconsented, same address
        page = browser.new_page()
        page.goto(f"{live.url}/join/claims?pid=4")
        heading = page.get_by_role("heading", name="Please wait a moment")
        heading.wait_for()
        assert "try again in" in page.locator("#join-message").inner_text()
        assert page.get_by_role("button", name="Try again").is_visible()
        SCREENSHOTS.mkdir(exist_ok=True)
        page.screenshot(path=str(SCREENSHOTS / "join-address-busy.png"))
