"""The robot's autonomous attempt: a timed trajectory planned once, sampled at any t.

``plan_attempt`` builds the whole motion at ``SAMPLE_RATE`` (base pose, joints,
gripper per sample) with closed-form IK along straight TCP lines; ``state_at``
interpolates linearly between samples and places the item from the event
times, so it is pure and cheap. Phases: drive to the shelf, approach above the
item (in high complexity at ``transfer_height``, over the obstacles), descend,
close, lift to ``transfer_height``, retract towards the mast, swing to the bin,
lower, release, settle.

Failures: "collision" (high complexity, probability ``P_COLLISION_HIGH`` of a
failure there): after grasping, the arm lifts only a little and heads
straight for the bin, through the obstacle in front of the item; it stops at
the first sample where ``collisions()`` reports contact and lets the item
fall ``FAIL_RELEASE_DELAY`` later. "drop" (all other failures): the item
slips out of the gripper during the retract or the swing and falls onto
whatever is below (the floor when possible, never the bin); the arm
finishes its motion empty.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from experiment.world import constants as K
from experiment.world.collision import collisions
from experiment.world.geometry import quat_yaw_pitch
from experiment.world.path import Path, bin_release_point, radial_point, ready_joints
from experiment.world.robot import arm_points, radial
from experiment.world.scene import Scene, transfer_height
from experiment.world.state import (
    ItemMode,
    ItemState,
    WorldState,
    falling_position,
    grasp_offset,
    held_pose,
    release_item,
    shelf_item_state,
)


class FailureMode(StrEnum):
    """How an autonomous attempt fails (``Trial.failure_mode``; the module docstring)."""

    COLLISION = "collision"  # high complexity only: the arm hits an obstacle
    DROP = "drop"  # the item slips out of the gripper


@dataclass(frozen=True, eq=False)
class Attempt:
    """A planned autonomous attempt (times in s at animation speed 1).

    ``events`` maps "arm_start", "grasp", "collision" | "drop", "deposit" and
    "end" to their times. The trajectory samples are ``times`` (K,), ``base``
    (K, 3), ``joints`` (K, 4) and ``gripper`` (K,); ``grip`` is the item's pose
    in the palm frame while held (7,) and ``released`` the item as let go.
    """

    scene: Scene
    outcome: str  # "success" | "failure"
    failure_mode: FailureMode | None
    events: dict[str, float]
    times: list[float]
    base: np.ndarray
    joints: np.ndarray
    gripper: np.ndarray
    grip: tuple[float, ...]
    released: ItemState | None  # the item as let go (deposited or dropped)

    @property
    def duration(self) -> float:
        return self.times[-1]

    @property
    def grasp_time(self) -> float:
        return self.events["grasp"]

    @property
    def deposit_time(self) -> float | None:
        return self.events.get("deposit")

    @property
    def failure_time(self) -> float | None:
        return self.events.get(self.failure_mode) if self.failure_mode else None

    @property
    def arm_start_time(self) -> float:
        """When the base has parked and the arm starts moving."""
        return self.events["arm_start"]

    def state_at(self, t: float) -> WorldState:
        """The world at time t (clamped to [0, duration])."""
        t = min(max(float(t), 0.0), self.duration)
        i = bisect_right(self.times, t) - 1
        if i >= len(self.times) - 1:
            b, q, g = self.base[-1], self.joints[-1], float(self.gripper[-1])
        else:
            w = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
            b = self.base[i] + w * (self.base[i + 1] - self.base[i])
            q = self.joints[i] + w * (self.joints[i + 1] - self.joints[i])
            g = float(self.gripper[i] + w * (self.gripper[i + 1] - self.gripper[i]))
        base, joints = tuple(b.tolist()), tuple(q.tolist())
        return WorldState(t, base, joints, g, g, self._item_at(t, base, joints))

    def _item_at(self, t: float, base, joints) -> ItemState:
        if t < self.grasp_time:
            return shelf_item_state(self.scene)
        rel = self.released
        if rel is None or t < rel.since:
            pos, q = held_pose(base, joints, self.grip)
            return ItemState(ItemMode.GRASPED, pos, q, self.grasp_time, self.grip)
        return ItemState(rel.mode, falling_position(rel, t), rel.wxyz, rel.since, None,
                         rel.fall_from, rel.rest_z)


def _rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def choose_failure_mode(scene: Scene, rng: np.random.Generator) -> FailureMode:
    """A collision with probability P_COLLISION_HIGH in high complexity, else a drop."""
    u = rng.random()
    return FailureMode.COLLISION if scene.complexity == "high" and u < K.P_COLLISION_HIGH else FailureMode.DROP


def _approach_and_grasp(scene: Scene) -> tuple[Path, dict[str, float], tuple[float, ...]]:
    """Drive, approach, descend and close; returns the path, events and grip offset."""
    d = K.DURATIONS
    path = Path(scene.start, ready_joints(), K.GRIPPER_MAX)
    path.drive(scene.park, d["drive"])
    events = {"arm_start": path.now}
    grasp = scene.target.grasp_point()
    z_app = grasp[2] + K.PREGRASP_HEIGHT
    if scene.complexity == "high":
        z_app = max(z_app, transfer_height(scene))
    path.line((grasp[0], grasp[1], z_app), d["approach"])
    path.line(grasp, d["descend"])
    path.hold(d["close"], gripper=scene.target.width)
    events["grasp"] = path.now
    pts = arm_points(scene.park, path.q[-1])
    palm_q = quat_yaw_pitch(pts.psi, pts.pitches[2])
    return path, events, grasp_offset(pts.palm, palm_q, shelf_item_state(scene))


def _carry_to_bin(path: Path, scene: Scene) -> tuple[int, int]:
    """Lift, retract, swing and lower over the bin; returns the retract+swing sample range."""
    d = K.DURATIONS
    z = transfer_height(scene)
    grasp = scene.target.grasp_point()
    path.line((grasp[0], grasp[1], z), d["lift"])
    first = len(path.t)
    _, heading = radial(scene.park, grasp)
    z_swing = max(z, K.SWING_MIN_Z)
    path.line(radial_point(scene.park, K.RETRACT_RADIUS, heading, z_swing), d["retract"])
    target = bin_release_point(scene)
    _, bin_heading = radial(scene.park, target)
    path.joints_to(radial_point(scene.park, K.RETRACT_RADIUS, bin_heading, z_swing), d["swing"])
    last = len(path.t)
    path.line(target, d["to_bin"])
    return first, last


def _finish(scene, path, events, grip, outcome, mode, released) -> Attempt:
    events["end"] = path.now
    return Attempt(scene, outcome, mode, events, path.t, np.array(path.b), np.array(path.q),
                   np.array(path.g), grip, released)


def plan_attempt(scene: Scene, success: bool, rng=None, failure_mode: FailureMode | str | None = None) -> Attempt:
    """Plan the robot's autonomous attempt in ``scene``.

    ``rng`` (Generator, seed or None) picks the failure mode and the drop
    moment; ``failure_mode`` ("collision" | "drop") forces the mode of a
    failure ("collision" needs obstacles, i.e. high complexity).
    """
    gen = _rng(rng)
    chosen = None if success else (failure_mode or choose_failure_mode(scene, gen))
    if chosen is not None and chosen not in set(FailureMode):
        raise ValueError(f"failure_mode must be 'collision' or 'drop', got {chosen!r}")
    mode = None if chosen is None else FailureMode(chosen)
    if mode == FailureMode.COLLISION and not scene.obstacles:
        raise ValueError("a collision failure needs obstacles (high complexity)")
    path, events, grip = _approach_and_grasp(scene)
    if mode == FailureMode.COLLISION:
        return _plan_collision(scene, path, events, grip)
    first, last = _carry_to_bin(path, scene)
    if mode == FailureMode.DROP:
        return _plan_drop(scene, path, events, grip, first, last, gen)
    events["deposit"] = path.now
    held = _held_state(scene, path, len(path.t) - 1, grip)
    released = release_item(scene, scene.park, held, path.now)
    if released.mode != ItemMode.IN_BIN:
        raise RuntimeError("planned release point is not over the bin")
    path.hold(K.DURATIONS["release"], gripper=K.GRIPPER_MAX)
    path.line(np.add(bin_release_point(scene), (0.0, 0.0, K.SETTLE_RISE)), K.DURATIONS["settle"])
    return _finish(scene, path, events, grip, "success", None, released)


def _held_state(scene: Scene, path: Path, k: int, grip) -> ItemState:
    pos, q = held_pose(path.b[k], path.q[k], grip)
    return ItemState(ItemMode.GRASPED, pos, q, 0.0, grip)


def _plan_collision(scene: Scene, path: Path, events, grip) -> Attempt:
    grasp = scene.target.grasp_point()
    low = (grasp[0], grasp[1], grasp[2] + K.FAIL_LIFT)
    path.line(low, K.DURATIONS["fail_lift"])
    start = len(path.t)
    _, heading = radial(scene.park, grasp)
    path.line(radial_point(scene.park, K.FAIL_RETRACT_RADIUS, heading, low[2]),
              K.DURATIONS["fail_move"])
    for k in range(start, len(path.t)):
        item = _held_state(scene, path, k, grip)
        state = WorldState(path.t[k], tuple(path.b[k]), tuple(path.q[k]), path.g[k], path.g[k], item)
        if collisions(state, scene):
            path.truncate(k + 1)
            events["collision"] = path.now
            released = release_item(scene, scene.park, item, path.now + K.FAIL_RELEASE_DELAY)
            path.hold(K.DURATIONS["fail_hold"])
            return _finish(scene, path, events, grip, "failure", FailureMode.COLLISION, released)
    raise RuntimeError("the collision path did not hit anything")


def _plan_drop(scene: Scene, path: Path, events, grip, first: int, last: int,
               rng: np.random.Generator) -> Attempt:
    floor: list[ItemState] = []
    other: list[ItemState] = []
    for k in range(first, last):
        rel = release_item(scene, scene.park, _held_state(scene, path, k, grip), path.t[k])
        if rel.mode == ItemMode.IN_BIN:
            continue
        (floor if math.isclose(rel.rest_z, scene.target.height / 2) else other).append(rel)
    candidates = floor or other
    released = candidates[int(rng.integers(len(candidates)))]
    events["drop"] = released.since
    path.hold(K.DURATIONS["release"], gripper=K.GRIPPER_MAX)
    path.hold(K.DURATIONS["settle"])
    return _finish(scene, path, events, grip, "failure", FailureMode.DROP, released)
