"""A reload, a reopened tab or a lost response resumes the same step and duplicates nothing."""

from __future__ import annotations

import re
import time

from playwright.sync_api import Page, Route, expect
from sqlalchemy import func, select

from experiment.config import PracticeConfig, PracticeTrial
from experiment.instruments import SCHAEFER_14, SHELF_TRUST_RELIANCE
from server.harness.driver import Teleoperator, state, trial_key, wait_for, wait_until_stopped
from server.models import Answer, Participant, Trial
from tests.browser.test_participant_flow import block_viewer, demo_config

PRACTICE = PracticeConfig(trials=[PracticeTrial(complexity="low", robot_action="auto", human_action_hint="rely"),
                                  PracticeTrial(complexity="low", robot_action="ask")])


def counts(server, external_id: str) -> tuple[int, int]:
    """(trial rows, answer rows) of one participant."""
    with server.app.state.services.sessionmaker() as session:
        pid = session.scalar(select(Participant.id).where(Participant.external_id == external_id))
        trials = session.scalar(select(func.count()).select_from(Trial).where(Trial.participant_id == pid))
        answers = session.scalar(select(func.count()).select_from(Answer).where(Answer.participant_id == pid))
    return trials, answers


def open_page(browser, url: str, dialogs: list[str] | None = None) -> Page:
    """The page at ``url``; it leaves when asked to (a "Leave site?" prompt is accepted and noted in ``dialogs``)."""
    page = browser.new_page()
    block_viewer(page)
    page.on("dialog", lambda dialog: (dialogs is not None and dialogs.append(dialog.type), dialog.accept()))
    page.goto(url)
    wait_for(page, "t.state !== null")
    return page


def draft_size(server, external_id: str) -> int:
    with server.app.state.services.sessionmaker() as session:
        draft = session.scalar(select(Participant.survey_draft).where(Participant.external_id == external_id))
    return len(draft["answers"]) if draft else 0


def test_reload_reopen_and_lost_responses_resume_without_duplicates(live_server, browser):
    live_server.create_study("resume", demo_config(practice=PRACTICE, questionnaires_before=[
        SCHAEFER_14.id, SHELF_TRUST_RELIANCE.id]))
    dialogs: list[str] = []
    page = open_page(browser, f"{live_server.url}/join/resume?PROLIFIC_PID=p-resume", dialogs)
    page.wait_for_url(re.compile(r"/p/"))
    url = page.url
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()

    # Mid-trial, during the decision window: a reload shows the same trial, still undecided or attempted.
    wait_for(page, "t.state.trial && t.state.trial.stage === 'decision'")
    before = trial_key(state(page))
    page.reload()
    assert dialogs == ["beforeunload"]  # leaving a running trial asks first (its window would pass unanswered)
    wait_for(page, "t.state !== null && t.state.trial !== null")
    assert trial_key(state(page)) == before
    assert counts(live_server, "p-resume") == (1, 0)

    # Mid-teleoperation: move the arm a little (precise moves, on-screen button held until the server says the arm
    # moves), close the tab, open the link again: same trial, same arm.
    wait_for(page, "t.state.trial && t.state.trial.trial === 2 && t.teleopClient.ready", timeout=30_000)
    start = page.evaluate("window.__trustlab.teleopClient.world.joints")
    page.get_by_label("Precise moves").check()
    page.get_by_role("button", name="Up").hover()
    page.mouse.down()
    wait_for(page, "t.teleopClient.lastWorldMessage && t.teleopClient.lastWorldMessage.moving")
    page.mouse.up()
    wait_until_stopped(page)
    page.get_by_label("Precise moves").uncheck()
    moved = page.evaluate("window.__trustlab.teleopClient.world.joints")
    assert moved != start
    page.close()
    page = open_page(browser, url)
    wait_for(page, "t.teleopClient.world !== null")
    assert trial_key(state(page)) == (True, 0, 2)
    assert page.evaluate("window.__trustlab.teleopClient.world.joints") == moved
    Teleoperator(page).run()

    # The practice is over: a reload shows that page again, and its Continue goes on.
    wait_for(page, "t.state.phase === 'practice_done'")
    page.reload()
    wait_for(page, "t.state !== null && t.state.phase === 'practice_done'")
    page.get_by_role("button", name="Continue").click()

    # Mid-survey: the answers given so far are kept (a draft on the server) and come back with a reload.
    wait_for(page, "t.state.phase === 'questionnaire'")
    items = [item["id"] for item in state(page)["questionnaire"]["items"]]
    given = {item: 10 * (i % 11) for i, item in enumerate(items[:7])}
    for item, value in given.items():
        page.locator(f'fieldset[data-item="{item}"] input[value="{value}"]').check()
    deadline = time.monotonic() + 10
    while draft_size(live_server, "p-resume") < 7 and time.monotonic() < deadline:
        time.sleep(0.1)
    page.reload()
    wait_for(page, "t.state !== null && t.state.phase === 'questionnaire'")
    for item, value in given.items():
        expect(page.locator(f'fieldset[data-item="{item}"] input[value="{value}"]')).to_be_checked()
    expect(page.locator("#survey-form input:checked")).to_have_count(7)
    assert counts(live_server, "p-resume") == (2, 0)

    # A second tab answers the page; the first (now out of date) says so at its next answer and moves on.
    other = open_page(browser, page.url)
    expect(other.locator("#survey-form input:checked")).to_have_count(7)  # the same draft
    for item in items[7:]:
        other.locator(f'fieldset[data-item="{item}"] input[value="50"]').check()
    other.get_by_role("button", name="Continue").click()
    wait_for(other, "t.state.phase === 'questionnaire' && t.state.questionnaire.id === arg",
             arg=SHELF_TRUST_RELIANCE.id)
    other.close()
    page.locator(f'fieldset[data-item="{items[7]}"] input[value="90"]').check()
    expect(page.locator("#notice")).to_contain_text("already been answered in another tab or window")
    expect(page.locator("#notice")).to_contain_text("The answers on this page were not saved")
    wait_for(page, "t.state.questionnaire && t.state.questionnaire.id === arg", arg=SHELF_TRUST_RELIANCE.id)
    expect(page.locator("#notice")).to_be_visible()  # still there on the page it moved to
    assert counts(live_server, "p-resume") == (2, 14)
    assert draft_size(live_server, "p-resume") == 0

    # The answers reach the server but the response is lost: the page retries with the same key.
    lost: list[str] = []

    def lose_response(route: Route) -> None:
        if not lost:
            lost.append(route.request.headers["idempotency-key"])
            route.fetch()  # the server records the answers…
            route.abort("connectionreset")  # …and the page never hears back
        else:
            assert route.request.headers["idempotency-key"] == lost[0]
            route.continue_()

    page.route(re.compile(r"/api/p/[^/]+/answers$"), lose_response)
    for item in state(page)["questionnaire"]["items"]:
        page.locator(f'fieldset[data-item="{item["id"]}"] input[value="6"]').check()
    page.get_by_role("button", name="Continue").click()
    wait_for(page, "t.state.phase === 'trial'")
    assert len(lost) == 1
    assert counts(live_server, "p-resume") == (2, 16)
    page.evaluate("window.__trustlab.events.flush()")
    wait_for(page, "t.events.queue.length === 0")
    events = live_server.admin("GET", "/api/admin/studies/resume/export/events.csv").text
    assert "client.disconnected" in events and "client.reconnected" in events
