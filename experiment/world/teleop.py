"""Teleoperation: the participant moves the arm; the server owns the world.

A command is a mapping (e.g. decoded JSON) or a ``TeleopCommand`` with at
most one motion field and an optional gripper action:

- ``ee_velocity``: [vx, vy, vz] TCP velocity in the world frame, m/s
  (clamped to ``MAX_EE_SPEED``; the gripper is kept pointing down), or
- ``joint_velocity``: [w1, w2, w3, w4] joint rates, rad/s (each clamped to
  ``MAX_JOINT_SPEED``),
- ``gripper``: "open", "close" or "toggle".

Rules (``teleop_step``): closing with the TCP within the grasp radius
(``TeleopRules.grasp_radius``, default ``GRASP_RADIUS``) of the target's grasp
point (and the fingers open wider than the item) grasps it ("grasped"). With
``TeleopRules.align_radius`` > 0, closing farther away but within that radius
first moves the gripper onto the grasp point when the way there is free
("aligned"), then grasps: an assistance a study may switch on. Opening while holding it lets go: over the bin opening it
is "deposited" (teleoperation succeeded); elsewhere it is "dropped", falls onto
whatever is below, and ``RESPAWN_DELAY`` s later is put back in its shelf
slot ("item_reset") so that the participant can try again without a stuck
trial. A motion that would add a collision is refused: the arm stays and
"blocked" is reported (half the step is tried first); fingers that would
open or close into something stall the same way.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from experiment.world import constants as K
from experiment.world.collision import collides, collisions
from experiment.world.geometry import quat_yaw_pitch
from experiment.world.path import ready_joints
from experiment.world.robot import _LOWER, _UPPER, arm_points, ik_step_floats, solve_ik
from experiment.world.scene import Scene
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

GRIPPER_ACTIONS = ("open", "close", "toggle")
#: Longest step a held input is integrated in (s): motion is checked for contacts at this resolution.
HOLD_SUBSTEP = 1 / 30
COMMAND_FIELDS = ("ee_velocity", "joint_velocity", "gripper")


class WorldEvent(StrEnum):
    """What happened in the world during a step (the rules in the module docstring)."""

    ALIGNED = "aligned"
    GRASPED = "grasped"
    DEPOSITED = "deposited"
    DROPPED = "dropped"
    BLOCKED = "blocked"
    ITEM_RESET = "item_reset"


@dataclass(frozen=True, slots=True)
class TeleopRules:
    """How forgiving the grasp is (study configuration; the defaults are the task as designed)."""

    grasp_radius: float = K.GRASP_RADIUS
    align_radius: float = 0.0  # 0: no alignment assistance

    def __post_init__(self) -> None:
        if not (0 < self.grasp_radius <= 0.2 and 0 <= self.align_radius <= 0.3):
            raise ValueError("grasp_radius must be in (0, 0.2] m and align_radius in [0, 0.3] m")


DEFAULT_RULES = TeleopRules()


@dataclass(frozen=True, slots=True)
class TeleopCommand:
    """One teleoperation command (see the module docstring), validated when it is made: ValueError if bad.

    The vectors are kept as tuples of finite floats, so a command once made is never checked again.
    """

    ee_velocity: tuple[float, float, float] | None = None
    joint_velocity: tuple[float, float, float, float] | None = None
    gripper: str | None = None

    def __post_init__(self) -> None:
        if not _clean_vector(self.ee_velocity, 3):
            object.__setattr__(self, "ee_velocity", _vector(self.ee_velocity, 3, "ee_velocity"))
        if not _clean_vector(self.joint_velocity, 4):
            object.__setattr__(self, "joint_velocity", _vector(self.joint_velocity, 4, "joint_velocity"))
        if self.ee_velocity is not None and self.joint_velocity is not None:
            raise ValueError("give either ee_velocity or joint_velocity, not both")
        if self.gripper is not None and self.gripper not in GRIPPER_ACTIONS:
            raise ValueError(f"gripper must be one of {list(GRIPPER_ACTIONS)}, got {self.gripper!r}")

    @property
    def moves(self) -> bool:
        """Whether the command holds a motion (of the hand or of the joints)."""
        return self.ee_velocity is not None or self.joint_velocity is not None

    @property
    def motion(self) -> TeleopCommand:
        """The command without its gripper action: what stays held after the action was applied."""
        return self if self.gripper is None else TeleopCommand(self.ee_velocity, self.joint_velocity)

    def as_dict(self) -> dict[str, list[float] | str]:
        """The command's fields that are set (JSON: how the teleoperation log records an input)."""
        out: dict[str, list[float] | str] = {}
        if self.ee_velocity is not None:
            out["ee_velocity"] = list(self.ee_velocity)
        if self.joint_velocity is not None:
            out["joint_velocity"] = list(self.joint_velocity)
        if self.gripper is not None:
            out["gripper"] = self.gripper
        return out


def _vector(value, n: int, name: str) -> tuple[float, ...] | None:
    if value is None:
        return None
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, (Sequence, np.ndarray)):
        raise ValueError(f"{name} must be a list of {n} numbers, got {type(value).__name__}")
    if len(value) != n:
        raise ValueError(f"{name} must have {n} numbers, got {len(value)}")
    out = []
    for v in value:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f"{name} must contain numbers, got {v!r}")
        if not math.isfinite(float(v)):
            raise ValueError(f"{name} must contain finite numbers, got {v!r}")
        out.append(float(v))
    return tuple(out)


def _clean_vector(value, n: int) -> bool:
    """Whether ``_vector`` would return ``value`` unchanged (None or a tuple of n finite floats)."""
    if value is None:
        return True
    if type(value) is not tuple or len(value) != n:
        return False
    for v in value:
        if type(v) is not float or not math.isfinite(v):
            return False
    return True


def parse_command(command) -> TeleopCommand:
    """A command from a mapping (e.g. decoded JSON); a ``TeleopCommand`` is valid already. ValueError if bad."""
    if isinstance(command, TeleopCommand):
        return command
    if not isinstance(command, Mapping):
        raise ValueError(f"a command must be a mapping, got {type(command).__name__}")
    unknown = sorted(str(k) for k in command if k not in COMMAND_FIELDS)
    if unknown:
        raise ValueError(f"unknown command field(s) {unknown}; allowed: {list(COMMAND_FIELDS)}")
    return TeleopCommand(command.get("ee_velocity"), command.get("joint_velocity"), command.get("gripper"))


def _check_dt(dt) -> float:
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)):
        raise ValueError(f"dt must be a number of seconds, got {dt!r}")
    dt = float(dt)
    if not (math.isfinite(dt) and 0.0 < dt <= K.MAX_TELEOP_DT):
        raise ValueError(f"dt must be in (0, {K.MAX_TELEOP_DT}] s, got {dt}")
    return dt


def teleop_start_state(scene: Scene) -> WorldState:
    """Base parked in front of the shelf, arm in the ready pose, gripper open, item in its slot."""
    q = tuple(ready_joints().tolist())
    return WorldState(0.0, scene.park, q, K.GRIPPER_MAX, K.GRIPPER_MAX, shelf_item_state(scene))


def grasp_distance(state: WorldState, scene: Scene) -> float:
    """Distance (m) from the TCP to the target's grasp point."""
    return math.dist(arm_points(state.base, state.joints).tcp, scene.target.grasp_point())


def can_grasp(state: WorldState, scene: Scene, rules: TeleopRules = DEFAULT_RULES) -> bool:
    """Whether closing now would grasp the target (in its slot, TCP close, fingers open)."""
    if state.item.mode != ItemMode.ON_SHELF or state.gripper < scene.target.width:
        return False
    return grasp_distance(state, scene) <= rules.grasp_radius


def _aligned(state: WorldState, scene: Scene, rules: TeleopRules, events: list[WorldEvent]) -> WorldState:
    """``state`` with the gripper moved onto the grasp point, when the assistance allows it and nothing is hit."""
    if (rules.align_radius <= 0 or state.item.mode != ItemMode.ON_SHELF or state.gripper < scene.target.width
            or not rules.grasp_radius < grasp_distance(state, scene) <= rules.align_radius):
        return state
    joints = solve_ik(state.base, scene.target.grasp_point())
    if joints is None:
        return state
    candidate = _with_joints(state, tuple(joints.tolist()))
    if _adds_contact(state, scene, candidate, []):
        return state
    events.append(WorldEvent.ALIGNED)
    return candidate


def _gripper_action(state: WorldState, scene: Scene, action: str | None, rules: TeleopRules,
                    events: list[WorldEvent]) -> tuple[WorldState, float, ItemState]:
    """The state (aligned by the assistance), new gripper target (m) and item after a command's gripper part."""
    target, item = state.gripper_target, state.item
    if action is None:
        return state, target, item
    # a held item keeps the fingers at its width, which may be more than half open: toggle then releases
    close = action == "close" or (action == "toggle" and item.mode != ItemMode.GRASPED and target > K.GRIPPER_MAX / 2)
    if close:
        state = _aligned(state, scene, rules, events)
        if can_grasp(state, scene, rules):
            pts = arm_points(state.base, state.joints)
            grip = grasp_offset(pts.palm, quat_yaw_pitch(pts.psi, pts.pitches[2]), item)
            events.append(WorldEvent.GRASPED)
            return state, scene.target.width, replace(item, mode=ItemMode.GRASPED, since=state.t, grip=grip)
        return state, (target if item.mode == ItemMode.GRASPED else 0.0), item
    if item.mode == ItemMode.GRASPED:
        item = release_item(scene, state.base, item, state.t)
        events.append(WorldEvent.DEPOSITED if item.mode == ItemMode.IN_BIN else WorldEvent.DROPPED)
    return state, K.GRIPPER_MAX, item


def _held_item(item: ItemState, base, joints) -> ItemState:
    """The grasped ``item`` following the palm of the arm at (base, joints)."""
    assert item.grip is not None, "a grasped item"
    pos, q = held_pose(base, joints, item.grip)
    return ItemState(item.mode, pos, q, item.since, item.grip, item.fall_from, item.rest_z)


def _with_joints(state: WorldState, joints: tuple) -> WorldState:
    """``state`` with other joints (and the held item following the palm)."""
    item = state.item
    if item.mode == ItemMode.GRASPED:
        item = _held_item(item, state.base, joints)
    return WorldState(state.t, state.base, joints, state.gripper, state.gripper_target, item)


def _target_joints(state: WorldState, cmd: TeleopCommand, dt: float) -> tuple | None:
    """Joints (4 floats) the command asks for after dt, within limits; None without a motion.

    Plain floats (the same operations as with arrays: ``np.clip`` is max then min element-wise)."""
    if cmd.ee_velocity is not None:
        return tuple(ik_step_floats(state.joints, _within_workspace(state, cmd.ee_velocity), dt,
                                    base_yaw=float(state.base[2])))
    if cmd.joint_velocity is not None:
        m = K.MAX_JOINT_SPEED
        return tuple(min(max(float(q) + min(max(w, -m), m) * dt, lo), hi)
                     for q, w, lo, hi in zip(state.joints, cmd.joint_velocity, _LOWER, _UPPER, strict=True))
    return None


def _within_workspace(state: WorldState, velocity) -> tuple[float, float, float]:
    """``velocity`` without the parts that would take the TCP above ``TCP_MAX_Z`` or beyond ``TCP_MAX_REACH``."""
    vx, vy, vz = map(float, velocity)
    pts = arm_points(state.base, state.joints)
    if pts.tcp[2] >= K.TCP_MAX_Z and vz > 0:
        vz = 0.0
    mx, my = pts.mast[0], pts.mast[1]  # mast_xy(state.base)
    dx, dy = pts.tcp[0] - mx, pts.tcp[1] - my
    rho = math.hypot(dx, dy)
    if rho >= K.TCP_MAX_REACH:
        outward = (vx * dx + vy * dy) / rho
        if outward > 0:  # keep the sideways part, drop the outward one
            vx, vy = vx - outward * dx / rho, vy - outward * dy / rho
    return vx, vy, vz


def _adds_contact(state: WorldState, scene: Scene, candidate: WorldState, known: list) -> bool:
    """Whether ``candidate`` has a contact that ``state`` does not (``known`` caches the latter)."""
    if not collides(candidate, scene):
        return False
    if not known:
        known.append(set(collisions(state, scene)))
    if not known[0]:
        return True
    return not set(collisions(candidate, scene)) <= known[0]  # leaving or sliding along an existing contact is fine


def _move(state: WorldState, scene: Scene, cmd: TeleopCommand, dt: float, events: list[WorldEvent]) -> tuple:
    """Joints (4,) after the motion part of a command, refusing motions that add contacts, and the state
    tried with them (None when the arm stays)."""
    goal = _target_joints(state, cmd, dt)
    if goal is None:
        return state.joints, None
    known: list = []
    for frac in (1.0, 0.5):
        joints = goal if frac == 1.0 else tuple(s + frac * (g - s)
                                                for s, g in zip(map(float, state.joints), goal, strict=True))
        candidate = _with_joints(state, joints)
        if not _adds_contact(state, scene, candidate, known):
            return joints, candidate
    events.append(WorldEvent.BLOCKED)
    return state.joints, None


def _move_fingers(state: WorldState, scene: Scene, target: float, dt: float,
                  events: list[WorldEvent]) -> float:
    """Finger gap (m) after dt, moving towards ``target``; stalls (``blocked``) on a new contact."""
    step = K.GRIPPER_SPEED * dt
    gap = min(max(target, state.gripper - step), state.gripper + step)
    if gap != state.gripper and _adds_contact(
            state, scene, WorldState(state.t, state.base, state.joints, gap, state.gripper_target, state.item), []):
        events.append(WorldEvent.BLOCKED)
        return state.gripper
    return gap


def _advance_item(item: ItemState, scene: Scene, base, joints, t: float, events: list[WorldEvent]) -> ItemState:
    """The item at time t (the arm at base, joints): following the palm, falling, or back in its slot
    after a drop."""
    if item.mode == ItemMode.GRASPED:
        return _held_item(item, base, joints)
    if item.mode == ItemMode.DROPPED and t - item.since >= K.RESPAWN_DELAY:
        events.append(WorldEvent.ITEM_RESET)
        return shelf_item_state(scene, t)
    if item.mode in (ItemMode.DROPPED, ItemMode.IN_BIN):
        return ItemState(item.mode, falling_position(item, t), item.wxyz, item.since, item.grip, item.fall_from,
                         item.rest_z)
    return item


def teleop_step(state: WorldState, scene: Scene, command, dt: float, rules: TeleopRules = DEFAULT_RULES
                ) -> tuple[WorldState, tuple[WorldEvent, ...]]:
    """Advance the world by dt s under a participant's command.

    Returns the new state and the events of this step, a tuple of
    ``WorldEvent``s.
    Raises ValueError for an invalid command or dt.
    """
    return _step(state, scene, parse_command(command), _check_dt(dt), rules)


def _step(state: WorldState, scene: Scene, cmd: TeleopCommand, dt: float, rules: TeleopRules
          ) -> tuple[WorldState, tuple[WorldEvent, ...]]:
    """``teleop_step`` for a validated command and dt (states built directly: ``replace`` costs ~8 us a call,
    and the server's clock runs this for every teleoperated arm 30 times a second)."""
    events: list[WorldEvent] = []
    if cmd.gripper is not None:
        state, gripper_target, item = _gripper_action(state, scene, cmd.gripper, rules, events)
        state = WorldState(state.t, state.base, state.joints, state.gripper, gripper_target, item)
    else:
        gripper_target, item = state.gripper_target, state.item
    gripper = _move_fingers(state, scene, gripper_target, dt, events)
    if gripper is not state.gripper:
        state = WorldState(state.t, state.base, state.joints, gripper, gripper_target, item)
    joints, moved = _move(state, scene, cmd, dt, events)
    t = state.t + dt
    if moved is not None and item.mode == ItemMode.GRASPED:
        item = moved.item  # the held item at these joints, as _advance_item would compute it again
    else:
        item = _advance_item(item, scene, state.base, joints, t, events)
    return WorldState(t, state.base, joints, gripper, gripper_target, item), tuple(dict.fromkeys(events))


def hold_command(state: WorldState, scene: Scene, command: TeleopCommand, duration: float,
                 rules: TeleopRules = DEFAULT_RULES) -> tuple[WorldState, tuple[WorldEvent, ...]]:
    """Advance the world by ``duration`` s with ``command`` held (its gripper action applied once, first).

    The server's clock calls this with the time since it last advanced the arm: how far the arm moves
    depends on how long an input is held, never on how many messages carried it.
    """
    events: list[WorldEvent] = []
    remaining = float(duration)
    while remaining > 1e-9:
        dt = min(remaining, HOLD_SUBSTEP)  # a float in (0, HOLD_SUBSTEP]: what _check_dt accepts
        state, step_events = _step(state, scene, command, dt, rules)
        events.extend(step_events)
        remaining -= dt
        command = command.motion  # an action happens once, not once per sub-step
    return state, tuple(dict.fromkeys(events))


def settling(state: WorldState) -> bool:
    """Whether the world changes with no input: fingers moving, an item falling or waiting to return."""
    item = state.item
    return (abs(state.gripper - state.gripper_target) > 1e-9 or item.mode == ItemMode.DROPPED
            or (item.mode == ItemMode.IN_BIN and item.position[2] > item.rest_z + 1e-9))


@dataclass(frozen=True, slots=True)
class HeldMove:
    """One stretch of an advance: ``command`` held for ``duration`` simulated seconds; with ``if_settling``, only
    when the world changes on its own at that point (after a dead-man stop, or with nothing held)."""

    command: TeleopCommand
    duration: float
    if_settling: bool = False


def hold_moves(state: WorldState, scene: Scene, moves: Sequence[HeldMove], rules: TeleopRules = DEFAULT_RULES
               ) -> list[tuple[WorldState, tuple[WorldEvent, ...]] | None]:
    """``hold_command`` for each move in turn, from ``state``: each move's (state, events), None for a move skipped
    (``if_settling`` with nothing settling). Pure: the server runs it in a helper process for many arms at once."""
    out: list[tuple[WorldState, tuple[WorldEvent, ...]] | None] = []
    for move in moves:
        if move.if_settling and not settling(state):
            out.append(None)
            continue
        state, events = hold_command(state, scene, move.command, move.duration, rules)
        out.append((state, events))
    return out
