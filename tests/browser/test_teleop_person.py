"""A person can teleoperate on an ordinary laptop: the real page, the 3D view on, the CPU throttled 4×.

The participant is ``experiment.participants.person.HumanModel`` (a modest reaction time, perceptual noise): it sees
only what the page exposes of the socket (``window.__trustlab.teleopClient``: the hello's setup, the latest world
and guidance) and acts only with key presses (``page.keyboard.down`` / ``up``; Shift for precise moves, G for
the gripper). It completes the guided tutorial (the practice teleoperation) and one scored teleoperation in
high complexity within the default time limit.
"""

from __future__ import annotations

import json
import re
import time
from typing import Any

from playwright.sync_api import Page, expect

from experiment.config import AlwaysAskSpec, BlockConfig, PracticeConfig, PracticeTrial, StudyConfig, TimingConfig
from experiment.participants.keys import Keys
from experiment.participants.person import HumanModel, HumanParams
from experiment.schedule import CountsSchedule
from experiment.task import Complexity, RobotAction
from server.harness.driver import export_rows, press_keys, state, wait_for

CPU_THROTTLE = 4
TIME_LIMIT_S = TimingConfig().teleop_time_limit_s  # the default (90 s)
#: A person who has practised a little: quicker than the benchmark's participants, still a few hundred ms late.
PERSON = HumanParams(reaction_s=0.22, reaction_sigma=0.2, hesitation_p=0.05)
POLL_S = 0.03

CLIENT = """() => {
  const c = window.__trustlab.teleopClient, s = window.__trustlab.state;
  return {ready: c.ready, wanted: c.wanted, over: c.over, setup: c.setup, world: c.world, guidance: c.guidance,
          stage: s && s.trial ? s.trial.stage : null};
}"""

VIEW = """() => ({viewer: window.__trustlab.viewer, fps: window.__trustlab.viewerFps,
                 frame_ms: window.__trustlab.viewerFrameMs, helper2d: window.__trustlab.teleopPanel.helperReason})"""


def study() -> StudyConfig:
    """The tutorial (one guided practice teleoperation, low complexity), then one scored one in high complexity."""
    return StudyConfig(
        title="teleoperation by a person",
        blocks=[BlockConfig(name="main", label="Part 1", policy=AlwaysAskSpec(),
                            schedule=CountsSchedule(n_low=0, n_high=1))],
        counterbalance="none", shelf_questionnaire=None,
        practice=PracticeConfig(trials=[PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.ASK)]),
        timing=TimingConfig(decision_window_s=2.0, teleop_time_limit_s=TIME_LIMIT_S))


class Person:
    """Holds keys on ``page`` as ``HumanModel`` decides, from what the page shows."""

    def __init__(self, page: Page, seed: int):
        self.page, self.seed = page, seed
        self.held: set[str] = set()
        self.shift = False
        self.presses = 0
        # (t, phase, keys, fine, tcp, step, blocked) at each change, for a failure's message
        self.trace: list[tuple] = []
        self.polls = 0

    def set_keys(self, keys: Keys) -> None:
        self.held, self.shift, presses = press_keys(self.page, self.held, self.shift, keys)
        self.presses += presses

    def teleoperate(self, timeout_s: float) -> dict[str, Any]:
        """Until the page says the teleoperation is over (a guided try that ran out starts again)."""
        deadline = time.monotonic() + timeout_s
        wait_for(self.page, "t.teleopClient.ready", timeout=20_000)
        human: HumanModel | None = None
        setup_seen, began = None, False
        start = time.monotonic()
        self.trace, self.polls, self.last_row, self.last_client = [], 0, None, None
        try:
            while time.monotonic() < deadline:
                client = self.page.evaluate(CLIENT)
                over = client["over"]
                began = began or client["ready"]  # (an ``over`` before that is the previous trial's)
                if began and over is not None and not over.get("retry"):
                    return {"over": over, "seconds": time.monotonic() - start, "polls": self.polls}
                if began and client["stage"] != "teleop":
                    # The page moved on without an ``over`` in hand (the socket dropped as the trial ended: the
                    # reconnected socket's hello says there is nothing to teleoperate): what a person sees is the
                    # next page; the export says how the trial ended.
                    return {"over": None, "seconds": time.monotonic() - start, "polls": self.polls}
                if not client["ready"] or client["world"] is None:
                    self.set_keys(Keys())
                    time.sleep(POLL_S)
                    continue
                if human is None or client["setup"] != setup_seen:  # a new (guided) try starts from the ready pose
                    human, setup_seen = HumanModel(client["setup"], self.seed, PERSON), client["setup"]
                now = time.monotonic() - start
                human.see(now, {"world": client["world"], "guidance": client["guidance"]})
                keys = human.keys(now)
                self.polls += 1
                row = (human.phase, sorted(keys.held), keys.fine, client["guidance"]["step"],
                       client["guidance"]["blocked"])
                if row != self.last_row:
                    self.last_row = row
                    self.trace.append((round(now, 2), *row[:3], [round(v, 3) for v in client["world"]["tcp"]],
                                       *row[3:]))
                self.last_client = client
                self.set_keys(keys)
                time.sleep(POLL_S)
            raise AssertionError(f"the teleoperation did not end in {timeout_s:.0f} s; {self.polls} polls; last "
                                 "steps:\n"
                                 + "\n".join(map(str, self.trace[-40:])))
        except BaseException:
            print("\n".join(map(str, self.trace)))  # the whole teleoperation, for the failure's log
            print("last seen:", json.dumps(self.last_client))
            raise
        finally:
            self.set_keys(Keys())


def test_a_person_teleoperates_with_the_3d_view_on_a_slow_machine(live_server, browser):
    live_server.create_study("person", study())
    page = browser.new_page()
    cdp = page.context.new_cdp_session(page)
    cdp.send("Emulation.setCPUThrottlingRate", {"rate": CPU_THROTTLE})
    started = time.monotonic()
    page.goto(f"{live_server.url}/join/person?PROLIFIC_PID=p-person-1")
    page.wait_for_url(re.compile(r"/p/[A-Za-z0-9_\-]+$"))
    page.get_by_role("button", name="I agree to take part").click()
    expect(page.get_by_role("button", name=re.compile("^Continue"))).to_be_visible()
    page.get_by_role("button", name=re.compile("^Continue")).click()

    person, results = Person(page, seed=13), []
    for expected in ("tutorial", "scored"):
        wait_for(page, "t.state.trial && t.state.trial.stage === 'teleop'", timeout=30_000)
        trial = state(page)["trial"]
        assert trial["practice"] == (expected == "tutorial")
        if expected == "tutorial":
            expect(page.locator("#tutorial-banner")).to_be_visible()
        result = person.teleoperate(TIME_LIMIT_S + 30)
        assert result["over"] is None or result["over"]["reason"] == "deposited", result  # (None: see the export)
        assert result["seconds"] < TIME_LIMIT_S, result
        results.append((expected, trial["complexity"], result["seconds"]))
        wait_for(page, "!t.state.trial || t.state.trial.stage !== 'teleop'", timeout=30_000)
        if expected == "tutorial":  # the page that ends the practice, then the scored part
            wait_for(page, "t.state.phase === 'practice_done'", timeout=30_000)
            page.get_by_role("button", name="Continue").click()
    view = page.evaluate(VIEW)
    assert view["viewer"] == "loaded"  # the 3D view was on (the page may pause it and show the 2-D view)
    wait_for(page, "t.state.phase === 'debrief'", timeout=30_000)
    print(f"teleoperations {results}; {person.presses} key presses; 3D view {view}; "
          f"{time.monotonic() - started:.0f} s in all")

    trials = export_rows(live_server, "person", "trials.csv")
    assert [(r["practice"], r["teleop_success"]) for r in trials] == [("1", "1"), ("0", "1")], trials
