"""The strategy of a person who teleoperates the robot from the participant page, having read the instructions.

It is the participant of ``benchmarks/bench_teleop.py`` and of the tests that show a person can teleoperate (with
``experiment.participants.person.HumanModel`` around it), and what the browser driver (``server.harness.driver``)
steers by. It reads plain dicts of the protocol (``server/teleop_messages.py``) — the hello's ``teleop`` setup
(scene, limits, world, guidance) and the latest ``world`` message — and answers what a person would do with the
page's keyboard (``Keys``): which motion keys are held, whether Shift (precise) is held, and whether G is pressed.
It knows nothing of the robot's code (no kinematics, no scene builder, no scripted controller): a test checks the
imports of ``experiment.participants``' teleoperation modules.

``Operator`` decides from the guidance step and the positions sent. Move the gripper along the world axes towards a
target with on/off keys, at full speed far away and precise (Shift) close to it; in high complexity rise above the
boxes (``scene.clear_height``) before moving over the item; lower onto the grasp point and press G when the page says
it is close enough; lift, pull in towards the mast, turn with Q/E towards the bin, move over the opening and press
G. The mast is estimated from the poses seen (``experiment.participants.mast``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from experiment.participants.keys import Keys
from experiment.participants.mast import MastEstimate, as_vector, heading_of, wrap_angle


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
        return cls(as_vector(world["tcp"]), heading_of(world), world, guidance)


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
        self.grasp = as_vector(scene["target"]["grasp_point"])
        self.release = as_vector(scene["bin"]["release_point"])
        self.bin_center = as_vector(scene["bin"]["opening_center"])
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
        if abs(wrap_angle(goal - view.heading)) > (TURN_TOL if self.turning else 0.35) and horizontal > 0.1:
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
        if not near and abs(wrap_angle(goal - view.heading)) > TURN_TOL + (0.0 if self.turning else 0.1):
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
        error = wrap_angle(goal - view.heading)
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
