"""Drive the participant page like a person would: read the screen (and ``window.__trustlab``), press keys.

Teleoperation is steered with real held keys. Which keys to hold is computed from the world
state in the page's latest ack (``window.__trustlab.teleopClient.world``) with the scripted
teleoperator of ``experiment.world`` as the route planner; far from a waypoint the keys are
held at normal speed, near it with Shift (precise), and last it taps one command at a time.
"""

from __future__ import annotations

import csv
import io
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from playwright.sync_api import Page

from experiment.world import build_scene, can_grasp, scripted
from experiment.world import constants as K
from experiment.world.robot import arm_points
from experiment.world.scene import Scene
from experiment.world.state import ItemMode, ItemState, WorldState, over_bin_opening

EE_KEYS = (("KeyW", "KeyS"), ("KeyA", "KeyD"), ("KeyR", "KeyF"))  # (+, -) for x, y, z
J1_KEYS = ("KeyQ", "KeyE")
TELEOP_TIMEOUT_S = 45.0
#: Waypoint errors (m): held at normal speed beyond FAR (a key is released a command or two late, so
#: it overshoots by up to ~10 cm), with Shift down to NEAR, then single taps until within DEADBAND.
FAR, NEAR, DEADBAND = 0.08, 0.025, 0.008


def state(page: Page) -> dict[str, Any]:
    return page.evaluate("() => window.__trustlab && window.__trustlab.state")


def wait_for(page: Page, js: str, timeout: float = 20_000, arg: Any = None) -> Any:
    """Wait until ``js`` (a function of window.__trustlab and arg) is truthy."""
    return page.wait_for_function(f"(arg) => {{ const t = window.__trustlab; return t && ({js}); }}", arg=arg,
                                  timeout=timeout, polling=10).json_value()


def trial_key(s: dict[str, Any] | None) -> tuple | None:
    t = s and s.get("trial")
    return (t["practice"], t["block"], t["trial"]) if t else None


def world_state(data: dict[str, Any]) -> WorldState:
    item = data["item"]
    return WorldState(data["t"], tuple(data["base"]), tuple(data["joints"]), data["gripper"], data["gripper_target"],
                      ItemState(ItemMode(item["mode"]), tuple(item["position"]), tuple(item["wxyz"])))


@dataclass
class Plan:
    """What to do next: toggle the gripper, or hold/tap these keys (with Shift when fine)."""

    gripper: bool = False
    keys: set[str] = field(default_factory=set)
    fine: bool = False
    tap: bool = False


def _goal_of(world: WorldState, scene: Scene) -> tuple[Any, np.ndarray | None]:
    """The scripted teleoperator's command and the waypoint it steers to (None for a turn)."""
    seen: dict[str, Any] = {}
    original = scripted._toward

    def spy(tcp, goal, gripper=None):
        seen["goal"] = np.asarray(goal, dtype=float)
        return original(tcp, goal, gripper)

    scripted._toward = spy
    try:
        command = scripted.scripted_teleop_commands(world, scene)
    finally:
        scripted._toward = original
    return command, seen.get("goal")


def plan(world: WorldState, scene: Scene) -> Plan:
    closed = world.gripper_target < K.GRIPPER_MAX - 1e-6
    mode = world.item.mode
    if mode == ItemMode.ON_SHELF and not closed and can_grasp(world, scene):
        return Plan(gripper=True)
    if mode == ItemMode.GRASPED and over_bin_opening(world.base, world.item.position):
        return Plan(gripper=True)
    command, goal = _goal_of(world, scene)
    if command.gripper == "open" and closed:
        return Plan(gripper=True)
    if command.joint_velocity is not None:
        rate = command.joint_velocity[0]
        error = rate / scripted.YAW_GAIN if abs(rate) < K.MAX_JOINT_SPEED - 1e-9 else math.copysign(1.0, rate)
        key = J1_KEYS[0] if error > 0 else J1_KEYS[1]
        if abs(error) > 0.4:
            return Plan(keys={key})
        return Plan(keys={key}, fine=True, tap=abs(error) <= 0.1)
    if goal is None:
        return Plan()  # waiting (item falling or back on its shelf)
    error = goal - np.array(arm_points(world.base, world.joints).tcp)
    biggest = float(np.max(np.abs(error)))
    if biggest <= FAR:
        return Plan(keys=_axis_keys(error, DEADBAND), fine=True, tap=biggest <= NEAR)
    small = _axis_keys(np.where(np.abs(error) > FAR, 0.0, error), 1.25 * DEADBAND)
    if small:  # first trim the other axes (one key speed for all), or they drift out of tolerance
        return Plan(keys=small, fine=True, tap=True)
    return Plan(keys=_axis_keys(error, FAR))


def _axis_keys(error: np.ndarray, deadband: float) -> set[str]:
    return {EE_KEYS[i][0 if e > 0 else 1] for i, e in enumerate(error.tolist()) if abs(e) > deadband}


class Teleoperator:
    """Holds and releases keys on ``page`` until the page's teleoperation of the current trial ends."""

    def __init__(self, page: Page):
        self.page = page
        self.held: set[str] = set()
        self.shift = False
        self.trace: deque[tuple] = deque(maxlen=10)  # for the message when it gets stuck

    def _client(self) -> dict[str, Any]:
        return self.page.evaluate("""() => { const c = window.__trustlab.teleopClient, s = window.__trustlab.state;
            return {lastAck: c.lastAck, wanted: c.wanted, open: c.open, seq: c.seq, ackSeq: c.ackSeq, world: c.world, scene: c.scene,
                    stage: s && s.trial ? s.trial.stage : null}; }""")

    def _set_keys(self, keys: set[str], fine: bool) -> None:
        keyboard = self.page.keyboard
        for key in self.held - keys:
            keyboard.up(key)
        if fine != self.shift:
            (keyboard.down if fine else keyboard.up)("Shift")
            self.shift = fine
        for key in sorted(keys - self.held):
            keyboard.down(key)
        self.held = set(keys)

    def release(self) -> None:
        self._set_keys(set(), False)

    def run(self) -> int:
        """Drive until the trial is no longer teleoperated; returns the number of commands the page sent."""
        wait_for(self.page, "t.teleopClient.open && t.teleopClient.world && t.teleopClient.scene")
        first = self._client()
        scene = build_scene(first["scene"]["complexity"], int(first["scene"]["seed"]), first["scene"]["target_slot"])
        deadline = time.monotonic() + TELEOP_TIMEOUT_S
        try:
            while True:
                client = self._client()
                if client["wanted"] is None or client["stage"] not in (None, "teleop"):
                    return client["seq"]
                if time.monotonic() > deadline:
                    raise AssertionError(f"teleoperation did not finish in {TELEOP_TIMEOUT_S} s; last steps: "
                                         + "\n".join(map(str, self.trace)))
                if client["world"] is None or not client["open"]:
                    time.sleep(0.02)
                    continue
                todo = plan(world_state(client["world"]), scene)
                self.trace.append((todo, client["world"]["joints"], client["world"]["item"]["mode"], client["lastAck"]))
                self._step(todo, client)
        finally:
            self.release()

    def _step(self, todo: Plan, client: dict[str, Any]) -> None:
        if todo.gripper and (self.held or client["ackSeq"] < client["seq"]):
            self.release()  # let the arm come to rest, then look again
            wait_for(self.page, "!t.teleopClient.wanted || t.teleopClient.ackSeq >= t.teleopClient.seq", timeout=5000)
        elif todo.gripper:
            target = client["world"]["gripper_target"]
            self.page.keyboard.press("KeyG")
            wait_for(self.page, "!t.teleopClient.wanted || (t.teleopClient.world && "
                                "t.teleopClient.world.gripper_target !== arg)", arg=target, timeout=5000)
        elif todo.tap:
            self._set_keys(todo.keys, True)
            wait_for(self.page, "!t.teleopClient.wanted || t.teleopClient.seq > arg", arg=client["seq"], timeout=5000)
            self.release()
            wait_for(self.page, "!t.teleopClient.wanted || t.teleopClient.ackSeq >= t.teleopClient.seq", timeout=5000)
        elif todo.keys:
            self._set_keys(todo.keys, todo.fine)
            time.sleep(0.005)
        else:
            self.release()
            time.sleep(0.03)


def export_rows(server, slug: str, name: str) -> list[dict[str, str]]:
    response = server.admin("GET", f"/api/admin/studies/{slug}/export/{name}")
    assert response.status_code == 200, response.text
    return list(csv.DictReader(io.StringIO(response.text)))
