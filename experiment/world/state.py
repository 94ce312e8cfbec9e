"""The dynamic world state (robot pose, gripper, target item) and item physics.

``WorldState`` is a frozen, slotted dataclass of floats and tuples: cheap to
copy with ``dataclasses.replace`` and safe to share between threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import (
    IDENTITY,
    Quat,
    Vec3,
    compose,
    quat,
    quat_rotate,
    quat_yaw,
    quat_yaw_pitch,
    relative,
    vec3,
    yaw_of,
)
from experiment.world.robot import arm_points
from experiment.world.scene import Scene, scene_boxes


class ItemMode(StrEnum):
    ON_SHELF = "on_shelf"
    GRASPED = "grasped"  # follows the palm
    IN_BIN = "in_bin"
    DROPPED = "dropped"  # falling or lying where it fell


@dataclass(frozen=True, slots=True)
class ItemState:
    """The target item: ``mode``, its current pose (position (3,) m, wxyz (4,)).

    ``since`` is the time (s) the mode began. While grasped, ``grip`` holds the
    item's pose in the palm frame (7,: position, wxyz). After a release
    (dropped or deposited) ``fall_from`` (3,) is where it was let go and
    ``rest_z`` the height of its centre once landed.
    """

    mode: ItemMode
    position: Vec3
    wxyz: Quat = IDENTITY
    since: float = 0.0
    grip: tuple[float, ...] | None = None
    fall_from: Vec3 | None = None
    rest_z: float = 0.0


@dataclass(frozen=True, slots=True)
class WorldState:
    """Robot and item at time ``t`` (s).

    ``base`` (x m, y m, yaw rad); ``joints`` (4,) rad; ``gripper`` the current
    finger gap (m); ``gripper_target`` the commanded gap (m).
    """

    t: float
    base: tuple[float, float, float]
    joints: tuple[float, float, float, float]
    gripper: float
    gripper_target: float
    item: ItemState


def as_joints(values) -> tuple[float, float, float, float]:
    """Four joint angles (rad; a sequence or a (4,) array) as floats, for ``WorldState.joints``."""
    q1, q2, q3, q4 = values
    return (float(q1), float(q2), float(q3), float(q4))


def shelf_item_state(scene: Scene, t: float = 0.0) -> ItemState:
    """The target item standing in its slot."""
    return ItemState(ItemMode.ON_SHELF, vec3(scene.target.center), IDENTITY, t)


def to_base_frame(base, p) -> tuple[float, float]:
    """(x, y) of world point p expressed in the base frame."""
    c, s = math.cos(base[2]), math.sin(base[2])
    dx, dy = p[0] - base[0], p[1] - base[1]
    return c * dx + s * dy, -s * dx + c * dy


def over_bin_opening(base, p, margin: float = 0.0) -> bool:
    """Whether world point p (3,) lies above the bin's inner opening (xy only)."""
    bx, by = to_base_frame(base, p)
    hx = K.BIN_SIZE[0] / 2 - K.BIN_WALL - margin
    hy = K.BIN_SIZE[1] / 2 - K.BIN_WALL - margin
    return abs(bx - K.BIN_XY[0]) <= hx and abs(by - K.BIN_XY[1]) <= hy


def _support_boxes(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """lo, hi (B, 3) of the static boxes, computed once per scene."""
    cached = scene.collision_cache.get("support")
    if cached is None:
        boxes = scene_boxes(scene)
        cached = scene.collision_cache.setdefault(
            "support", (np.array([b.lo for b in boxes]), np.array([b.hi for b in boxes])))
    return cached


def support_height(scene: Scene, base, p) -> float:
    """Height (m) of the highest surface under world point p (3,) and below it.

    Considers the floor, shelf parts, other items, obstacles, the robot base
    top and the bin floor (for points over the bin opening).
    """
    lo, hi = _support_boxes(scene)
    under = (lo[:, 0] <= p[0]) & (p[0] <= hi[:, 0]) & (lo[:, 1] <= p[1]) & (p[1] <= hi[:, 1])
    tops = hi[under & (hi[:, 2] <= p[2] + 1e-9), 2]
    z = max(0.0, float(tops.max())) if tops.size else 0.0
    bx, by = to_base_frame(base, p)
    if abs(bx) <= K.BASE_LENGTH / 2 and abs(by) <= K.BASE_WIDTH / 2 and K.BASE_TOP <= p[2]:
        z = max(z, K.BIN_FLOOR if over_bin_opening(base, p) else K.BASE_TOP)
    return z


def release_item(scene: Scene, base, item: ItemState, t: float) -> ItemState:
    """Let go of the held item at time t: it falls (mode DROPPED or IN_BIN)."""
    h = scene.target.height
    pos = vec3(item.position)
    in_bin = over_bin_opening(base, pos)
    if in_bin:  # falls inside: keep it clear of the walls
        pos = _inside_bin(base, pos, scene.target.width / 2)
    bottom = (pos[0], pos[1], pos[2] - h / 2)
    rest = (K.BIN_FLOOR if in_bin else support_height(scene, base, bottom)) + h / 2
    upright = quat_yaw(yaw_of(item.wxyz))
    mode = ItemMode.IN_BIN if in_bin else ItemMode.DROPPED
    return ItemState(mode, pos, upright, float(t), None, pos, min(float(rest), pos[2]))


def _inside_bin(base, p, half_width: float) -> Vec3:
    """p (3,) moved horizontally so that an item of this half width fits in the bin."""
    bx, by = to_base_frame(base, p)
    hx = max(0.0, K.BIN_SIZE[0] / 2 - K.BIN_WALL - half_width)
    hy = max(0.0, K.BIN_SIZE[1] / 2 - K.BIN_WALL - half_width)
    bx = min(max(bx, K.BIN_XY[0] - hx), K.BIN_XY[0] + hx)
    by = min(max(by, K.BIN_XY[1] - hy), K.BIN_XY[1] + hy)
    c, s = math.cos(base[2]), math.sin(base[2])
    return (base[0] + c * bx - s * by, base[1] + s * bx + c * by, p[2])


def falling_position(item: ItemState, t: float) -> Vec3:
    """Position (3,) at time t of an item released at ``item.since``."""
    assert item.fall_from is not None, "a released item"
    x, y, z0 = item.fall_from
    tau = max(0.0, t - item.since)
    return (x, y, max(item.rest_z, z0 - 0.5 * K.GRAVITY * tau * tau))


def grasp_offset(palm_pos: Vec3, palm_q: Quat, item: ItemState) -> tuple[float, ...]:
    """The item's pose (7,) in the palm frame, kept while it is held."""
    rel_p, rel_q = relative(palm_pos, palm_q, item.position, item.wxyz)
    return (*rel_p, *rel_q)


def held_pose(base, joints, grip: tuple[float, ...]) -> tuple[Vec3, Quat]:
    """World pose of a held item for the arm configuration (base (3,), joints (4,))."""
    pts = arm_points(base, joints)
    palm_q = quat_yaw_pitch(pts.psi, pts.pitches[2])
    return compose(pts.palm, palm_q, vec3(grip[:3]), quat(grip[3:]))


def item_axis(item: ItemState) -> Vec3:
    """World direction (3,) of the item's local z (its height axis)."""
    return quat_rotate(item.wxyz, (0.0, 0.0, 1.0))
