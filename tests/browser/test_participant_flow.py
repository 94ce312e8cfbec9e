"""A participant completes the demo study in the browser, and the export holds exactly what they did."""

from __future__ import annotations

import re
import time
from typing import Any

from playwright.sync_api import Page, expect

from experiment.config import CompletionConfig, TimingConfig
from experiment.templates import demo
from server.harness.driver import Teleoperator, export_rows, state, trial_key, wait_for

#: The robot at 2x: attempts stay short, and teleoperation (sped up as much, at most 8x) stays at a pace the key-holding
#: driver, like a person, can steer.
#: (The "Next item" pause shortened: browser tests go through many items.)
TIMING = TimingConfig(decision_window_s=2.0, animation_speed=2.0, teleop_time_limit_s=60.0, next_item_pause_s=0.5)
#: The whole demo, played through here: the robot at 4x, which halves its attempts (8 of them) and, as much, its
#: teleoperations (6), which the driver still steers to the item and the bin (3-4 s each, against 5-6 s at 2x). The
#: other pages' tests keep ``TIMING``.
FLOW_TIMING = TIMING.model_copy(update={"animation_speed": 4.0})


def demo_config(**changes: Any):
    return demo().model_copy(update={"timing": TIMING, **changes})


def block_viewer(page: Page) -> None:
    """The page must work without the 3D view; leaving it out keeps SwiftShader off the two CPU cores."""
    page.route(re.compile(r"/viewer/"), lambda route: route.abort())


def console_of(page: Page) -> list[str]:
    """Every console message (of any type) and uncaught exception of ``page`` from now on, but the browser's note
    of the 3D view refused by ``block_viewer``."""
    messages: list[str] = []
    page.on("console", lambda m: "/viewer/" in m.location.get("url", "")
            or messages.append(f"{m.type}: {m.text} at {m.location} on {page.url}"))
    page.on("pageerror", lambda e: messages.append(f"uncaught: {e} on {page.url}"))
    return messages


def heading_ring(page: Page) -> str:
    """The focus ring of the focused element (a heading the page focused): its outline style."""
    return page.evaluate("() => getComputedStyle(document.activeElement).outlineStyle")


class Participant:
    """Plays the demo: records every decision and answer it makes."""

    def __init__(self, page: Page):
        self.page = page
        self.interventions: list[tuple] = []
        self.relied: list[tuple] = []
        self.teleops = 0
        self.answers: dict[str, dict[str, float]] = {}
        self.checked_missing = False
        self.ignored_hint = False

    def play(self) -> dict[str, Any]:
        handled = None
        for _ in range(400):
            s = state(self.page)
            marker = (s["phase"], repr(s["step"]), repr(trial_key(s)), s["trial"] and s["trial"]["stage"])
            if marker == handled:
                time.sleep(0.05)
                continue
            handled = marker
            if s["phase"] == "debrief":
                return s
            self.step(s)
        raise AssertionError(f"the study did not end: {state(self.page)}")

    def step(self, s: dict[str, Any]) -> None:
        phase = s["phase"]
        if phase == "consent":
            # How long it takes, from the config (the study's own estimate), before agreeing.
            expect(self.page.locator("#consent-duration")).to_have_text(f"The study takes {s['duration']['text']} in "
                                                                        "all.")
            expect(self.page.locator("h1:focus")).to_have_text("Consent to take part")
            assert heading_ring(self.page) == "none"  # focused for screen readers, without a ring
            self.page.get_by_role("button", name="I agree to take part").click()
        elif phase == "instructions":
            expect(self.page.locator("#instructions-duration")).to_contain_text(s["duration"]["text"])
            self.back_button()
            # How to collect an item, with the time limit, before the first teleoperation.
            expect(self.page.get_by_role("heading", name="Collecting an item yourself")).to_be_visible()
            expect(self.page.locator("#howto-limit")).to_have_text("60 seconds")
            expect(self.page.locator("#howto-tutorial")).to_contain_text("guided tutorial")
            self.page.get_by_role("button", name=re.compile("^Continue")).click()
        elif phase == "practice_done":
            # Between the practice and the scored trials: choices count now, with the window's length (config).
            expect(self.page.get_by_role("heading", level=1)).to_have_text("The practice is over")
            expect(self.page.locator("#practice-done-window")).to_contain_text(
                f"you have {TIMING.decision_window_s:g} seconds to press Intervene")
            self.page.get_by_role("button", name="Continue").click()
            wait_for(self.page, "t.state.phase !== 'practice_done'")
        elif phase in ("questionnaire", "shelf_survey"):
            self.survey(s)
        elif s["ready_to_start"]:
            wait_for(self.page, "t.state.trial !== null || t.state.phase !== arg", arg=phase)
        else:
            self.trial(s)

    def back_button(self) -> None:
        """Back keeps the participant on the page, says why, and the page goes on working."""
        url = self.page.url
        self.page.go_back()
        expect(self.page.locator("#notice")).to_contain_text("The Back button does not take you to an earlier page")
        assert self.page.url == url and state(self.page)["phase"] == "instructions"
        self.page.get_by_role("button", name="OK").click()
        expect(self.page.locator("#notice")).to_be_hidden()

    def trial(self, s: dict[str, Any]) -> None:
        t, key = s["trial"], trial_key(s)
        # Robots are named by the order the participant meets them, whichever policy comes first.
        robot = "Robot" if t["practice"] else f"Robot {'AB'[t['block'] - 1]}"
        expect(self.page.locator("#block-label")).to_have_text("Practice" if t["practice"] else robot)
        expect(self.page.locator("#robot-heading")).to_have_text(robot)
        if t["stage"] == "decision":
            if key == (False, 1, 1):
                self.page.keyboard.press("Digit3")  # a camera preset (the view itself is left out here)
                expect(self.page.get_by_role("button", name="End effector")).to_have_attribute("aria-pressed", "true")
            self.decide(s, key)
        elif t["stage"] == "teleop":
            if self.teleops == 0:  # the first teleoperation is the guided tutorial: the page walks through the steps
                expect(self.page.locator("#tutorial-banner")).to_have_text(re.compile(r"Guided practice: try 1 of \d"))
                wait_for(self.page, "t.teleopClient.guidance")
                guidance = self.page.evaluate("window.__trustlab.teleopClient.guidance")
                expect(self.page.locator("#guide-text")).to_have_text(guidance["text"])
                expect(self.page.locator("#guide-steps li[aria-current=step]")).to_have_count(1)
            self.teleops += 1
            start = time.monotonic()
            sent = Teleoperator(self.page).run()
            print(f"teleop {key}: {time.monotonic() - start:.1f} s, {sent} messages")
        wait_for(self.page, "!t.state.trial || t.state.trial.stage !== arg", arg=t["stage"], timeout=30_000)

    def decide(self, s: dict[str, Any], key: tuple) -> None:
        t = s["trial"]
        scored = [k for k in self.interventions if not k[0]]
        asked = t["practice"] and t["expected_human_action"] == "intervene"
        # The first practice item that asks to intervene is let go: the page then says the hint was not followed.
        ignore_hint = asked and not self.ignored_hint
        intervene = (asked and not ignore_hint) or (not t["practice"] and (
            len(scored) == 0 or (t["block"] == 2 and len(scored) < 2)))
        expect(self.page.locator("#countdown-text")).to_contain_text("s left to intervene")
        if not intervene:
            self.relied.append(key)
            if ignore_hint:
                self.ignored_hint = True
                expect(self.page.locator("#hint")).to_contain_text(
                    "you were asked to intervene, but you let the robot go on. In the scored part the choice is yours",
                    timeout=60_000)
            return
        self.interventions.append(key)
        expect(self.page.get_by_role("button", name="Intervene")).to_be_enabled()
        if t["practice"] or t["block"] == 1:
            self.page.keyboard.press("Space")
        else:
            self.page.get_by_role("button", name="Intervene").click()
        wait_for(self.page, "!t.state.trial || t.state.trial.stage !== 'decision'")

    def survey(self, s: dict[str, Any]) -> None:
        q = s["questionnaire"]
        page = self.page
        expect(page.get_by_role("heading", level=1)).to_have_text(q["title"])
        assert "HRI" not in q["title"] and "reliance" not in q["title"].lower()  # plain words, not the instrument
        if s["step"].get("block"):
            expect(page.locator("#survey-about")).to_contain_text(f"Robot {'AB'[s['step']['block'] - 1]}")
        scale = q["scale"]
        points = [scale["min"] + i * scale["step"]
                  for i in range(round((scale["max"] - scale["min"]) / scale["step"]) + 1)]
        chosen = {item["id"]: points[(3 * i + len(self.answers) + 2) % len(points)]
                  for i, item in enumerate(q["items"])}
        skip = q["items"][-1]["id"] if not self.checked_missing and len(q["items"]) > 2 else None
        for item_id, value in chosen.items():
            if item_id != skip:
                page.locator(f'fieldset[data-item="{item_id}"] input[value="{value:g}"]').check()
        if skip:
            self.checked_missing = True
            page.get_by_role("button", name="Continue").click()
            expect(page.get_by_role("alert")).to_contain_text("Please answer question 14")
            expect(page.locator(f'fieldset[data-item="{skip}"]')).to_have_attribute("aria-invalid", "true")
            assert state(page)["questionnaire"]["context"] == q["context"]  # nothing was sent
            page.locator(f'fieldset[data-item="{skip}"] input[value="{chosen[skip]:g}"]').check()
        page.get_by_role("button", name="Continue").click()
        self.answers[q["context"]] = chosen
        wait_for(page, "!t.state.questionnaire || t.state.questionnaire.context !== arg", arg=q["context"])


def test_participant_completes_the_demo_in_the_browser(live_server, browser):
    redirect_url = f"{live_server.url}/static/css/participant.css?cc={{code}}"
    config = demo_config(completion=CompletionConfig(redirect_url=redirect_url), timing=FLOW_TIMING)
    live_server.create_study("demo", config)
    page = browser.new_page()
    block_viewer(page)
    console = console_of(page)  # join, consent, instructions, practice, trials, questionnaires, debrief: all empty
    started = time.monotonic()
    page.goto(f"{live_server.url}/join/demo?PROLIFIC_PID=p-browser-1&STUDY_ID=s1&SESSION_ID=x1")
    page.wait_for_url(re.compile(r"/p/[A-Za-z0-9_\-]+$"))
    expect(page.get_by_role("heading", name="Consent to take part")).to_be_visible()

    player = Participant(page)
    final = player.play()

    expect(page.get_by_role("heading", name="Thank you!")).to_be_visible()
    expect(page.locator("#compensation")).to_be_hidden()  # the demo pays nothing itself: no "0.00 USD"
    # ... but it plays for points: the final score, the sum of the scored trials' rewards
    expect(page.locator("#final-score")).to_have_text(
        re.compile(rf"^Your final score: {'−' if final['score'] < 0 else ''}{abs(final['score']):g} points?\.$"))
    assert final["completion"]["compensation"] is None
    outcome = "(last) => import('/static/js/trial.js').then((m) => m.describeOutcome(last)[0])"
    zero = {**final["last_trial"], "practice": False, "reward": 0, "score": 5, "human_action": "intervene"}
    assert page.evaluate(outcome, zero).endswith("No points. Score: 5.")  # not "±0 points"
    code = final["completion"]["code"]
    expect(page.locator("#completion-code")).to_have_text(code)
    expect(page.get_by_role("link", name="Return to the recruitment site")).to_have_attribute(
        "href", re.compile(f"cc={code}$"))
    page.evaluate("window.__trustlab.events.flush()")
    wait_for(page, "t.events.queue.length === 0 && !t.events.sending")
    page.wait_for_url(re.compile(f"cc={code}$"), timeout=15_000)  # the auto-redirect, after the code was shown
    print(f"demo completed in {time.monotonic() - started:.1f} s with {player.teleops} teleoperations")
    assert console == []

    trials = [r for r in export_rows(live_server, "demo", "trials.csv")]
    scored = [r for r in trials if r["practice"] == "0"]
    assert len(scored) == 12 and len([r for r in trials if r["practice"] == "1"]) == 4
    assert final["final_score"] == final["score"] == sum(float(r["reward"]) for r in scored)
    # "Robot A" was block 1 (its position), whichever policy it ran: position and policy are both recorded.
    order = live_server.admin("GET", "/api/admin/studies/demo/participants").json()[0]["block_order"]
    assert {(r["block"], r["block_name"]) for r in scored} == {("1", order[0]), ("2", order[1])}
    intervened = {(int(r["block"]), int(r["trial"])) for r in scored
                  if r["human_action"] == "intervene" and r["robot_action"] == "auto"}
    assert intervened == {(b, n) for _, b, n in player.interventions if not _}
    relied = {(int(r["block"]), int(r["trial"])) for r in scored if r["human_action"] == "rely"}
    assert relied == {(b, n) for p, b, n in player.relied if not p}
    for r in scored:
        if (int(r["block"]), int(r["trial"])) in intervened:
            assert r["robot_action"] == "auto" and float(r["decision_time_ms"]) > 0
    answers = export_rows(live_server, "demo", "surveys.csv")
    given = {(ctx, item): value for ctx, items in player.answers.items() for item, value in items.items()}
    assert {(r["context"], r["item"]): float(r["value"]) for r in answers} == given
    assert len(answers) == len(given) == 4 * 2 + 2 * 14

    events = export_rows(live_server, "demo", "events.csv")
    kinds = [e["kind"] for e in events]
    assert kinds.count("client.decision_window_opened") == sum(1 for r in trials if r["robot_action"] == "auto")
    assert kinds.count("client.intervene_pressed") == len(player.interventions)
    assert {"client.page_loaded", "client.key_down", "client.key_up", "client.camera", "camera"} <= set(kinds)
