"""The human-like operator (experiment.participants) steers the robot world from the protocol's dicts alone.

A small in-process simulation stands in for the server: the world advances on its own clock (30 ticks a
second, ``hold_command`` under the held input, the dead-man stop), world messages are pushed at most
``WORLD_HZ`` a second, the hello and world dicts are built from ``WorldState`` + ``guidance`` as the
server builds them (and validated against ``server.teleop_messages``). The client's loop runs at a fixed
rate (``ClientLoop``); time is simulated, so a run takes well under a second of CPU.
"""

from __future__ import annotations

import ast
import heapq
import json
import math
import random
import statistics
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from experiment.participants.keys import Keys, gripper_action, input_fields, input_message
from experiment.participants.page import PAGE_FRAME_S, ClientLoop
from experiment.participants.person import HumanModel, HumanParams
from experiment.participants.teleoperator import BACK_OUT_AFTER_S, BACK_OUT_M, Operator, View
from experiment.world import build_scene, teleop_start_state
from experiment.world import constants as K
from experiment.world.guidance import guidance
from experiment.world.robot import arm_points
from experiment.world.scene import Scene
from experiment.world.state import ItemMode, WorldState
from experiment.world.teleop import DEFAULT_RULES, TeleopCommand, TeleopRules, hold_command
from server.i18n import Translator
from server.services.teleop_views import scene_info, world_view
from server.services.wording import guidance_text
from server.settings import Settings
from server.teleop_messages import CLIENT_MESSAGE, SERVER_MESSAGE, TeleopSetup
from server.world.teleop import DEADMAN_S, KEEPALIVE_S

SERVER_HZ = 30.0  # the world loop
WORLD_HZ = Settings.model_fields["teleop_world_hz"].default
TIME_LIMIT_S = 90.0
NETWORK_S = 0.01  # one way


# -- the server's dicts (as the socket builds them) ------------------------------------------------------------
def world_dict(state: WorldState) -> dict[str, Any]:
    return world_view(state).model_dump(mode="json")


def guidance_dict(state: WorldState, scene: Scene, rules: TeleopRules, blocked: bool) -> dict[str, Any]:
    g = guidance(state, scene, rules)
    return {"step": g.step.value, "text": guidance_text(g.message, Translator("en")), "can_grasp": g.can_grasp,
            "over_bin": g.over_bin,
            "blocked": blocked, "grasp_distance": round(g.grasp_distance, 6), "to_grasp": list(g.to_grasp),
            "to_bin": list(g.to_bin)}


def scene_dict(scene: Scene, rules: TeleopRules = DEFAULT_RULES) -> dict[str, Any]:
    return scene_info(scene, rules).model_dump(mode="json")


# -- the simulated server and client ---------------------------------------------------------------------------
@dataclass
class Run:
    deposited: bool
    seconds: float  # simulated time until the deposit (or the limit)
    inputs: int
    keepalives: int
    events: list[str] = field(default_factory=list)
    trace: list[tuple] = field(default_factory=list)


class Simulation:
    """One teleoperation: a server (world on its own clock) and a client at ``rate_hz`` with a person."""

    def __init__(self, scene: Scene, seed: int, rate_hz: float, *, params: HumanParams | None = None,
                 rules: TeleopRules = DEFAULT_RULES, time_limit_s: float = TIME_LIMIT_S, validate: bool = False,
                 timer: bool = False, stalls: tuple[tuple[float, float], ...] = (), resume: bool = True):
        """``timer``: the page handles keys and draws every ``PAGE_FRAME_S``, only its keep-alive timer runs at
        ``rate_hz`` (else its one loop runs at ``rate_hz``); ``resume``: a keep-alive after the dead-man stop
        gives the held input back (as ``server.world`` does)."""
        self.scene, self.rules, self.rate_hz, self.time_limit_s = scene, rules, rate_hz, time_limit_s
        self.timer, self.seed, self.stalls = timer, seed, stalls  # stalls: (from, seconds) the client does nothing
        self.resume = resume
        self.stopped: TeleopCommand | None = None  # the input the dead-man stop took away
        self.validate = validate
        self.state = teleop_start_state(scene)
        self.held = TeleopCommand()
        self.blocked = False
        self.last_message = 0.0
        self.advanced = 0.0
        self.version = 0
        self.shown = -1
        self.last_push = -1e9
        self.events: list[str] = []
        self.input_seq: int | None = None
        setup = {"scene": scene_dict(scene, rules),
                 "limits": {"max_ee_speed": K.MAX_EE_SPEED, "max_joint_speed": K.MAX_JOINT_SPEED,
                            "grasp_radius": rules.grasp_radius, "align_radius": rules.align_radius, "speedup": 1.0,
                            "deadman_s": DEADMAN_S, "keepalive_s": KEEPALIVE_S, "world_hz": WORLD_HZ,
                            "rate_limit_hz": 60.0, "max_view_wait_s": 30.0, "view_wait_left_s": 30.0},
                 "time_limit_s": time_limit_s, "time_left_ms": time_limit_s * 1000, "tutorial": None,
                 "world": world_dict(self.state), "guidance": self._guidance()}
        if validate:
            TeleopSetup.model_validate(setup)
        self.setup = setup
        self.human = HumanModel(setup, seed, params)
        self.client = ClientLoop(self.human, KEEPALIVE_S)

    def _guidance(self) -> dict[str, Any]:
        return guidance_dict(self.state, self.scene, self.rules, self.blocked)

    # server side
    def _advance(self, now: float) -> None:
        start = self.advanced
        if now <= start:
            return
        moving = self.held.ee_velocity is not None or self.held.joint_velocity is not None
        if moving and now >= self.last_message + DEADMAN_S:
            stop = max(start, self.last_message + DEADMAN_S)
            self._hold(self.held, stop - start)
            start, self.held, self.stopped, moving = stop, TeleopCommand(), self.held, False
            self.version += 1
        state = self.state
        settling = abs(state.gripper - state.gripper_target) > 1e-9 or state.item.mode in (ItemMode.DROPPED,
                                                                                             ItemMode.IN_BIN)
        if (moving or settling) and now > start:
            self._hold(self.held, now - start)
        self.advanced = now

    def _hold(self, command: TeleopCommand, seconds: float) -> None:
        if seconds <= 0:
            return
        state, events = hold_command(self.state, self.scene, command, min(seconds, 0.25), self.rules)
        blocked = "blocked" in events
        if state != self.state or events or blocked != self.blocked:
            self.version += 1
        self.state, self.blocked = state, blocked
        self.events += [e for e in events if e != "blocked" or not self.events or self.events[-1] != "blocked"]

    def _receive(self, now: float, message: dict[str, Any]) -> None:
        if self.validate:
            CLIENT_MESSAGE.validate_json(json.dumps(message))  # as the socket reads it
        self._advance(now)
        self.last_message = now
        if message["type"] != "input":
            if self.stopped is not None and self.resume:  # a keep-alive after the dead-man stop resumes the input
                self.held, self.stopped = self.stopped, None
                self.version += 1
            return
        self.stopped = None
        self.input_seq = message["seq"]
        held = TeleopCommand(ee_velocity=tuple(message["ee_velocity"]) if "ee_velocity" in message else None,
                             joint_velocity=tuple(message["joint_velocity"]) if "joint_velocity" in message else None)
        if held != self.held:
            self.held = held
            self.version += 1
        if message.get("gripper"):
            self._hold(replace(held, gripper=message["gripper"]), 0.001)

    def _world_message(self, now: float) -> dict[str, Any]:
        self.shown, self.last_push = self.version, now
        message = {"type": "world", "input_seq": self.input_seq, "server_ms": round(now * 1000, 1),
                   "world": world_dict(self.state), "guidance": self._guidance(), "events": [],
                   "moving": self.held != TeleopCommand(), "time_left_ms": max(0.0, (self.time_limit_s - now) * 1000)}
        if self.validate:
            SERVER_MESSAGE.validate_python(message)
        return message

    def run(self, trace: bool = False) -> Run:
        """Until the deposit or the time limit (events on one simulated clock)."""
        queue: list[tuple[float, int, str, Any]] = []
        order = 0

        def at(t: float, kind: str, data: Any = None) -> None:
            nonlocal order
            order += 1
            heapq.heappush(queue, (t, order, kind, data))

        at(0.0, "server")
        phase = random.Random(self.seed).random() / self.rate_hz  # where in its period the client's loop starts
        at(NETWORK_S + phase, "timer" if self.timer else "client")
        if self.timer:
            at(NETWORK_S, "client")
        client_period = PAGE_FRAME_S if self.timer else 1 / self.rate_hz
        received: dict[str, Any] = {"world": self.setup["world"], "guidance": self.setup["guidance"]}
        out = Run(False, self.time_limit_s, 0, 0)
        while queue:
            now, _, kind, data = heapq.heappop(queue)
            if now >= self.time_limit_s:
                break
            if kind == "server":
                self._advance(now)
                if self.version != self.shown and now - self.last_push >= 1 / WORLD_HZ - 1e-9:
                    at(now + NETWORK_S, "world", self._world_message(now))
                if self.state.item.mode == ItemMode.IN_BIN:
                    out.deposited, out.seconds = True, now
                    break
                at(now + 1 / SERVER_HZ, "server")
            elif kind == "world":
                received = data
            elif kind == "to_server":
                self._receive(now, data)
            elif kind in ("timer", "client") and (stall := next((f + d for f, d in self.stalls if f <= now < f + d),
                                                                None)) is not None:
                at(stall, kind)  # the page's main thread is busy: nothing runs until it is free
            elif kind == "timer":
                for message in self.client.keepalive(now):
                    at(now + NETWORK_S, "to_server", message)
                at(now + 1 / self.rate_hz, "timer")
            elif kind == "client":
                for message in self.client.tick(now, received, keepalive=not self.timer):
                    at(now + NETWORK_S, "to_server", message)
                if trace:
                    out.trace.append((round(now, 2), self.human.phase, sorted(self.human.held.held),
                                      self.human.held.fine, self.state.item.mode.value,
                                      [round(v, 3) for v in arm_points(self.state.base, self.state.joints).tcp]))
                at(now + client_period, "client")
        out.inputs, out.keepalives, out.events = self.client.inputs, self.client.keepalives, self.events
        return out


def simulate(complexity: str, seed: int, rate_hz: float = 30.0, **kwargs: Any) -> Run:
    return Simulation(build_scene(complexity, seed), seed, rate_hz, **kwargs).run()


# -- tests -------------------------------------------------------------------------------------------------------
def test_the_operator_modules_do_not_import_the_robot():
    """They see only the protocol: no kinematics, scene builder, scripted controller or other robot code."""
    folder = Path(__file__).resolve().parents[2] / "experiment" / "participants"
    modules = ("keys", "mast", "teleoperator", "person", "page")
    imported = set()
    for module in modules:
        for node in ast.walk(ast.parse((folder / f"{module}.py").read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom):
                imported.add("." * node.level + (node.module or ""))
    allowed = {"__future__", "math", "random", "collections.abc", "dataclasses", "typing", "numpy"}
    assert imported <= allowed | {f"experiment.participants.{m}" for m in modules}, imported


def test_keys_become_the_pages_input():
    assert input_fields(set()) == {}
    assert input_fields({"x+"}) == {"ee_velocity": [0.2, 0.0, 0.0]}
    assert input_fields({"x+", "x-", "z-"}, fine=True) == {"ee_velocity": [0.0, 0.0, -0.025]}
    assert input_fields({"y+", "z+"}) == {"ee_velocity": [0.0, 0.2, 0.2]}
    # a joint key takes precedence over the axis keys (as the page's command())
    assert input_fields({"x+", "j1-"}) == {"joint_velocity": [-0.6, 0.0, 0.0, 0.0]}
    assert input_fields({"j1+"}, fine=True) == {"joint_velocity": [0.1, 0.0, 0.0, 0.0]}
    assert input_fields({"j1+", "j1-", "x-"}) == {"ee_velocity": [-0.2, 0.0, 0.0]}
    assert gripper_action({"gripper_target": 0.1}) == "close"
    assert gripper_action({"gripper_target": 0.07}) == "open"
    message = input_message(3, Keys(frozenset({"z+"}), gripper="close"), {"gripper_target": 0.1}, client_ms=5.0)
    assert message == {"type": "input", "seq": 3, "client_ms": 5.0, "ee_velocity": [0.0, 0.0, 0.2], "gripper": "close"}
    CLIENT_MESSAGE.validate_json(json.dumps(message))  # as the socket reads it


def test_the_mast_is_found_from_what_the_arm_shows():
    scene = build_scene("low", 2)
    sim = Simulation(scene, 2, 30.0)
    operator = Operator(sim.setup)
    state = teleop_start_state(scene)
    for command, seconds in (({"ee_velocity": (0.1, 0.0, -0.2)}, 1.5), ({"joint_velocity": (0.5, 0, 0, 0)}, 1.0)):
        for _ in range(int(seconds * 30)):
            state, _ = hold_command(state, scene, TeleopCommand(**command), 1 / 30)
            operator.see(arm_points(state.base, state.joints).tcp, world_dict(state))
    mast = arm_points(state.base, state.joints).mast
    assert math.dist(operator.mast.xy, mast[:2]) < 0.003


def test_an_ideal_operator_collects_the_item():
    """The strategy alone (no delay, no noise), applied every server tick."""
    for complexity, seed in (("low", 1), ("high", 5)):
        scene = build_scene(complexity, seed)
        sim = Simulation(scene, seed, 30.0)
        operator = Operator(sim.setup)
        state, t = teleop_start_state(scene), 0.0
        blocked = False
        while state.item.mode != ItemMode.IN_BIN and t < 60:
            world = world_dict(state)
            view = View.exact(world, guidance_dict(state, scene, DEFAULT_RULES, blocked))
            operator.see(view.tcp, world)
            keys = operator.decide(view, t)
            command = TeleopCommand(**{k: tuple(v) for k, v in keys.motion().items()},
                                    gripper=gripper_action(world) if keys.gripper else None)
            state, events = hold_command(state, scene, command, 1 / 30)
            blocked, t = "blocked" in events, t + 1 / 30
        assert state.item.mode == ItemMode.IN_BIN, (complexity, seed, operator.phase)
        assert t < 25


@pytest.mark.parametrize("complexity", ["low", "high"])
def test_a_person_completes_teleoperations_within_the_limit(complexity):
    runs = [simulate(complexity, seed, validate=seed == 0) for seed in range(6)]
    assert all(r.deposited for r in runs), [(r.seconds, r.events) for r in runs]
    assert statistics.median(r.seconds for r in runs) < 30
    assert all(r.seconds < TIME_LIMIT_S for r in runs)


def test_the_message_rate_does_not_change_how_long_it_takes():
    """The arm moves on the server's clock: a client looping 5 times a second is about as fast as one at 30; at 2
    a second the person sees a jerky picture and their keys act up to half a second late, yet finishes in time."""
    times = {}
    for rate in (2.0, 5.0, 30.0):
        runs = [simulate(c, seed, rate) for c in ("low", "high") for seed in range(4)]
        assert all(r.deposited for r in runs), rate
        times[rate] = statistics.median(r.seconds for r in runs)
    assert times[5.0] < 1.15 * times[30.0], times
    assert times[2.0] < 20.0, times


def test_a_page_sending_2_or_30_messages_a_second_moves_the_arm_alike():
    """Keys handled as they come, keep-alives on a timer at 2 or 30 a second: the same person takes as long."""
    times, messages = {}, {}
    for rate in (2.0, 30.0):
        runs = [simulate(c, seed, rate, timer=True) for c in ("low", "high") for seed in range(4)]
        assert all(r.deposited for r in runs), rate
        times[rate] = statistics.median(r.seconds for r in runs)
        messages[rate] = statistics.mean(r.inputs + r.keepalives for r in runs)
    assert abs(times[2.0] / times[30.0] - 1) < 0.1, times
    assert messages[30.0] > 5 * messages[2.0], messages


def test_a_person_believes_the_eyes_when_the_arm_does_not_move():
    """Keys that never reach the arm (a page that does not take them, a long stall): the picture does not
    change, so after a while the person stops believing in the motion they expected and keeps pressing."""
    scene = build_scene("low", 4)
    sim = Simulation(scene, 4, 30.0)
    human = HumanModel(sim.setup, 4)
    shown = {"world": sim.setup["world"], "guidance": sim.setup["guidance"]}
    pressed = set()
    for i in range(int(6 / 0.05)):
        human.see(i * 0.05, shown)
        pressed |= human.keys(i * 0.05).held
    keys = human.keys(6.0)
    assert "x+" in pressed and keys.held and human.phase == "move above the item", (keys, human.phase)
    # one look after a long stall of the driver: what was decided meanwhile never reached the page
    before = len(human.history)
    human.keys(9.0)
    assert len(human.history) <= before + 1


@pytest.mark.parametrize("resume", [True, False])
def test_a_page_that_stalls_past_the_dead_man_time_goes_on(resume):
    """The page's loop stops for 1.5 s while a key is held: the server stops the arm (dead-man). Its next keep-alive
    gives the held input back; a server that did not would still say the arm is not moving although it holds the
    page's input, and the page sends the input again."""
    sim = Simulation(build_scene("low", 2), 2, 30.0, stalls=((6.0, 1.5),), resume=resume)  # while it turns (Q)
    run = sim.run()
    assert run.deposited and run.seconds < 20, run.seconds
    if not resume:
        assert sim.client.resends >= 1


def test_a_refused_input_is_sent_again():
    """The server refused the latest input (too many messages): the page sends its input state again."""
    sim = Simulation(build_scene("low", 2), 2, 30.0)
    client, shown = sim.client, {"world": sim.setup["world"], "guidance": sim.setup["guidance"]}
    for i in range(40):
        client.tick(i / 30, shown)
    refused = client.input_seq
    client.ack({"type": "ack", "seq": refused, "ok": False, "error": "too many messages; slow down"})
    again = client.tick(40 / 30, shown)
    assert [m["type"] for m in again] == ["input"] and again[0]["seq"] > refused
    assert {k: v for k, v in again[0].items() if k.endswith("velocity")} == client.sent_motion


def test_the_person_is_deterministic_for_a_seed():
    a, b = simulate("high", 3, 10.0), simulate("high", 3, 10.0)
    assert (a.seconds, a.inputs, a.keepalives) == (b.seconds, b.inputs, b.keepalives)


def _keys_step(keys: Keys) -> np.ndarray:
    """The direction the held translation keys move the gripper in."""
    return np.array([0.2 if "x+" in keys.held else -0.2 if "x-" in keys.held else 0.0,
                     0.2 if "y+" in keys.held else -0.2 if "y-" in keys.held else 0.0,
                     0.2 if "z+" in keys.held else -0.2 if "z-" in keys.held else 0.0])


def test_a_person_held_down_while_rising_above_the_boxes_backs_out_then_rises_again():
    """Rising above the boxes with something over the gripper (a shelf board, a box's edge), the move is refused
    (``blocked``). A person backs out towards the robot, without the rise key (a move into the obstacle is refused
    whole), then rises again; holding the rise key against it ran a guided practice try into its time limit."""
    scene = build_scene("high", 5)
    operator = Operator(Simulation(scene, 5, 30.0).setup)
    reach, heading = operator.mast.radial(operator.grasp)
    towards_robot = -np.array([math.cos(heading), math.sin(heading), 0.0])
    under = operator.grasp + 0.08 * towards_robot
    under[2] = operator.clear - 0.05  # below the boxes' top, 8 cm in front of the item
    setup = Simulation(scene, 5, 30.0).setup

    def decide(tcp, blocked: bool, now: float) -> Keys:
        world = setup["world"] | {"tcp": list(tcp)}
        return operator.decide(View.exact(world, setup["guidance"] | {"blocked": blocked}), now)

    assert decide(under, False, 0.0).held == {"z+"} and operator.phase == "rise above the boxes"
    assert decide(under, True, 0.1).held == {"z+"}  # a bump: a person tries on for a moment
    keys = decide(under, True, 0.1 + BACK_OUT_AFTER_S + 0.05)
    assert operator.phase == "back out from under the obstacle" and "z+" not in keys.held and keys.held
    assert _keys_step(keys) @ towards_robot > 0  # the keys held move the gripper towards the robot
    out = under + (BACK_OUT_M + 0.005) * towards_robot  # backed out: the move is free again
    assert decide(out, False, 2.0).held == {"z+"} and operator.phase == "rise above the boxes"


def test_a_person_who_cannot_back_out_towards_the_robot_moves_the_other_way_then_rises():
    """Backing out of a blocked rise can be refused too: the arm folded back against the robot's own body (seen
    once in a 100-participant load run: the model held the back-out keys for the try's 300 s). A person then moves
    away from the robot by as much, then rises again; and when that is refused as well, rises again (no way is held
    against a refusal for long)."""
    scene = build_scene("high", 5)
    setup = Simulation(scene, 5, 30.0).setup
    operator = Operator(setup)
    _, heading = operator.mast.radial(operator.grasp)
    outwards = np.array([math.cos(heading), math.sin(heading), 0.0])
    folded = np.append(operator.mast.xy, 0.0) + 0.2 * outwards
    folded[2] = operator.clear - 0.05  # close to the mast, below the boxes' top, between the robot and the item

    def decide(tcp, blocked: bool, now: float) -> Keys:
        world = setup["world"] | {"tcp": list(tcp)}
        return operator.decide(View.exact(world, setup["guidance"] | {"blocked": blocked}), now)

    assert decide(folded, True, 0.0).held == {"z+"}
    keys = decide(folded, True, BACK_OUT_AFTER_S + 0.05)
    assert operator.phase == "back out from under the obstacle" and _keys_step(keys) @ outwards < 0
    assert decide(folded, True, BACK_OUT_AFTER_S + 0.5).held == keys.held  # a moment blocked: a person tries on
    keys = decide(folded, True, 2 * BACK_OUT_AFTER_S + 0.1)  # refused as long: the other way
    assert operator.phase == "move out from under the obstacle" and _keys_step(keys) @ outwards > 0
    assert "z+" not in keys.held
    away = folded + (BACK_OUT_M + 0.005) * outwards  # out from under it: up again
    assert decide(away, False, 2.5).held == {"z+"} and operator.phase == "rise above the boxes"
    # both ways refused: no way is held for long, the person rises again and starts over
    decide(folded, True, 5.0)
    decide(folded, True, 5.0 + BACK_OUT_AFTER_S + 0.05)
    assert operator.phase == "back out from under the obstacle"
    decide(folded, True, 5.0 + 2 * BACK_OUT_AFTER_S + 0.1)
    assert operator.phase == "move out from under the obstacle"
    assert decide(folded, True, 5.0 + 3 * BACK_OUT_AFTER_S + 0.15).held == {"z+"}
