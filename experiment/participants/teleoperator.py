"""A human-like teleoperator that sees only what the teleoperation socket sends.

It is the participant of ``benchmarks/bench_teleop.py`` and of the tests that show a person can
teleoperate: it reads plain dicts of the protocol (``server/teleop_messages.py``) — the hello's
``teleop`` setup (scene, limits, world, guidance) and the latest ``world`` message — and answers what
a person would do with the page's keyboard: which motion keys are held, whether Shift (precise) is
held, and whether G is pressed. It knows nothing of the robot's code (no kinematics, no scene builder,
no scripted controller): a test checks this module's imports.

- ``Operator``: the strategy, from the guidance step and the positions sent. Move the gripper along
  the world axes towards a target with on/off keys, at full speed far away and precise (Shift) close
  to it; in high complexity rise above the boxes (``scene.clear_height``) before moving over the item;
  lower onto the grasp point and press G when the page says it is close enough; lift, pull in towards
  the mast, turn with Q/E towards the bin, move over the opening and press G. The mast (the axis the
  arm turns about) is not sent: it is estimated from the TCP positions and joint angles seen, by least
  squares over the arm's pose (the TCP lies in the vertical plane through the mast at heading
  ``base yaw + j1``, at a horizontal reach that is a sum of link projections).
- ``HumanModel``: the person around it. What is seen reaches the decision a reaction time later
  (lognormal, a few hundred ms), with perceptual noise of a few mm; keys are held, not steered, so a key
  is released late when the delay is misjudged (overshoot); the person anticipates the motion of the
  keys held (a learned display lag, from when the arm was seen to start moving after a press, and the
  page's rhythm: how often its picture changes and it takes keys in), slows down (Shift) farther out on
  a jerky page, believes the eyes when the picture stops changing although keys are held, and sometimes
  hesitates when the instruction changes. Deterministic for a seed.
- ``input_fields`` / ``gripper_action`` / ``ClientLoop``: held keys as the page turns them into an
  input message (``static/js/teleop.js``, ``Teleop.motion``): 0.2 m/s per world axis held (0.025 with
  Shift), each axis clamped to ±1 × the speed; j1 at 0.6 rad/s (0.1); a joint key takes precedence over
  the axis keys; G sends "close" when the gripper is fully open, else "open". ``ClientLoop`` is the page
  between the person and the socket: a starved page whose one loop runs at a fixed rate, or a page that
  takes keys as they come and sends keep-alives on a timer.
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Motion actions: world axis (x towards the shelf, y to the left, z up) or joint 1 (yaw about the mast).
ACTIONS = {"x+": ("ee", 0, 1), "x-": ("ee", 0, -1), "y+": ("ee", 1, 1), "y-": ("ee", 1, -1),
           "z+": ("ee", 2, 1), "z-": ("ee", 2, -1), "j1+": ("joint", 0, 1), "j1-": ("joint", 0, -1)}
#: The page's speeds (static/js/teleop.js): m/s per world axis held, rad/s of j1; fine = with Shift.
EE_SPEED, EE_SPEED_FINE = 0.2, 0.025
JOINT_SPEED, JOINT_SPEED_FINE = 0.6, 0.1
#: Finger gap (m) of the fully open gripper (the protocol's ``gripper_target`` when open).
GRIPPER_OPEN = 0.1
#: The page's keys for the actions (for a browser driver).
KEY_CODES = {"x+": "KeyW", "x-": "KeyS", "y+": "KeyA", "y-": "KeyD", "z+": "KeyR", "z-": "KeyF",
             "j1+": "KeyQ", "j1-": "KeyE"}


@dataclass(frozen=True)
class Keys:
    """What the person does at one moment: motion keys held, Shift held, G pressed (with what it means)."""

    held: frozenset[str] = frozenset()
    fine: bool = False
    gripper: str | None = None  # "open" / "close": G pressed now, meaning that (None: not pressed)

    def motion(self) -> dict[str, Any]:
        return input_fields(self.held, self.fine)


# -- the page's mapping from keys to the input message ------------------------------------------------------
def input_fields(held: Iterable[str], fine: bool = False) -> dict[str, Any]:
    """The motion part of an input message for these held keys, as the page's ``Teleop.motion()`` builds it:
    ``{"joint_velocity": [...]}``, ``{"ee_velocity": [...]}`` or ``{}`` (nothing held: stop)."""
    ee, joint = [0.0, 0.0, 0.0], 0.0
    for action in held:
        kind, axis, sign = ACTIONS[action]
        if kind == "ee":
            ee[axis] += sign
        else:
            joint += sign
    clamp = lambda v: max(-1.0, min(1.0, v))  # noqa: E731
    if joint != 0:
        return {"joint_velocity": [clamp(joint) * (JOINT_SPEED_FINE if fine else JOINT_SPEED), 0.0, 0.0, 0.0]}
    if any(v != 0 for v in ee):
        speed = EE_SPEED_FINE if fine else EE_SPEED
        return {"ee_velocity": [clamp(v) * speed for v in ee]}
    return {}


def gripper_action(world: Mapping[str, Any] | None) -> str:
    """What the page sends for a press of G with ``world`` shown: close a fully open gripper, else open."""
    return "close" if world is None or world["gripper_target"] >= GRIPPER_OPEN - 1e-6 else "open"


def input_message(seq: int, keys: Keys, world: Mapping[str, Any] | None, client_ms: float | None = None
                  ) -> dict[str, Any]:
    """The input message the page sends for ``keys`` (G's meaning from ``world``, as the page decides it)."""
    message: dict[str, Any] = {"type": "input", "seq": seq, "client_ms": client_ms, **keys.motion()}
    if keys.gripper is not None:
        message["gripper"] = gripper_action(world)
    return message


# -- small geometry ------------------------------------------------------------------------------------------
def _vec(value) -> np.ndarray:
    return np.asarray(value, dtype=float)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def heading_of(world: Mapping[str, Any]) -> float:
    """The arm's heading (rad, world frame): base yaw + j1."""
    return float(world["base"][2]) + float(world["joints"][0])


class MastEstimate:
    """Where the mast axis is (world x, y), from the arm poses seen (least squares, see the module docstring).

    Unknowns: mast x, y and the horizontal projections' lengths of the upper arm and forearm. Each pose
    seen gives tcp_xy = mast + (L2 cos q2 + L3 cos(q2 + q3)) (cos h, sin h) with h = base yaw + j1 (the
    tool points down, so it adds no reach). A weak prior (the base's origin, 0.5 m links) holds it
    while the poses seen are too alike.
    """

    PRIOR_WEIGHT = 0.03

    def __init__(self, base: Iterable[float]):
        base = list(base)
        self.prior = np.array([base[0], base[1], 0.5, 0.5])
        w2 = self.PRIOR_WEIGHT ** 2
        self.ata = np.eye(4) * w2
        self.atb = self.prior * w2
        self.last_joints: np.ndarray | None = None
        self.count = 0
        self._solution = self.prior.copy()

    def add(self, tcp: Iterable[float], world: Mapping[str, Any]) -> None:
        joints = _vec(world["joints"])
        if self.last_joints is not None and float(np.abs(joints - self.last_joints).sum()) < 0.004:
            return
        self.last_joints = joints
        h = heading_of(world)
        c2, c3 = math.cos(joints[1]), math.cos(joints[1] + joints[2])
        tcp = list(tcp)
        for row, value in (((1.0, 0.0, math.cos(h) * c2, math.cos(h) * c3), tcp[0]),
                           ((0.0, 1.0, math.sin(h) * c2, math.sin(h) * c3), tcp[1])):
            r = np.array(row)
            self.ata += np.outer(r, r)
            self.atb += r * value
        self.count += 1
        self._solution = np.linalg.solve(self.ata, self.atb)

    @property
    def xy(self) -> np.ndarray:
        return self._solution[:2]

    def radial(self, point: Iterable[float]) -> tuple[float, float]:
        """(reach m, heading rad) of a world point about the estimated mast axis."""
        p = list(point)
        dx, dy = p[0] - self._solution[0], p[1] - self._solution[1]
        return math.hypot(dx, dy), math.atan2(dy, dx)


# -- the strategy ----------------------------------------------------------------------------------------------
@dataclass
class View:
    """What the person believes now: the TCP position and the arm's heading (noisy, anticipated), with
    the world and guidance messages they were read from."""

    tcp: np.ndarray
    heading: float
    world: Mapping[str, Any]
    guidance: Mapping[str, Any]
    settled: bool = True  # no motion key has been held for a while (the arm is at rest)

    @classmethod
    def exact(cls, world: Mapping[str, Any], guidance: Mapping[str, Any]) -> View:
        return cls(_vec(world["tcp"]), heading_of(world), world, guidance)


@dataclass
class Axis:
    """One world axis's goal: hold its key until the error is within ``tol`` (m); far off at full speed.

    ``side`` +1: only at least ``target`` matters (-1: at most; 0: both); ``loose``: never slow down (Shift)
    for it: overshooting does not matter.
    """

    target: float
    tol: float
    side: int = 0
    loose: bool = False


#: Errors (m) beyond which a key is held at full speed; within them with Shift. Wider for loose goals.
COARSE_BAND = 0.015
#: Heading errors (rad): turned when within TURN_TOL; Q/E at full speed beyond TURN_COARSE.
TURN_TOL, TURN_COARSE = 0.06, 0.12
#: Reach from the mast (m) to pull in to before turning, and the margin (m) above the shelf and boxes.
SWING_REACH, SWING_MARGIN = 0.28, 0.05
#: Rising above the boxes and held there by something over the gripper (a shelf board, a box's edge): after this
#: long blocked (s) the person backs out towards the robot by ``BACK_OUT_M``, then rises again. Without it the model
#: held the rise key against the obstacle until the time limit (seen once in a 100-participant load run). When
#: backing out is refused as long (the arm folded back against the robot's own body, also seen once at 100), the
#: person moves the other way, away from the robot, by as much, then rises again.
BACK_OUT_AFTER_S, BACK_OUT_M = 0.8, 0.10


class Operator:
    """The strategy of a person who has read the instructions (see the module docstring).

    ``decide(view, now)`` returns the ``Keys`` to hold. It keeps a little state: the mast estimate
    (``see``), a pending gripper press (waits to see its effect before pressing again), margins that
    grow when a move was blocked.
    """

    def __init__(self, setup: Mapping[str, Any]):
        scene = setup["scene"]
        self.complexity = scene["complexity"]
        self.grasp = _vec(scene["target"]["grasp_point"])
        self.release = _vec(scene["bin"]["release_point"])
        self.bin_center = _vec(scene["bin"]["opening_center"])
        self.clear = float(scene["clear_height"])
        self.obstacles = bool(scene["obstacles"])
        target = scene["target"]
        #: How far the carried item hangs below the TCP (its bottom), from its size and grasp point.
        self.hang = float(self.grasp[2]) - (float(target["center"][2]) - float(target["size"][2]) / 2)
        shelf_top = max((b["center"][2] + b["size"][2] / 2 for b in scene["shelf"]), default=0.0)
        #: Turning, the carried item passes above everything: the boxes (clear_height) and the shelf.
        self.swing_z = max(self.clear, shelf_top + self.hang) + SWING_MARGIN
        self.swing_reach = SWING_REACH
        self.hover_z = self.clear + 0.01 if self.obstacles else float(self.grasp[2]) + 0.06
        self.mast = MastEstimate(setup["world"]["base"])
        #: A G press whose effect has not been seen yet: (pressed at, gripper_target then, item mode then, keys held
        #: meanwhile).
        self.pending: tuple[float, float, str, Keys] | None = None
        self.lowering = False
        self.turning = False
        self.blocked_since: float | None = None
        self.backed_off = -math.inf
        #: Getting out from under what blocks a rise: (the reach (m) to go to, -1 towards the robot or +1 away).
        self.back_out: tuple[float, int] | None = None
        #: Errors (m, rad) beyond which keys are held at full speed; a person seeing a jerky page widens them.
        self.coarse_band, self.coarse_turn = COARSE_BAND, TURN_COARSE
        self.phase = ""  # what it is doing (for traces)

    def see(self, tcp: Iterable[float], world: Mapping[str, Any]) -> None:
        """A pose seen (positions as perceived): refines the mast estimate."""
        self.mast.add(tcp, world)

    # -- deciding ------------------------------------------------------------------------------------------
    def decide(self, view: View, now: float) -> Keys:
        world, guidance = view.world, view.guidance
        step = guidance["step"]
        if self.pending is not None:
            pressed_at, target, mode, meanwhile = self.pending
            if (world["gripper_target"] != target or world["item"]["mode"] != mode) or now - pressed_at > 2.0:
                self.pending = None
            else:
                self.phase = "wait for the gripper" + (" (lifting)" if meanwhile.held else "")
                return meanwhile
        self._note_blocked(guidance, now)
        if step in ("done", "wait_for_item"):
            self.phase = step
            return Keys()
        if step == "open_gripper":
            return self._press("open", world, now)
        if step == "close_gripper":
            distance = math.dist(view.tcp, self.grasp)
            if distance < 0.035:
                # sure of it when the picture shows the arm at rest there, or it is well inside: lift at once (G, R)
                sure = view.settled or distance < 0.025
                return self._press("close", world, now, Keys(frozenset({"z+"})) if sure else Keys())
            self.phase = "almost close enough"
            return self._steer(view, {i: Axis(float(self.grasp[i]), 0.008) for i in range(3)})
        if world["item"]["mode"] == "grasped":
            return self._to_bin(view, now)
        return self._to_item(view, now)

    def _press(self, action: str, world: Mapping[str, Any], now: float, meanwhile: Keys = Keys()) -> Keys:
        """Press G; until its effect is seen, hold ``meanwhile``."""
        self.pending = (now, world["gripper_target"], world["item"]["mode"], meanwhile)
        self.phase = f"press G ({action})"
        self.lowering = False
        return Keys(gripper=action)

    def _note_blocked(self, guidance: Mapping[str, Any], now: float) -> None:
        if not guidance.get("blocked"):
            self.blocked_since = None
            return
        if self.blocked_since is None:
            self.blocked_since = now
            if self.lowering:
                self.lowering = False  # back up and line up again above the item
        if now - self.backed_off > 1.0:
            # a person who bumped into something keeps a bigger distance from then on
            self.backed_off = now
            self.swing_z += 0.03
            self.swing_reach = max(0.18, self.swing_reach - 0.03)

    def _to_item(self, view: View, now: float) -> Keys:
        tcp = view.tcp
        _, goal = self.mast.radial(self.grasp)
        horizontal = math.dist(tcp[:2], self.grasp[:2])
        if abs(_wrap(goal - view.heading)) > (TURN_TOL if self.turning else 0.35) and horizontal > 0.1:
            return self._swing(view, goal, "turn back to the shelf")
        self.turning = False
        if self.lowering and horizontal > 0.04:
            self.lowering = False
        if not self.lowering and horizontal < 0.02:
            self.lowering = True
        if self.lowering:
            self.phase = "lower onto the item"
            return self._steer(view, {0: Axis(float(self.grasp[0]), 0.012), 1: Axis(float(self.grasp[1]), 0.012),
                                      2: Axis(float(self.grasp[2]), 0.012)})
        if self.obstacles and tcp[2] < self.clear - 0.01 and horizontal > 0.06:
            return self._rise(view, now)
        self.back_out = None
        self.phase = "move above the item"
        # down to the hover height on the way (back up to it only when still far: the fingers would hit the item)
        z = Axis(self.hover_z + 0.02, 0.02) if horizontal > 0.04 else Axis(self.hover_z, 0.02, side=-1)
        return self._steer(view, {0: Axis(float(self.grasp[0]), 0.01), 1: Axis(float(self.grasp[1]), 0.01), 2: z})

    def _rise(self, view: View, now: float) -> Keys:
        """Up above the boxes; when something above holds the gripper down, back out towards the robot first (by
        ``BACK_OUT_M``, without the rise key: a move into the obstacle is refused whole), or away from it when that
        is refused too, then rise again, as a person who sees the arm stuck under it does."""
        tcp = view.tcp
        reach, heading = self.mast.radial(tcp)
        stuck = self.blocked_since is not None and now - self.blocked_since > BACK_OUT_AFTER_S
        if self.back_out is not None:
            goal, way = self.back_out
            if way * (reach - goal) >= -0.01:  # out from under it: rise again
                self.back_out = None
            elif stuck:  # this way is refused too: the other way (from away, rise again)
                self.back_out = (reach + BACK_OUT_M, 1) if way < 0 else None
                self.blocked_since = now  # how long the next way is refused counts from now
        elif stuck:
            self.back_out, self.blocked_since = (max(0.0, reach - BACK_OUT_M), -1), now
        if self.back_out is not None:
            goal, way = self.back_out
            self.phase = "back out from under the obstacle" if way < 0 else "move out from under the obstacle"
            out = self.mast.xy + goal * np.array([math.cos(heading), math.sin(heading)])
            return self._steer(view, {0: Axis(float(out[0]), 0.01, loose=True), 1: Axis(float(out[1]), 0.01,
                                                                                          loose=True)})
        self.phase = "rise above the boxes"
        return self._steer(view, {2: Axis(self.clear + 0.02, 0.015, side=1, loose=True)})

    def _to_bin(self, view: View, now: float) -> Keys:
        tcp = view.tcp
        guidance = view.guidance
        _, goal = self.mast.radial(self.release)
        off = math.dist(tcp[:2], self.release[:2])
        if guidance.get("over_bin") and (off < 0.06 or view.settled):
            return self._press("open", view.world, now)  # over the opening, and (as anticipated) still there
        near = off < 0.15  # over the bin's corner already: just move over the opening
        if not near and abs(_wrap(goal - view.heading)) > TURN_TOL + (0.0 if self.turning else 0.1):
            return self._swing(view, goal, "turn to the bin")
        self.turning = False
        self.phase = "move over the bin"
        z = min(max(float(tcp[2]), float(self.release[2])), self.swing_z + 0.05)
        return self._steer(view, {0: Axis(float(self.release[0]), 0.012), 1: Axis(float(self.release[1]), 0.012),
                                  2: Axis(z, 0.03)})

    def _swing(self, view: View, goal: float, what: str) -> Keys:
        """Rise above the shelf and boxes, pull in towards the mast, then turn to heading ``goal``."""
        tcp = view.tcp
        reach, now_heading = self.mast.radial(tcp)
        low = tcp[2] < self.swing_z - (0.06 if self.turning else 0.02)
        axes: dict[int, Axis] = {}
        if low:
            axes[2] = Axis(self.swing_z + 0.01, 0.01, side=1, loose=True)
        if reach > self.swing_reach + (0.1 if self.turning else 0.03) and (not low or tcp[2] >= self.clear):
            mast = self.mast.xy
            in_xy = mast + self.swing_reach * np.array([math.cos(now_heading), math.sin(now_heading)])
            axes[0], axes[1] = Axis(float(in_xy[0]), 0.03, loose=True), Axis(float(in_xy[1]), 0.03, loose=True)
        if axes:
            self.phase = f"{what}: rise and pull in"
            return self._steer(view, axes)
        self.phase, self.turning = what, True
        error = _wrap(goal - view.heading)
        if abs(error) <= TURN_TOL:
            return Keys()
        return Keys(frozenset({"j1+" if error > 0 else "j1-"}), fine=abs(error) < self.coarse_turn)

    def _steer(self, view: View, axes: Mapping[int, Axis]) -> Keys:
        """On/off keys per world axis: full speed on the axes far off; when none is, Shift on the rest."""
        names = (("x+", "x-"), ("y+", "y-"), ("z+", "z-"))
        far, near = set(), set()
        for i, goal in axes.items():
            error = goal.target - float(view.tcp[i])
            key = names[i][0 if error > 0 else 1]
            if goal.side * error < 0:
                continue  # on the side that is fine
            if abs(error) > goal.tol and goal.loose:
                far.add(key)
            elif abs(error) > max(goal.tol, self.coarse_band):
                far.add(key)
            elif abs(error) > goal.tol:
                near.add(key)
        if far:
            return Keys(frozenset(far))
        return Keys(frozenset(near), fine=bool(near))


# -- the person --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HumanParams:
    reaction_s: float = 0.30  # median delay from seeing to acting
    reaction_sigma: float = 0.25  # its lognormal spread
    noise_m: float = 0.003  # perceptual noise (sd per axis) on positions
    noise_rad: float = 0.01  # on the arm's heading
    speed_belief_sd: float = 0.08  # how wrong the person's sense of the keys' speeds is (relative)
    initial_lag_s: float = 0.15  # the display lag a person expects before seeing how the page responds
    hesitation_p: float = 0.15  # chance of pausing when the instruction changes
    hesitation_s: tuple[float, float] = (0.3, 1.2)
    cycle_s: float = 0.04  # how often the person re-decides


@dataclass
class _Percept:
    available: float  # when it reaches the decision (seen + reaction)
    seen: float  # when the page showed it
    world: Mapping[str, Any]
    guidance: Mapping[str, Any]
    tcp: np.ndarray  # as perceived (with noise)
    heading: float


@dataclass
class _LagProbe:
    pressed: float
    direction: np.ndarray | None  # ee direction pressed (None: a turn)
    turn: float
    speed: float  # m/s or rad/s
    tcp: np.ndarray
    heading: float


class HumanModel:
    """A person at the keyboard: ``see(now, message)`` what the page shows, ``keys(now)`` what is held.

    ``message`` is a world message or the hello's ``teleop`` setup (dicts with ``world`` and ``guidance``).
    Time is the caller's clock (s); call ``keys`` as often as the page would look at the keyboard.
    """

    def __init__(self, setup: Mapping[str, Any], seed: int, params: HumanParams | None = None):
        self.params = params or HumanParams()
        self.rng = random.Random(seed)
        self.operator = Operator(setup)
        p = self.params
        self.speed_belief = max(0.5, self.rng.gauss(1.0, p.speed_belief_sd))
        self.lag = p.initial_lag_s
        self.lag_samples: list[float] = []
        self.queue: list[_Percept] = []
        self.current: _Percept | None = None
        self.last_message: Any = None
        self.last_new: float | None = None
        self.frame_s = 1 / 15  # how often the page's picture changes while the arm moves (as the person sees it)
        self.frames: list[float] = []
        self.bias = np.zeros(3)
        self.bias_heading = 0.0
        self.brain_t: float | None = None
        self.held = self.wanted = Keys()
        self.last_call: float | None = None
        self.calls: list[float] = []
        self.cadence = 0.0  # how often the page takes keys in (s), as the person experiences it
        self.history: list[tuple[float, Keys]] = [(-1e9, Keys())]  # (since, keys) as decided
        self.hesitate_until = -1e9
        self.last_step: str | None = None
        self.pending_gripper: str | None = None
        self.probe: _LagProbe | None = None
        self.decisions = 0

    # -- perception ----------------------------------------------------------------------------------
    def see(self, now: float, message: Mapping[str, Any]) -> None:
        last = self.last_message
        if message is last or (last is not None and message["world"] == last["world"]
                               and message["guidance"] == last["guidance"]):
            return  # the same picture
        self.last_message = message
        if self.last_new is not None and now - self.last_new < 1.0:
            self.frames = (self.frames + [now - self.last_new])[-6:]
            self.frame_s = float(np.median(self.frames))
            self._bands()
        self.last_new = now
        p = self.params
        delay = p.reaction_s * math.exp(self.rng.gauss(0.0, p.reaction_sigma))
        available = max(now + delay, self.queue[-1].available if self.queue else -1e9)
        keep = math.exp(-0.3)  # a slowly wandering misjudgement of where the gripper is
        self.bias = self.bias * keep + np.array([self.rng.gauss(0, p.noise_m) for _ in range(3)]) * math.sqrt(1 - keep**2)
        self.bias_heading = (self.bias_heading * keep
                             + self.rng.gauss(0, p.noise_rad) * math.sqrt(1 - keep**2))
        world = message["world"]
        self.queue.append(_Percept(available, now, world, message["guidance"], _vec(world["tcp"]) + self.bias,
                                   heading_of(world) + self.bias_heading))

    def _perceive(self, t: float) -> bool:
        """Take in what has reached the decision by ``t``; whether anything new did."""
        new = False
        while self.queue and self.queue[0].available <= t:
            percept = self.queue.pop(0)
            self.current, new = percept, True
            self.operator.see(percept.tcp, percept.world)
            self._learn_lag(percept)
        return new

    def _learn_lag(self, percept: _Percept) -> None:
        probe = self.probe
        if probe is None or percept.seen <= probe.pressed:
            return
        if percept.guidance.get("blocked") or percept.seen - probe.pressed > 2.0:
            self.probe = None  # it did not move as pressed: nothing to learn from
            return
        if probe.direction is not None:
            moved = float(np.dot(percept.tcp - probe.tcp, probe.direction))
            threshold = 0.01
        else:
            moved = _wrap(percept.heading - probe.heading) * probe.turn
            threshold = 0.04
        if moved > threshold:
            # seen at `seen`, it had moved for moved / speed since the press took effect
            self.lag_samples.append(min(1.5, max(0.0, percept.seen - probe.pressed - moved / probe.speed)))
            self.lag = max(0.05, float(np.median(self.lag_samples[-5:])))
            self.probe = None

    # -- anticipation ----------------------------------------------------------------------------------
    def _velocity(self, keys: Keys) -> tuple[np.ndarray, float]:
        motion = keys.motion()
        if "joint_velocity" in motion:
            return np.zeros(3), motion["joint_velocity"][0] * self.speed_belief
        if "ee_velocity" in motion:
            return _vec(motion["ee_velocity"]) * self.speed_belief, 0.0
        return np.zeros(3), 0.0

    def _anticipate(self, percept: _Percept, t: float) -> tuple[np.ndarray, float, bool]:
        """Where the person believes the gripper is when a key change made at ``t`` takes effect: what was
        seen, moved on by the keys held since (shifted by the lag the person expects); and whether it has come
        to rest."""
        tcp, heading = percept.tcp.copy(), percept.heading
        shown_until = percept.seen - self.lag  # the picture shows the keys held up to about then
        arrives = self._effective(t)  # where it will be when a change made now takes effect
        blocked = bool(percept.guidance.get("blocked"))  # it did not move as the keys said: believe the eyes
        # keys held long enough ago that a new picture should have shown the motion, yet none came: not moving
        window = self.lag + 2 * max(self.frame_s, self.cadence) + 0.5
        if self.last_new is not None and t - self.last_new > window:
            for i, (since, keys) in enumerate(self.history):
                until = self.history[i + 1][0] if i + 1 < len(self.history) else math.inf
                if keys.held and since < t - window and until > self.last_new - self.lag + 0.05:
                    blocked = True
        settled = not blocked
        for i, (since, keys) in enumerate(self.history):
            until = self.history[i + 1][0] if i + 1 < len(self.history) else math.inf
            if keys.held and until > shown_until - 0.1:  # the picture may still show it moving
                settled = False
            lo, hi = max(since, shown_until), min(until, arrives)
            if hi <= lo or blocked:
                continue
            v, w = self._velocity(keys)
            tcp += v * (hi - lo)
            heading += w * (hi - lo)
        return tcp, heading, settled

    # -- acting --------------------------------------------------------------------------------------
    def keys(self, now: float) -> Keys:
        """The keys held at ``now`` (a G press is reported once).

        Call it whenever the page takes keys in (its loop, or the test driver's poll): what the person decided
        since the last call is what the page gets now; decisions in between that were undone never reach it.
        """
        cycle = self.params.cycle_s
        if self.last_call is not None and 0 < now - self.last_call < 2.0:
            self.calls = (self.calls + [now - self.last_call])[-6:]
            self.cadence = float(np.median(self.calls))
            self._bands()
        if self.brain_t is None:
            self.brain_t = now
        while self.brain_t <= now + 1e-9:
            self._think(self.brain_t)
            self.brain_t += cycle
        self.last_call = now
        self._hold(now, self.wanted)
        gripper, self.pending_gripper = self.pending_gripper, None
        return Keys(self.held.held, self.held.fine, gripper)

    def _bands(self) -> None:
        """A jerky page (pictures or key handling far apart) makes the person slow down (Shift) farther out:
        full speed only while a whole step of the page's rhythm lands closer to the goal."""
        step = max(self.frame_s, self.cadence)
        self.operator.coarse_band = max(COARSE_BAND, 0.75 * EE_SPEED * step)
        self.operator.coarse_turn = max(TURN_COARSE, 0.75 * JOINT_SPEED * step)

    def _think(self, t: float) -> None:
        self._perceive(t)
        percept = self.current
        if percept is None:
            return
        step = percept.guidance["step"]
        if step != self.last_step:
            if self.last_step is not None and self.rng.random() < self.params.hesitation_p:
                low, high = self.params.hesitation_s
                self.hesitate_until = t + self.rng.uniform(low, high)
            self.last_step = step
        if t < self.hesitate_until:
            self.wanted = Keys()
            return
        tcp, heading, settled = self._anticipate(percept, t)
        view = View(tcp, heading, percept.world, percept.guidance, settled)
        decided = self.operator.decide(view, t)
        self.decisions += 1
        if decided.gripper is not None:
            self.pending_gripper = decided.gripper
        self.wanted = Keys(decided.held, decided.fine)

    def _effective(self, t: float) -> float:
        """When a key change decided at ``t`` reaches the arm, as the person has come to expect: at the page's
        next look at the keyboard."""
        if self.last_call is None:
            return t
        return max(t, self.last_call + self.cadence)

    def _hold(self, t: float, keys: Keys) -> None:
        """The page takes ``keys`` in at ``t``."""
        if keys == self.held:
            return
        was_idle = not self.held.held
        self.held = keys
        idle_since = self.history[-1][0]
        self.history.append((t, keys))
        if len(self.history) > 200:
            self.history = self.history[-100:]
        self.probe = None  # a new press from rest shows the lag; any other change spoils the measurement
        if keys.held and was_idle and idle_since < t - 0.3 and self.current is not None:
            motion = keys.motion()
            if "ee_velocity" in motion:
                v = _vec(motion["ee_velocity"])
                speed = float(np.linalg.norm(v))
                self.probe = _LagProbe(t, v / speed, 0.0, speed, self.current.tcp, self.current.heading)
            elif "joint_velocity" in motion:
                w = motion["joint_velocity"][0]
                self.probe = _LagProbe(t, None, math.copysign(1.0, w), abs(w), self.current.tcp,
                                       self.current.heading)

    @property
    def phase(self) -> str:
        return self.operator.phase


# -- a client: the page's loop --------------------------------------------------------------------------------
#: How often a page that is not starved looks at the keyboard and redraws (s): about a display frame.
PAGE_FRAME_S = 0.04


@dataclass
class ClientLoop:
    """The page between the person and the socket; each call returns the messages to send.

    Two ways to use it (``benchmarks/bench_teleop.py`` runs both):

    - a page whose one loop runs at a fixed rate (a starved page): call ``tick`` at that rate. It shows the
      latest world message to the person, sends an input message when the held keys changed (or G was
      pressed), and a keep-alive when ``keepalive_s`` has passed since the last message while motion is held.
    - a page that handles keys and draws as they come but whose timer sends at a fixed rate: call
      ``tick(now, latest, keepalive=False)`` every ``PAGE_FRAME_S`` and ``keepalive(now)`` at the rate (one
      keep-alive per timer tick while motion is held).

    A world message that says the arm is not moving although the server holds this client's latest input
    (``moving`` false, ``input_seq`` its own: the dead-man time passed while the loop stalled) makes it send
    the held motion again; so does a refused input (``ack``: e.g. too many messages).
    """

    human: HumanModel
    keepalive_s: float
    seq: int = 0
    sent_motion: dict[str, Any] = field(default_factory=dict)
    last_send: float = -1e9
    input_seq: int = -1  # seq of the last input message sent
    resent_for: Any = None
    inputs: int = 0
    keepalives: int = 0
    resends: int = 0  # inputs sent again after a dead-man stop
    refused: int = 0  # messages the server refused
    refused_input: bool = False  # the latest input was refused: send the input state again

    def tick(self, now: float, latest: Mapping[str, Any] | None, keepalive: bool = True) -> list[dict[str, Any]]:
        if latest is not None:
            self.human.see(now, latest)
        keys = self.human.keys(now)
        motion = keys.motion()
        world = latest["world"] if latest is not None else None
        if (motion != self.sent_motion or keys.gripper is not None or self._stopped(latest, motion)
                or self.refused_input):
            self.refused_input = False
            self.seq += 1
            self.sent_motion, self.last_send, self.input_seq = motion, now, self.seq
            self.inputs += 1
            return [input_message(self.seq, keys, world, client_ms=now * 1000)]
        if keepalive and now - self.last_send >= self.keepalive_s - 1e-6:
            return self.keepalive(now)
        return []

    def _stopped(self, latest: Mapping[str, Any] | None, motion: Mapping[str, Any]) -> bool:
        """The server holds this client's latest input but says the arm is not moving: the dead-man time
        passed (a stalled loop); the motion still held is sent again (once per such world message)."""
        if (not motion or latest is None or latest.get("type") != "world" or latest.get("moving", True)
                or latest is self.resent_for or (latest.get("input_seq") or -1) < self.input_seq):
            return False
        self.resent_for = latest
        self.resends += 1
        return True

    def ack(self, message: Mapping[str, Any]) -> None:
        """An ack from the server: a refused input (e.g. too many messages) is sent again at the next tick."""
        if not message.get("ok", True):
            self.refused += 1
            if message.get("seq") == self.input_seq:
                self.refused_input = True

    def keepalive(self, now: float) -> list[dict[str, Any]]:
        """A keep-alive, when motion is held."""
        if not self.sent_motion:
            return []
        self.seq += 1
        self.last_send = now
        self.keepalives += 1
        return [{"type": "keepalive", "seq": self.seq, "client_ms": now * 1000}]
