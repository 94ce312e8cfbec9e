"""Screenshots of every participant page at 1280x720 and 1920x1080, to look at (nothing is asserted).

Runs the app in this process on a fresh SQLite database (/tmp), creates the demo study (with a payment in a second
study) and walks one participant per page kind through it in Debian's Chromium (headless), moving the session
straight to the page to shoot where playing up to it would take minutes. Writes ``NN_page_WIDTHxHEIGHT.png``
into ``--out`` and prints each file with the console messages the page logged (there should be none).

    .venv/bin/python benchmarks/shots_participant.py [--out /tmp/shots_participant] [--viewer]

Without ``--viewer`` the 3D view is left out (the page then says so in its place), which keeps SwiftShader off a
busy machine; with it the trial page shows the 3D view as participants see it.
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from pathlib import Path
from typing import Any

from playwright.sync_api import Page, sync_playwright
from sqlalchemy import select

from experiment.config import CompensationConfig, CompletionConfig, TimingConfig
from experiment.flow import QuestionnaireStep, ShelfSurveyStep, Step
from experiment.instruments import SCHAEFER_14
from experiment.templates import demo
from server.db.migrate import upgrade
from server.harness.browser import CHROMIUM, CHROMIUM_ARGS
from server.harness.driver import wait_for
from server.harness.live import live_server
from server.models import Participant

SIZES = ((1280, 720), (1920, 1080))
TIMING = TimingConfig(decision_window_s=30.0, animation_speed=1.0, teleop_time_limit_s=60.0)


class Shooter:
    def __init__(self, live: Any, browser: Any, out: Path, viewer: bool, throttle: float = 1.0):
        self.live, self.browser, self.out, self.viewer, self.throttle = live, browser, out, viewer, throttle
        self.count = 0

    def page(self, size: tuple[int, int]) -> Page:
        page = self.browser.new_page(viewport={"width": size[0], "height": size[1]})
        page.on("dialog", lambda dialog: dialog.accept())
        messages: list[str] = []
        page.on("console", lambda m: messages.append(f"{m.type}: {m.text}"))
        page.on("pageerror", lambda e: messages.append(f"pageerror: {e}"))
        page.messages = messages
        if not self.viewer:
            page.route(re.compile(r"/viewer/"), lambda route: route.abort())
        if self.throttle > 1:  # a cheap laptop: every page of the run at this CPU slow-down
            page.context.new_cdp_session(page).send("Emulation.setCPUThrottlingRate", {"rate": self.throttle})
        return page

    def shoot(self, page: Page, name: str, *, full_page: bool = False) -> None:
        self.count += 1
        size = page.viewport_size
        assert size is not None, "every page is opened with a viewport"
        path = self.out / f"{self.count:02d}_{name}_{size['width']}x{size['height']}.png"
        time.sleep(0.3)  # fonts and layout settle
        page.screenshot(path=str(path), full_page=full_page)
        print(path, "console:", page.messages or "empty")  # type: ignore[attr-defined]  # set by page()

    def join(self, page: Page, slug: str, pid: str) -> None:
        page.goto(f"{self.live.url}/join/{slug}?PROLIFIC_PID={pid}")
        page.wait_for_url(re.compile(r"/p/"))
        wait_for(page, "t.state !== null")

    def move(self, pid: str, step: Step, order=("trust_agnostic", "trust_aware")) -> None:
        with self.live.app.state.services.sessionmaker.begin() as session:
            participant = session.scalar(select(Participant).where(Participant.external_id == pid))
            participant.step, participant.block_order = step, list(order)


def run(shooter: Shooter, size: tuple[int, int]) -> None:
    tag = f"{size[0]}"
    page = shooter.page(size)
    # The join page while the join request is held back.
    held: list = []
    page.route(re.compile(r"/api/studies/demo/join"), lambda route: held.append(route))
    page.goto(f"{shooter.live.url}/join/demo?PROLIFIC_PID=shots-{tag}", wait_until="domcontentloaded")
    page.get_by_role("heading", name="Joining the study…").wait_for()
    while not held:
        page.wait_for_timeout(50)
    shooter.shoot(page, "join")
    held[0].continue_()
    page.wait_for_url(re.compile(r"/p/"))
    page.get_by_role("heading", name="Consent to take part").wait_for()
    shooter.shoot(page, "consent")
    page.get_by_role("button", name="I do not agree").click()
    shooter.shoot(page, "consent_decline_confirm")
    page.get_by_role("button", name="No, go back").click()
    page.get_by_role("button", name="I agree to take part").click()
    page.get_by_role("heading", name="Instructions").wait_for()
    shooter.shoot(page, "instructions")
    shooter.shoot(page, "instructions_full", full_page=True)
    page.go_back()
    page.locator("#notice").wait_for()
    shooter.shoot(page, "back_notice")
    page.get_by_role("button", name="OK").click()
    page.get_by_role("button", name=re.compile("^Continue")).click()
    wait_for(page, "t.state.trial && t.state.trial.stage === 'decision'", timeout=60_000)
    shooter.shoot(page, "practice_decision")

    shooter.move(f"shots-{tag}", ShelfSurveyStep(block=1, shelf=1, trial=3))
    page.reload()
    wait_for(page, "t.state && t.state.phase === 'shelf_survey'")
    shooter.shoot(page, "shelf_survey")
    shooter.move(f"shots-{tag}", QuestionnaireStep(context="after:1", block=1, questionnaire=SCHAEFER_14.id))
    page.reload()
    wait_for(page, "t.state && t.state.phase === 'questionnaire'")
    page.locator('fieldset[data-item="reliable"] input[value="70"]').check()
    page.locator('fieldset[data-item="predictable"] input[value="40"]').check()
    page.get_by_role("button", name="Continue").click()  # 12 missing
    shooter.shoot(page, "questionnaire_missing")
    # A second tab answers the page; this one then sends its answers.
    other = shooter.page(size)
    other.goto(page.url)
    wait_for(other, "t.state && t.state.phase === 'questionnaire'")
    for item in SCHAEFER_14.items:
        other.locator(f'fieldset[data-item="{item.id}"] input[value="50"]').check()
    other.get_by_role("button", name="Continue").click()
    wait_for(other, "t.state && t.state.phase !== 'questionnaire'")
    other.close()
    for item in SCHAEFER_14.items:
        page.locator(f'fieldset[data-item="{item.id}"] input[value="60"]').check()
    page.get_by_role("button", name="Continue").click()
    page.locator("#notice").wait_for()
    wait_for(page, "t.state && t.state.phase !== 'questionnaire'")
    shooter.shoot(page, "stale_notice")
    page.close()

    for slug, name in (("demo", "debrief"), ("paid", "debrief_paid")):
        page = shooter.page(size)
        pid = f"{name}-{tag}"
        shooter.join(page, slug, pid)
        page.get_by_role("button", name="I agree to take part").click()
        page.get_by_role("heading", name="Instructions").wait_for()
        shooter.move(pid, QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id))
        page.reload()
        wait_for(page, "t.state && t.state.phase === 'questionnaire'")
        for item in SCHAEFER_14.items:
            page.locator(f'fieldset[data-item="{item.id}"] input[value="80"]').check()
        page.get_by_role("button", name="Continue").click()
        page.get_by_role("heading", name="Thank you!").wait_for()
        if slug == "paid":  # it has a redirect: stay for the picture
            page.get_by_role("button", name="Stay on this page").click()
        shooter.shoot(page, name)
        page.close()

    page = shooter.page(size)
    shooter.join(page, "demo", f"decliner-{tag}")
    page.get_by_role("button", name="I do not agree").click()
    page.get_by_role("button", name="Yes, I do not want to take part").click()
    page.get_by_role("heading", name="You chose not to take part").wait_for()
    shooter.shoot(page, "declined")
    page.goto(f"{shooter.live.url}/p/{'x' * 32}")
    page.get_by_role("heading", name="This link is not valid").wait_for()
    shooter.shoot(page, "invalid_link")
    page.goto(f"{shooter.live.url}/join/shut?PROLIFIC_PID=a")
    page.get_by_role("heading", name="This study is closed").wait_for()
    shooter.shoot(page, "join_closed")
    page.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/shots_participant"))
    parser.add_argument("--viewer", action="store_true", help="show the 3D view (SwiftShader: slow)")
    parser.add_argument("--throttle", type=float, default=1.0, help="CPU slow-down (DevTools), e.g. 4")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/shots.db"
        upgrade(url)
        with live_server(url) as live, sync_playwright() as p:
            config = demo().model_copy(update={"timing": TIMING})
            for slug, study in (("demo", config), ("shut", config), ("paid", config.model_copy(update={
                    "compensation": CompensationConfig(base=6.0, bonus_per_point=0.05, bonus_cap=2.0, currency="GBP"),
                    "completion": CompletionConfig(redirect_url="https://example.org/done?cc={code}")}))):
                response = live.admin("POST", "/api/admin/studies", json={"status": "open", "slug": slug,
                                                                           "config": study.model_dump(mode="json")})
                assert response.status_code == 201, response.text
            assert live.admin("POST", "/api/admin/studies/shut/close").status_code == 200
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
            shooter = Shooter(live, browser, args.out, args.viewer, args.throttle)
            try:
                for size in SIZES:
                    run(shooter, size)
            finally:
                browser.close()


if __name__ == "__main__":
    main()
