"""Issue 41 in the browser: a whole study in German (every page photographed, no English on any of them), the
language kept over a reload, and the pages right to left in Arabic (chosen by the browser's Accept-Language).

The screenshots are saved under the test's temporary folder (``screenshots/``; its path is printed).
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

from playwright.sync_api import Page, expect

from experiment.config import (
    AlwaysAutoSpec,
    BlockConfig,
    PracticeConfig,
    PracticeTrial,
    StudyConfig,
    TextsConfig,
    TimingConfig,
)
from experiment.schedule import CountsSchedule
from experiment.task import Complexity, RobotAction
from server import i18n
from server.harness.driver import Teleoperator, export_rows, state, trial_key, wait_for
from tests.browser.test_participant_flow import block_viewer, console_of

#: A sped-up study with every kind of page: consent, instructions, a practice item the robot tries and one it asks
#: help with (the guided teleoperation), the page after the practice, two scored items (one taken over), the shelf
#: questionnaire, the questions at the end, the debrief.
TIMING = TimingConfig(decision_window_s=2.0, animation_speed=2.0, teleop_time_limit_s=60.0, next_item_pause_s=0.5)


def study(languages: list[str]) -> StudyConfig:
    return StudyConfig(
        title="languages", languages=languages, counterbalance="none", shelf_size=2, timing=TIMING,
        practice=PracticeConfig(trials=[
            PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.AUTO, human_action_hint="rely"),
            PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.ASK)]),
        blocks=[BlockConfig(name="auto", policy=AlwaysAutoSpec(), schedule=CountsSchedule(n_low=2, n_high=0))],
        questionnaires_end=["demographics"],
        texts=TextsConfig(consent={language: CONSENT[language] for language in languages}),
    )


CONSENT = {"de": "Sie nehmen an einer Studie über Roboter teil. Die Teilnahme ist freiwillig.",
           "en": "You take part in a study about robots. Taking part is voluntary.",
           "ar": "أنت تشارك في دراسة عن الروبوتات. المشاركة طوعية."}


def english_phrases() -> set[str]:
    """The English catalogue's sentences that German says differently (fragments between placeholders of at least
    12 characters): none of them may be on a German page."""
    english, german = (i18n.translated(i18n.read_catalog(tag), tag) for tag in ("en", "de"))
    phrases = set()
    for key, text in english.items():
        for form in text.values() if isinstance(text, dict) else [text]:
            if german.get(key) == text:
                continue
            plain = re.sub(r"<[^>]+>", "", form)
            phrases |= {part.strip() for part in re.split(r"\{\w+\}", plain) if len(part.strip()) >= 12}
    return phrases


class Walker:
    """Goes through the study as a participant would, photographing each kind of page once."""

    def __init__(self, page: Page, shots: Path, english: set[str]):
        self.page, self.shots, self.english = page, shots, english
        self.taken: list[str] = []
        self.intervened = False

    def shot(self, name: str) -> None:
        if name in self.taken:
            return
        self.page.wait_for_timeout(150)  # the page's own focus and layout settled
        self.page.screenshot(path=str(self.shots / f"{len(self.taken) + 1:02d}-{name}.png"))
        self.taken.append(name)
        self.no_english()

    def no_english(self) -> None:
        shown = self.page.evaluate("() => document.body.innerText")
        found = sorted(phrase for phrase in self.english if phrase in shown)
        assert not found, f"English on the German page: {found}"
        assert self.page.evaluate("() => document.documentElement.lang") == "de"

    def play(self) -> dict[str, Any]:
        handled = None
        for _ in range(400):
            s = state(self.page)
            if s is None:  # the page is loading its words
                time.sleep(0.05)
                continue
            marker = (s["phase"], repr(s["step"]), repr(trial_key(s)), s["trial"] and s["trial"]["stage"])
            if marker == handled:
                time.sleep(0.05)
                continue
            handled = marker
            if s["phase"] == "debrief":
                expect(self.page.locator("#debrief-heading")).to_have_text("Vielen Dank!")
                self.shot("debrief")
                return s
            self.step(s)
        raise AssertionError(f"the study did not end: {state(self.page)}")

    def step(self, s: dict[str, Any]) -> None:
        page, phase = self.page, s["phase"]
        if phase == "consent":
            expect(page.locator("#consent-heading")).to_have_text("Einwilligung zur Teilnahme")
            expect(page.locator("#consent-text")).to_have_text(CONSENT["de"])  # the lab's own German text
            expect(page.locator("#consent-duration")).to_contain_text("Minuten")
            self.shot("consent")
            page.get_by_role("button", name="Ich bin nicht einverstanden").click()
            self.shot("consent-decline-asked")
            page.get_by_role("button", name="Nein, zurück").click()
            page.get_by_role("button", name="Ich bin mit der Teilnahme einverstanden").click()
        elif phase == "instructions":
            expect(page.get_by_role("heading", name="Einen Gegenstand selbst holen")).to_be_visible()
            page.reload()  # the language is the session's: a reload keeps it
            expect(page.locator("#instructions-heading")).to_have_text("Anleitung")
            expect(page.locator("#howto-limit")).to_have_text("60 Sekunden")
            self.shot("instructions")
            page.get_by_role("button", name="Weiter zur Übung").click()
        elif phase == "practice_done":
            expect(page.locator("#practice-done-window")).to_contain_text("haben Sie 2 Sekunden")
            self.shot("practice-done")
            page.get_by_role("button", name="Weiter").click()
            wait_for(page, "t.state.phase !== 'practice_done'")
        elif phase in ("questionnaire", "shelf_survey"):
            self.survey(s)
        elif s["ready_to_start"]:
            wait_for(page, "t.state.trial !== null || t.state.phase !== arg", arg=phase)
        else:
            self.trial(s)

    def trial(self, s: dict[str, Any]) -> None:
        t, page = s["trial"], self.page
        where = "practice" if t["practice"] else "scored"
        expect(page.locator("#block-label")).to_have_text("Übung" if t["practice"] else "Roboter A")
        if t["stage"] == "decision":
            expect(page.locator("#countdown-text")).to_contain_text("zum Eingreifen")
            expect(page.locator("#robot-message")).to_have_text(re.compile(r"^Ich hole die .+ selbst\.$"))
            self.shot(f"{where}-decision")
            if not t["practice"] and not self.intervened:
                self.intervened = True
                page.get_by_role("button", name="Eingreifen").click()
                wait_for(page, "!t.state.trial || t.state.trial.stage !== 'decision'")
        elif t["stage"] == "teleop":
            wait_for(page, "t.teleopClient.guidance")
            expect(page.locator("#teleop-heading")).to_have_text("Den Gegenstand holen")
            expect(page.locator("#teleop-status")).to_contain_text("Greifer:")
            if t["practice"]:
                expect(page.locator("#tutorial-banner")).to_contain_text("Geführte Übung: Versuch 1 von")
            self.shot(f"{where}-teleop")
            Teleoperator(page).run()
        elif t["stage"] == "presenting":
            self.shot(f"{where}-presenting")
        wait_for(page, "!t.state.trial || t.state.trial.stage !== arg", arg=t["stage"], timeout=30_000)

    def survey(self, s: dict[str, Any]) -> None:
        page, q = self.page, s["questionnaire"]
        expect(page.get_by_role("heading", level=1)).to_have_text(q["title"])
        page.get_by_role("button", name="Weiter").click()  # nothing answered: the page says what is missing
        expect(page.locator("#survey-error")).to_contain_text("Bitte beantworten Sie")
        self.shot(f"survey-{q['id']}-missing")
        for item in q["items"]:
            fieldset = page.locator(f'fieldset[data-item="{item["id"]}"]')
            if item["kind"] == "text":
                fieldset.locator("textarea").fill("Keine")
            else:
                fieldset.locator("input").first.check()
        self.shot(f"survey-{q['id']}")
        page.get_by_role("button", name="Weiter").click()
        wait_for(page, "!t.state.questionnaire || t.state.questionnaire.context !== arg", arg=q["context"])


def test_the_whole_study_in_german(live_server, browser, tmp_path) -> None:
    live_server.create_study("sprachen", study(["en", "de"]))
    shots = tmp_path / "screenshots"
    shots.mkdir()
    print(f"screenshots: {shots}")
    page = browser.new_page()
    page.set_extra_http_headers({"Accept-Language": "en-US,en;q=0.9"})  # the link's lang wins over the browser's
    block_viewer(page)
    console = console_of(page)
    page.goto(f"{live_server.url}/join/sprachen?lang=de&PROLIFIC_PID=p-de")
    page.wait_for_url(re.compile(r"/p/[A-Za-z0-9_\-]+$"))
    walker = Walker(page, shots, english_phrases())
    final = walker.play()
    assert final["language"] == "de"
    assert {"consent", "instructions", "practice-decision", "practice-teleop", "practice-done", "scored-decision",
            "scored-teleop", "debrief"} <= set(walker.taken), walker.taken
    assert any(name.startswith("survey-") for name in walker.taken)
    assert console == [], console
    # The export says which language the participant saw.
    rows = export_rows(live_server, "sprachen", "participants.csv")
    assert [row["language"] for row in rows] == ["de"]
    # The join page of a study that is full or closed speaks the browser's language too.
    live_server.admin("POST", "/api/admin/studies/sprachen/close")
    page.goto(f"{live_server.url}/join/sprachen?lang=de&PROLIFIC_PID=p-late")
    expect(page.locator("#join-heading")).to_have_text("Diese Studie ist geschlossen")
    walker.shot("join-closed")


def test_right_to_left_in_arabic(live_server, browser, tmp_path) -> None:
    live_server.create_study("rtl", study(["en", "ar"]))
    shots = tmp_path / "screenshots"
    shots.mkdir()
    print(f"screenshots: {shots}")
    page = browser.new_page()
    page.set_extra_http_headers({"Accept-Language": "ar-EG,ar;q=0.9,en;q=0.5"})  # no lang in the link: the browser's
    block_viewer(page)
    page.goto(f"{live_server.url}/join/rtl?PROLIFIC_PID=p-ar")
    page.wait_for_url(re.compile(r"/p/[A-Za-z0-9_\-]+$"))
    expect(page.locator("#consent-heading")).to_have_text("الموافقة على المشاركة")
    assert page.evaluate("() => [document.documentElement.lang, document.documentElement.dir]") == ["ar", "rtl"]
    expect(page.locator("#consent-text")).to_have_text(CONSENT["ar"])
    page.screenshot(path=str(shots / "01-consent-ar.png"))
    # Right to left: the first button of a row starts at the right, the text starts at the right.
    main, agree = (page.locator(sel).bounding_box() for sel in ("#view-consent", "#consent-agree"))
    assert agree is not None and main is not None
    assert agree["x"] + agree["width"] > main["x"] + main["width"] * 0.6, (agree, main)
    assert page.evaluate("() => getComputedStyle(document.querySelector('#consent-text p')).direction") == "rtl"
    page.get_by_role("button", name="أوافق على المشاركة").click()
    expect(page.locator("#instructions-heading")).to_have_text("التعليمات")
    page.reload()
    expect(page.locator("#instructions-heading")).to_have_text("التعليمات")  # kept over a reload
    page.screenshot(path=str(shots / "02-instructions-ar.png"), full_page=True)
    page.get_by_role("button", name="المتابعة إلى التدريب").click()
    wait_for(page, "t.state.trial && t.state.trial.stage === 'decision'", timeout=30_000)
    expect(page.locator("#robot-heading")).to_have_text("الروبوت")
    page.screenshot(path=str(shots / "03-trial-ar.png"))
    # The trial grid mirrors: the side column (facts, robot, Intervene) is left of the view.
    side, view = (page.locator(sel).bounding_box() for sel in (".side", ".viewer-col"))
    assert side is not None and view is not None and side["x"] < view["x"], (side, view)
