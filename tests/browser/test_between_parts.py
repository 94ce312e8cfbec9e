"""What a new participant noticed between the study's parts (issue 37), in the browser at 1280x720: the page that
ends the practice, the final score on the debrief, questions at the end that name no robot, the shelf questions
naming the robot, and a refused move saying what to do."""

from __future__ import annotations

import re

from playwright.sync_api import expect
from sqlalchemy import select

from experiment.config import PracticeConfig, PracticeTrial, StudyConfig, TimingConfig, TutorialConfig
from experiment.flow import QuestionnaireStep, ShelfSurveyStep
from experiment.instruments import SCHAEFER_14
from experiment.task import RewardTable, TaskParams
from experiment.templates import demo
from server.harness.driver import state, wait_for
from server.models import Event, Participant
from tests.browser.test_participant_flow import block_viewer, console_of

#: A decision window of an unround length, to see it is the config's that the page states.
TIMING = TimingConfig(decision_window_s=2.5, animation_speed=4.0, teleop_time_limit_s=60.0)


def config_with(**changes) -> StudyConfig:
    doc = demo().model_copy(update={"timing": TIMING}).model_dump(mode="json")
    return StudyConfig.model_validate(doc | changes)


def joined(live_server, browser, slug: str, pid: str):
    page = browser.new_page()
    block_viewer(page)
    page.goto(f"{live_server.url}/join/{slug}?PROLIFIC_PID={pid}")
    page.wait_for_url(re.compile(r"/p/"))
    wait_for(page, "t.state !== null")
    return page


def move(live_server, pid: str, step, score: float | None = None) -> None:
    with live_server.app.state.services.sessionmaker.begin() as session:
        participant = session.scalar(select(Participant).where(Participant.external_id == pid))
        participant.step, participant.block_order = step, ["trust_agnostic", "trust_aware"]
        if score is not None:
            participant.score = score


def test_the_practice_ends_with_a_page_saying_choices_now_count(live_server, browser):
    practice = PracticeConfig(trials=[PracticeTrial(complexity="low", robot_action="auto", human_action_hint="rely")])
    live_server.create_study("ends", config_with(practice=practice.model_dump(mode="json")))
    page = joined(live_server, browser, "ends", "p-ends")
    console = console_of(page)
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()
    wait_for(page, "t.state.phase === 'practice_done'", timeout=60_000)  # the practice trial played out
    heading = page.get_by_role("heading", level=1)
    expect(heading).to_have_text("The practice is over")
    expect(heading).to_be_focused()
    expect(page.locator("#view-practice-done")).to_contain_text("From now on, your choices count.")
    expect(page.locator("#practice-done-window")).to_have_text(
        "When the robot says it will collect an item by itself, you have 2.5 seconds to press Intervene (or Space) "
        "and collect it yourself. If you do not, the robot tries by itself.")
    expect(page.locator("#practice-done-robots")).to_contain_text("2 robots, one after the other: Robot A and Robot B")
    expect(page.locator("#practice-done-points")).to_contain_text("Every item now scores points")
    # the last practice item's outcome (the trial screen gave way at once): the robot's attempt, success or not
    outcome = page.evaluate("(last) => import('/static/js/trial.js').then((m) => m.describeOutcome(last)[0])",
                            state(page)["last_trial"])
    assert outcome.startswith("The robot ") and outcome.endswith("Practice: no points.")
    expect(page.locator("#practice-done-last")).to_have_text(f"Last practice item: {outcome}")
    page.get_by_role("button", name="Continue").click()
    wait_for(page, "t.state.phase === 'trial'")
    assert state(page)["step"] == {"phase": "trial", "block": 1, "trial": 1}
    with live_server.app.state.services.sessionmaker() as session:
        steps = [e.payload["phase"] for e in session.scalars(select(Event).where(Event.kind == "step")
                                                            .order_by(Event.id))]
    assert steps[-3:] == ["practice", "practice_done", "trial"]  # recorded like every step
    assert console == []


def test_the_debrief_shows_the_final_score_only_when_the_study_plays_for_points(live_server, browser):
    live_server.create_study("scored", config_with(questionnaires_end=["comments"]))
    unscored = TaskParams(rewards=RewardTable(auto_rely_success=0, auto_rely_failure=0, auto_intervene=0, ask=0))
    live_server.create_study("unscored", config_with(task=unscored.model_dump(mode="json")))
    page = joined(live_server, browser, "scored", "p-scored")
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("heading", name="Instructions").wait_for()
    move(live_server, "p-scored", QuestionnaireStep(context="end", questionnaire="comments"), score=-4.0)
    page.reload()
    wait_for(page, "t.state && t.state.phase === 'questionnaire'")
    expect(page.get_by_role("heading", level=1)).to_have_text("Anything else?")
    expect(page.locator("#survey-about")).to_be_hidden()  # at the end of the study: no robot named
    page.get_by_role("button", name="Continue").click()
    page.get_by_role("heading", name="Thank you!").wait_for()
    expect(page.locator("#final-score")).to_have_text("Your final score: −4 points.")

    other = joined(live_server, browser, "unscored", "p-unscored")
    other.get_by_role("button", name="I agree to take part").click()
    other.get_by_role("heading", name="Instructions").wait_for()
    move(live_server, "p-unscored", QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id))
    other.reload()
    wait_for(other, "t.state && t.state.phase === 'questionnaire'")
    expect(other.locator("#survey-about")).to_contain_text("These questions are about Robot B")
    for item in SCHAEFER_14.items:
        other.locator(f'fieldset[data-item="{item.id}"] input[value="50"]').check()
    other.get_by_role("button", name="Continue").click()
    other.get_by_role("heading", name="Thank you!").wait_for()
    expect(other.locator("#final-score")).to_be_hidden()


def test_the_shelf_questions_name_the_robot_the_page_names(live_server, browser):
    live_server.create_study("shelf", config_with())
    page = joined(live_server, browser, "shelf", "p-shelf")
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("heading", name="Instructions").wait_for()
    move(live_server, "p-shelf", ShelfSurveyStep(block=2, shelf=1, trial=3))
    page.reload()
    wait_for(page, "t.state && t.state.phase === 'shelf_survey'")
    expect(page.locator("#survey-about")).to_have_text("You have just finished shelf 1 with Robot B.")
    expect(page.locator('fieldset[data-item="trust"] legend')).to_have_text(
        "1. To what extent do you trust Robot B in this scenario?")
    expect(page.locator('fieldset[data-item="reliance"] legend')).to_have_text(
        "2. To what extent did you rely on Robot B in this scenario?")


def test_a_refused_move_says_which_key_to_let_go_and_which_way_back(live_server, browser):
    """The guided practice teleoperation: the tutorial says which way each key moves; holding F (down) from above
    the item until the arm would hit the shelf, the page says to let go of F and move back up with R."""
    practice = PracticeConfig(trials=[PracticeTrial(complexity="low", robot_action="ask")],
                              tutorial=TutorialConfig(time_limit_s=300.0))
    live_server.create_study("blocked", config_with(practice=practice.model_dump(mode="json")))
    page = joined(live_server, browser, "blocked", "p-blocked")
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()
    wait_for(page, "t.state.trial && t.state.trial.stage === 'teleop' && t.teleopClient.guidance", timeout=60_000)
    expect(page.locator("#tutorial-keys")).to_have_text(
        "In the World view: W to the shelf · S back to you · A left · D right · R up · F down")
    expect(page.locator("#guide-text")).to_contain_text("hold ")
    page.keyboard.down("KeyF")
    try:
        expect(page.locator("#guide-blocked")).to_be_visible(timeout=20_000)
        expect(page.locator("#guide-blocked")).to_have_text(
            "Blocked: moving down, the arm would hit something. Let go of F, then move back with R (up).")
    finally:
        page.keyboard.up("KeyF")
    # with two keys held sideways, both are named, with the way back and over
    advice = page.evaluate("""() => window.__trustlab.teleopPanel.blockedAdvice(["x+", "y+"])""")
    assert advice == ("Blocked: moving towards the shelf and left, the arm would hit something. Let go of W and A, "
                      "then move back with S (away from the shelf) and D (right) or up with R to pass over it.")
