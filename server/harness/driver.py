"""Drive the participant page like a person would: read the screen (and ``window.__trustlab``), press keys.

Teleoperation is steered with real held keys. Which keys to hold is decided by
``experiment.participants.teleoperator.Operator`` (the strategy of a person who has read the instructions), from
what the page's teleoperation client holds of the socket's messages only
(``window.__trustlab.teleopClient``: the hello's ``setup``, the latest ``world`` and ``guidance``); it sees
them exactly and at once (no reaction time: the benchmark's ``HumanModel`` adds that). Keys are held
and released with ``page.keyboard`` (Shift for precise moves, G for the gripper).
"""

from __future__ import annotations

import csv
import io
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from experiment.participants.keys import KEY_CODES, Keys
from experiment.participants.teleoperator import Operator, View

if TYPE_CHECKING:
    from playwright.sync_api import Page

TELEOP_TIMEOUT_S = 90.0
POLL_S = 0.02
#: The arm counts as at rest (for the operator's "settled") when no motion key changed for this long.
SETTLED_S = 0.3

CLIENT = """() => { const c = window.__trustlab.teleopClient, s = window.__trustlab.state;
  return {ready: c.ready, wanted: c.wanted, over: c.over, hellos: c.hellos, seq: c.seq, ackSeq: c.ackSeq,
          world: c.world, guidance: c.guidance, lastAck: c.lastAck,
          stage: s && s.trial ? s.trial.stage : null}; }"""


def state(page: Page) -> dict[str, Any]:
    return page.evaluate("() => window.__trustlab && window.__trustlab.state")


def wait_for(page: Page, js: str, timeout: float = 20_000, arg: Any = None) -> Any:
    """Wait until ``js`` (a function of window.__trustlab and arg) is truthy."""
    return page.wait_for_function(f"(arg) => {{ const t = window.__trustlab; return t && ({js}); }}", arg=arg,
                                  timeout=timeout, polling=10).json_value()


def trial_key(s: dict[str, Any] | None) -> tuple | None:
    t = s and s.get("trial")
    return (t["practice"], t["block"], t["trial"]) if t else None


def wait_until_stopped(page: Page, timeout: float = 5_000) -> None:
    """Until the server has taken the page's latest input and says the arm is not moving."""
    wait_for(page, "!t.teleopClient.wanted || (t.teleopClient.ackSeq >= t.teleopClient.seq && "
                   "t.teleopClient.lastWorldMessage && !t.teleopClient.lastWorldMessage.moving && "
                   "t.teleopClient.lastWorldMessage.input_seq >= t.teleopClient.inputSeq)", timeout=timeout)


def press_keys(page: Page, held: set[str], shift: bool, keys: Keys) -> tuple[set[str], bool, int]:
    """Hold ``keys`` on ``page`` (keys already held stay down); returns the keys and Shift now held and the presses."""
    keyboard = page.keyboard
    wanted = {KEY_CODES[action] for action in keys.held}
    for code in sorted(held - wanted):
        keyboard.up(code)
    if keys.fine != shift:
        (keyboard.down if keys.fine else keyboard.up)("Shift")
    for code in sorted(wanted - held):
        keyboard.down(code)
    presses = len(wanted - held)
    if keys.gripper is not None:
        keyboard.press("KeyG")
        presses += 1
    return wanted, keys.fine, presses


class Teleoperator:
    """Holds and releases keys on ``page`` until the page's teleoperation of the current trial ends."""

    def __init__(self, page: Page):
        self.page = page
        self.held: set[str] = set()
        self.shift = False
        self.changed = time.monotonic()
        self.trace: deque[tuple] = deque(maxlen=60)  # for the message when it gets stuck

    def _client(self) -> dict[str, Any]:
        return self.page.evaluate(CLIENT)

    def _set_keys(self, keys: Keys) -> None:
        if {KEY_CODES[action] for action in keys.held} != self.held or keys.fine != self.shift:
            self.changed = time.monotonic()
        self.held, self.shift, _ = press_keys(self.page, self.held, self.shift, keys)

    def release(self) -> None:
        self._set_keys(Keys())

    def run(self) -> int:
        """Drive until the trial is no longer teleoperated; returns the number of messages the page sent."""
        wait_for(self.page, "t.teleopClient.ready || t.teleopClient.over || !t.teleopClient.wanted")
        first_seq = self.page.evaluate("() => window.__trustlab.teleopClient.seq")
        deadline = time.monotonic() + TELEOP_TIMEOUT_S
        operator, hellos = None, None
        start = time.monotonic()
        try:
            while True:
                client = self._client()
                over = client["over"]
                if (over is not None and not over.get("retry")) or client["wanted"] is None \
                        or client["stage"] not in (None, "teleop"):
                    return client["seq"] - first_seq
                if time.monotonic() > deadline:
                    raise AssertionError(f"teleoperation did not finish in {TELEOP_TIMEOUT_S} s; last steps:\n"
                                         + "\n".join(map(str, self.trace)))
                if not client["ready"] or client["world"] is None:
                    self.release()
                    time.sleep(POLL_S)
                    continue
                if operator is None or client["hellos"] != hellos:  # a new (guided) try starts afresh
                    setup = self.page.evaluate("() => window.__trustlab.teleopClient.setup")
                    operator, hellos = Operator(setup), client["hellos"]
                world, guidance = client["world"], client["guidance"]
                operator.see(world["tcp"], world)
                view = View.exact(world, guidance)
                view.settled = not self.held and time.monotonic() - self.changed > SETTLED_S
                keys = operator.decide(view, time.monotonic() - start)
                row = (operator.phase, sorted(keys.held), keys.fine, keys.gripper, guidance["step"],
                       guidance["blocked"], world["item"]["mode"])
                if not self.trace or self.trace[-1][1:-1] != row:  # changes only
                    self.trace.append((round(time.monotonic() - start, 2), *row, world["tcp"]))
                self._set_keys(keys)
                time.sleep(POLL_S)
        finally:
            self.release()


def export_rows(server, slug: str, name: str) -> list[dict[str, str]]:
    response = server.admin("GET", f"/api/admin/studies/{slug}/export/{name}")
    assert response.status_code == 200, response.text
    return list(csv.DictReader(io.StringIO(response.text)))
