"""Collision checks: arm links and the held item as capsules vs axis-aligned boxes.

Boxes: the floor, shelf parts, the other items and the obstacles (world
coordinates) and the robot's body, mast and bin (base frame). A broad phase
keeps the (capsule, box) pairs whose bounding boxes overlap; for those (all
pairs in one array operation: the arm is checked at every small step of
teleoperation), the capsule (segment + radius) is sampled with spheres spaced
at most one radius apart and each sphere is tested against the box. The union of the spheres lies inside the capsule, so
a contact shallower than about 0.13 radius (<= 6 mm) can be missed; nothing
is reported that does not truly overlap. The target item is an obstacle
only while held (on the shelf the fingers straddle it; in the bin or on the
floor it is ignored). Arm links are not checked against each other.
"""

from __future__ import annotations

import math

import numpy as np

from experiment.world import constants as K
from experiment.world.robot import arm_points
from experiment.world.scene import Scene, scene_boxes
from experiment.world.state import ItemMode, WorldState, item_axis

ITEM = "/items/target"
CAPSULES = ("/robot/j2", "/robot/j3", "/robot/j4", "/robot/palm",
            "/robot/finger_left", "/robot/finger_right", ITEM)
ROBOT_BOXES = ("/robot/base", "/robot/mast", "/robot/bin")


def _robot_box_bounds() -> tuple[np.ndarray, np.ndarray]:
    """Lower/upper corners (3, 3) of the robot's body, mast and bin in the base frame."""
    mx, my = K.MAST_XY
    hm = K.MAST_WIDTH / 2
    bx, by = K.BIN_XY
    sx, sy, _ = K.BIN_SIZE
    lo = [(-K.BASE_LENGTH / 2, -K.BASE_WIDTH / 2, K.BASE_BOTTOM),
          (mx - hm, my - hm, K.BASE_TOP), (bx - sx / 2, by - sy / 2, K.BASE_TOP)]
    hi = [(K.BASE_LENGTH / 2, K.BASE_WIDTH / 2, K.BASE_TOP),
          (mx + hm, my + hm, K.MAST_TOP), (bx + sx / 2, by + sy / 2, K.BIN_RIM)]
    return np.array(lo), np.array(hi)


def _item_radius(scene: Scene) -> float:
    return scene.target.width / 2 - K.ITEM_INSET


def _cache(scene: Scene) -> dict:
    """Per-scene constants: boxes, capsule radii and sphere counts (computed once)."""
    cached = scene.collision_cache.get("static")
    if cached is not None:
        return cached
    boxes = scene_boxes(scene)
    item_r = _item_radius(scene)
    item_half = max(0.0, scene.target.height / 2 - item_r - K.ITEM_INSET)
    lengths = [K.UPPER_ARM, K.FOREARM, K.WRIST_LINK, 2 * K.PALM_HALF_WIDTH,
               K.FINGER_LENGTH, K.FINGER_LENGTH, 2 * item_half]
    radii = np.array([K.LINK_RADII[n] for n in CAPSULES[:-1]] + [item_r])
    counts = [max(2, math.ceil(length / r) + 1) for length, r in zip(lengths, radii)]
    robot_lo, robot_hi = _robot_box_bounds()
    data = dict(
        lo=np.array([b.lo for b in boxes]), hi=np.array([b.hi for b in boxes]),
        robot_lo=robot_lo, robot_hi=robot_hi, n_world=len(boxes), item_half=item_half,
        radius=radii, r2=radii ** 2, n_points=counts,
        # sample positions along each capsule, padded with its end point to the longest count
        t_padded=np.array([np.pad(np.linspace(0.0, 1.0, n), (0, max(counts) - n), mode="edge") for n in counts]),
        capsule_of={n: np.arange(2 * n) % n for n in (6, 7)},
        names=[b.name for b in boxes] + list(ROBOT_BOXES), shifted=(None, None, None))
    return scene.collision_cache.setdefault("static", data)  # atomic: safe across threads


def capsule_segments(state: WorldState, scene: Scene) -> np.ndarray:
    """Segment end points (7, 2, 3) of the capsules named in ``CAPSULES``, world m."""
    pts = arm_points(state.base, state.joints)
    (xx, xy, xz), (yx, yy, yz) = pts.tool_x, pts.side_y
    px, py, pz = pts.palm
    off = state.gripper / 2 + K.FINGER_RADIUS
    fl, pw = K.FINGER_LENGTH, K.PALM_HALF_WIDTH
    lx, ly, lz = px + off * yx, py + off * yy, pz + off * yz
    rx, ry, rz = px - off * yx, py - off * yy, pz - off * yz
    cx, cy, cz = state.item.position
    ax, ay, az = item_axis(state.item)
    h = _cache(scene)["item_half"]
    flat = [*pts.shoulder, *pts.elbow, *pts.elbow, *pts.wrist, *pts.wrist, *pts.palm,
            px - pw * yx, py - pw * yy, pz - pw * yz, px + pw * yx, py + pw * yy, pz + pw * yz,
            lx, ly, lz, lx + fl * xx, ly + fl * xy, lz + fl * xz,
            rx, ry, rz, rx + fl * xx, ry + fl * xy, rz + fl * xz,
            cx - h * ax, cy - h * ay, cz - h * az, cx + h * ax, cy + h * ay, cz + h * az]
    return np.array(flat).reshape(7, 2, 3)


def collisions(state: WorldState, scene: Scene) -> list[str]:
    """Sorted, unique ``"<moving part> vs <thing>"`` strings for every contact.

    Moving parts: ``/robot/j2`` (upper arm), ``/robot/j3`` (forearm),
    ``/robot/j4`` (wrist), ``/robot/palm``, ``/robot/finger_left|right`` and
    ``/items/target`` while grasped. Things: the names of ``scene_boxes`` and
    ``/robot/base``, ``/robot/mast``, ``/robot/bin``. Empty list: no contact.
    """
    cache = _cache(scene)
    segs = capsule_segments(state, scene)
    n_caps = 7 if state.item.mode == ItemMode.GRASPED else 6
    lo, hi = _boxes_in_base_frame(cache, state.base)
    ends = segs[:n_caps]
    if state.base[2] != 0.0:
        ends = _to_base_frame(ends.reshape(-1, 3), state.base).reshape(-1, 2, 3)
        ends = np.concatenate([segs[:n_caps], ends])  # world copy for world boxes, local for robot boxes
    rad = cache["radius"][cache["capsule_of"][n_caps][:len(ends)]][:, None]
    cmin, cmax = ends.min(axis=1) - rad, ends.max(axis=1) + rad
    # broad phase: (capsule, box) pairs whose extents overlap; a base-frame copy meets the robot boxes only
    over = np.all((lo[None] <= cmax[:, None]) & (hi[None] >= cmin[:, None]), axis=2)
    if len(ends) > n_caps:
        over[:n_caps, cache["n_world"]:] = False
        over[n_caps:, :cache["n_world"]] = False
    ci, bi = np.nonzero(over)
    if ci.size == 0:
        return []
    # narrow phase, all pairs at once: spheres along each capsule (padded to one count) against its box
    caps = ci % n_caps
    p0 = ends[ci, 0]
    points = p0[:, None, :] + cache["t_padded"][caps][:, :, None] * (ends[ci, 1] - p0)[:, None, :]
    d = points - np.minimum(np.maximum(points, lo[bi][:, None, :]), hi[bi][:, None, :])
    hit = np.any(np.einsum("kmj,kmj->km", d, d) < cache["r2"][caps][:, None], axis=1)
    names = cache["names"]
    return sorted({f"{CAPSULES[c]} vs {names[b]}" for c, b in zip(caps[hit].tolist(), bi[hit].tolist())})


def _to_base_frame(points: np.ndarray, base) -> np.ndarray:
    """World points (N, 3) expressed in the frame of base pose (x, y, yaw)."""
    x, y, yaw = (float(v) for v in base)
    c, s = math.cos(yaw), math.sin(yaw)
    return (points - np.array([x, y, 0.0])) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _boxes_in_base_frame(cache: dict, base) -> tuple[np.ndarray, np.ndarray]:
    """World boxes then robot boxes, lo/hi (B, 3). With base yaw 0 the robot boxes
    are shifted into the world; otherwise they stay in the base frame. Cached per base."""
    key = tuple(float(v) for v in base)
    cached_key, lo, hi = cache["shifted"]
    if cached_key != key:
        shift = np.array([key[0], key[1], 0.0]) if key[2] == 0.0 else np.zeros(3)
        lo = np.vstack([cache["lo"], cache["robot_lo"] + shift])
        hi = np.vstack([cache["hi"], cache["robot_hi"] + shift])
        cache["shifted"] = (key, lo, hi)  # one assignment: consistent for other threads
    return lo, hi
