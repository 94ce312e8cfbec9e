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

Teleoperation checks poses a few millimetres apart, so the check keeps, per scene
(``scene.collision_cache``), what makes most of them cheap without changing any answer:

- temporal coherence (``surely_free``): the last pose checked in full and found free, with lower bounds
  of its capsules' clearances; a pose whose capsules moved less than that is free without a check;
- ``collides`` (only whether there is a contact) first tries the pairs found in contact last, and is
  done when a sphere of one is inside its box by more than rounding could change;
- the contacts of the last few poses found in contact (moving along a contact checks each pose twice).
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


#: Margin (m) kept in the temporal-coherence bounds for rounding: far above the ~1e-15 m of float error.
EPS = 1e-9
#: Poses in contact whose contacts ``collisions`` keeps (per scene, newest first).
RECENT = 3
_CATEGORIES = np.arange(4)[:, None, None]  # a pair's bound: 0 distance, 1-3 along x, y, z


def _cache(scene: Scene) -> dict:
    """Per-scene constants: boxes, capsule radii and sphere counts (computed once).

    It also holds what the checks keep (``ref``, ``likely``, ``recent``: see the module docstring), each
    replaced by one assignment (consistent for other threads).
    """
    cached = scene.collision_cache.get("static")
    if cached is not None:
        return cached
    boxes = scene_boxes(scene)
    item_r = _item_radius(scene)
    item_half = max(0.0, scene.target.height / 2 - item_r - K.ITEM_INSET)
    lengths = [K.UPPER_ARM, K.FOREARM, K.WRIST_LINK, 2 * K.PALM_HALF_WIDTH,
               K.FINGER_LENGTH, K.FINGER_LENGTH, 2 * item_half]
    radii = np.array([K.LINK_RADII[n] for n in CAPSULES[:-1]] + [item_r])
    counts = [max(2, math.ceil(length / r) + 1) for length, r in zip(lengths, radii, strict=True)]
    robot_lo, robot_hi = _robot_box_bounds()
    data = dict(
        lo=np.array([b.lo for b in boxes]), hi=np.array([b.hi for b in boxes]),
        robot_lo=robot_lo, robot_hi=robot_hi, n_world=len(boxes), item_half=item_half,
        radius=radii, r2=radii ** 2, n_points=counts,
        # sample positions along each capsule, padded with its end point to the longest count
        t_padded=np.array([np.pad(np.linspace(0.0, 1.0, n), (0, max(counts) - n), mode="edge") for n in counts]),
        capsule_of={n: np.arange(2 * n) % n for n in (6, 7)},
        names=[b.name for b in boxes] + list(ROBOT_BOXES), shifted=(None,) * 5,
        # for the Python loops of ``_surely_touches``: squared radii and sphere positions per capsule
        r2_list=(radii ** 2).tolist(), t_lists=[np.linspace(0.0, 1.0, n).tolist() for n in counts],
        ref=None, likely=(), recent=())  # what the checks keep: see the module docstring
    return scene.collision_cache.setdefault("static", data)  # atomic: safe across threads


def _ends(state: WorldState, item_half: float, with_item: bool) -> list[float]:
    """End points of the capsules (``CAPSULES``, the item's only ``with_item``) as one flat list of floats:
    capsule c's ends are items 6c..6c+2 and 6c+3..6c+5."""
    pts = arm_points(state.base, state.joints)
    (xx, xy, xz), (yx, yy, yz) = pts.tool_x, pts.side_y
    px, py, pz = pts.palm
    off = state.gripper / 2 + K.FINGER_RADIUS
    fl, pw = K.FINGER_LENGTH, K.PALM_HALF_WIDTH
    lx, ly, lz = px + off * yx, py + off * yy, pz + off * yz
    rx, ry, rz = px - off * yx, py - off * yy, pz - off * yz
    flat = [*pts.shoulder, *pts.elbow, *pts.elbow, *pts.wrist, *pts.wrist, px, py, pz,
            px - pw * yx, py - pw * yy, pz - pw * yz, px + pw * yx, py + pw * yy, pz + pw * yz,
            lx, ly, lz, lx + fl * xx, ly + fl * xy, lz + fl * xz,
            rx, ry, rz, rx + fl * xx, ry + fl * xy, rz + fl * xz]
    if with_item:
        cx, cy, cz = state.item.position
        ax, ay, az = item_axis(state.item)
        h = item_half
        flat += [cx - h * ax, cy - h * ay, cz - h * az, cx + h * ax, cy + h * ay, cz + h * az]
    return flat


def capsule_segments(state: WorldState, scene: Scene) -> np.ndarray:
    """Segment end points (7, 2, 3) of the capsules named in ``CAPSULES``, world m."""
    return np.array(_ends(state, _cache(scene)["item_half"], True)).reshape(7, 2, 3)


def collisions(state: WorldState, scene: Scene) -> list[str]:
    """Sorted, unique ``"<moving part> vs <thing>"`` strings for every contact.

    Moving parts: ``/robot/j2`` (upper arm), ``/robot/j3`` (forearm),
    ``/robot/j4`` (wrist), ``/robot/palm``, ``/robot/finger_left|right`` and
    ``/items/target`` while grasped. Things: the names of ``scene_boxes`` and
    ``/robot/base``, ``/robot/mast``, ``/robot/bin``. Empty list: no contact.

    A pose that ``surely_free`` proves free is not checked; a pose found in contact lately is not
    checked again (the module docstring).
    """
    return _contacts(state, scene, False)


def collides(state: WorldState, scene: Scene) -> bool:
    """``bool(collisions(state, scene))``, sooner in contact: the pairs (capsule, box) found in contact by
    the last check that found any are tried first, and a sphere of one well inside its box (by more than
    rounding could change) settles it."""
    return bool(_contacts(state, scene, True))


def _contacts(state: WorldState, scene: Scene, any_will_do: bool) -> list[str]:
    """``collisions``; with ``any_will_do`` maybe only ``[_SOME_CONTACT]`` instead of the contacts."""
    cache = _cache(scene)
    n_caps = 7 if state.item.mode == ItemMode.GRASPED else 6
    base = state.base
    flat = _ends(state, cache["item_half"], n_caps == 7)
    if _moved_less(cache["ref"], base, flat, n_caps):
        return []
    if any_will_do and cache["likely"] and _surely_touches(cache, base, flat, n_caps):
        return [_SOME_CONTACT]
    key = None
    if type(base) is tuple and type(state.joints) is tuple:  # (arrays do not compare as keys)
        item = state.item
        key = (base, state.joints, state.gripper, n_caps == 7 and (item.position, item.wxyz))
        for known, hits in cache["recent"]:
            if known == key:
                return list(hits)
    hits = _check(cache, base, flat, n_caps)
    if hits and key is not None:  # moving along a contact: this pose is the next step's state
        cache["recent"] = ((key, tuple(hits)), *cache["recent"][:RECENT - 1])
    return hits


_SOME_CONTACT = "(some contact)"


def _surely_touches(cache: dict, base, flat: list[float], n_caps: int) -> bool:
    """Whether a sphere of a pair in ``cache["likely"]`` is inside its box by a margin (its squared distance
    less than its squared radius by a factor 1 - 1e-9, far more than the rounding of the full check's
    arithmetic): then the full check reports the pair."""
    lo, hi = _box_lists(cache, base)
    r2, t_values = cache["r2_list"], cache["t_lists"]
    local = base[2] != 0.0  # the robot boxes are in the base frame: left to the full check
    n_world = cache["n_world"]
    for c, b in cache["likely"]:
        if c >= n_caps or (local and b >= n_world):
            continue
        k = 6 * c
        x0, y0, z0, x1, y1, z1 = flat[k:k + 6]
        ex, ey, ez = x1 - x0, y1 - y0, z1 - z0
        lx, ly, lz = lo[b]
        hx, hy, hz = hi[b]
        inside = r2[c] * (1.0 - 1e-9)
        for t in t_values[c]:
            x, y, z = x0 + t * ex, y0 + t * ey, z0 + t * ez
            dx = lx - x if x < lx else (x - hx if x > hx else 0.0)
            dy = ly - y if y < ly else (y - hy if y > hy else 0.0)
            dz = lz - z if z < lz else (z - hz if z > hz else 0.0)
            if dx * dx + dy * dy + dz * dz < inside:
                return True
    return False


def surely_free(state: WorldState, scene: Scene) -> bool:
    """Whether the reference pose kept in ``scene``'s cache proves ``state`` free of contacts.

    The reference is the last pose that ``collisions`` checked in full and found free, with lower bounds
    of the clearance (distance less radius) of each capsule's spheres from the boxes, per capsule: one
    for the boxes it is apart from as a whole (a distance), and one per axis x, y, z for the boxes from
    which its segment's bounding box is separated along that axis. Every sphere lies at a fixed fraction
    of its segment, so it moves at most as far as the farther of the segment's end points, and along an
    axis at most as far as they do along it. A capsule whose end points moved less than each of its
    bounds (less ``EPS``), in distance and along each axis, touches no box.
    """
    cache = _cache(scene)
    n_caps = 7 if state.item.mode == ItemMode.GRASPED else 6
    return _moved_less(cache["ref"], state.base, _ends(state, cache["item_half"], n_caps == 7), n_caps)


def _moved_less(ref, base, flat: list[float], n_caps: int) -> bool:
    """``surely_free`` for the capsules with end points ``flat``."""
    if ref is None:
        return False
    ref_base, ref_caps, ref_flat, limits = ref
    if ref_caps != n_caps or ref_base[0] != base[0] or ref_base[1] != base[1] or ref_base[2] != base[2]:
        return False
    k = 0
    for dist2, ax, ay, az in limits:  # per capsule: squared distance, then motion along x, y, z
        x0, y0, z0 = flat[k] - ref_flat[k], flat[k + 1] - ref_flat[k + 1], flat[k + 2] - ref_flat[k + 2]
        x1, y1, z1 = flat[k + 3] - ref_flat[k + 3], flat[k + 4] - ref_flat[k + 4], flat[k + 5] - ref_flat[k + 5]
        if (x0 * x0 + y0 * y0 + z0 * z0 >= dist2 or x1 * x1 + y1 * y1 + z1 * z1 >= dist2
                or not (-ax < x0 < ax and -ax < x1 < ax and -ay < y0 < ay and -ay < y1 < ay
                        and -az < z0 < az and -az < z1 < az)):
            return False
        k += 6
    return True


def _check(cache: dict, base, flat: list[float], n_caps: int) -> list[str]:
    """The contacts of the capsules with end points ``flat`` (broad and narrow phase, every pair).
    A free pose becomes the reference of ``surely_free``."""
    lo, hi = _boxes_in_base_frame(cache, base)
    segs = np.array(flat).reshape(n_caps, 2, 3)
    ends = segs
    rotated = base[2] != 0.0
    if rotated:
        ends = _to_base_frame(ends.reshape(-1, 3), base).reshape(-1, 2, 3)
        ends = np.concatenate([segs, ends])  # world copy for world boxes, local for robot boxes
    n_world = cache["n_world"]
    rad = cache["radius"][cache["capsule_of"][n_caps][:len(ends)]][:, None]
    emin, emax = ends.min(axis=1), ends.max(axis=1)
    cmin, cmax = emin - rad, emax + rad
    # broad phase: (capsule, box) pairs whose extents overlap; a base-frame copy meets the robot boxes only.
    # apart: per pair and axis, how far the extents are apart (> 0) along it. The rounded a - b is <= 0
    # exactly when a <= b: the test is lo <= cmax and hi >= cmin on every axis.
    apart = np.maximum(lo[None] - cmax[:, None], cmin[:, None] - hi[None])
    most = np.maximum(np.maximum(apart[:, :, 0], apart[:, :, 1]), apart[:, :, 2])
    over = most <= 0.0
    if rotated:
        over[:n_caps, n_world:] = False
        over[n_caps:, :n_world] = False
    ci, bi = np.nonzero(over)
    near = None
    if ci.size:
        # narrow phase, all pairs at once: spheres along each capsule (padded to one count) against its box
        caps = ci % n_caps
        p0 = ends[ci, 0]
        points = p0[:, None, :] + cache["t_padded"][caps][:, :, None] * (ends[ci, 1] - p0)[:, None, :]
        d = points - np.minimum(np.maximum(points, lo[bi][:, None, :]), hi[bi][:, None, :])
        near = np.einsum("kmj,kmj->km", d, d).min(axis=1)  # squared distance of the nearest sphere centre
        hit = near < cache["r2"][caps]  # some sphere overlaps the box
        if hit.any():
            names = cache["names"]
            pairs = tuple(zip(caps[hit].tolist(), bi[hit].tolist(), strict=True))
            cache["likely"] = pairs
            return sorted({f"{CAPSULES[c]} vs {names[b]}" for c, b in pairs})
    _set_reference(cache, base, flat, n_caps, rad, apart, most, ci, bi, near)
    return []


def _set_reference(cache, base, flat, n_caps, rad, apart, most, ci, bi, near) -> None:
    """Make the free pose with end points ``flat`` the reference of ``surely_free``, with bounds from
    ``_check``'s ``apart`` and ``most`` (extents grown by the radius ``rad``) and the narrow phase's squared
    distances ``near`` of the pairs (``ci``, ``bi``). (Rounding makes them off by ~1e-16 m: ``EPS`` covers it.)"""
    gap = np.maximum(apart + rad[:, :, None], 0.0)  # per axis: how far the segment's bounding box is apart
    dist2 = np.einsum("cbj,cbj->cb", gap, gap)  # squared distance of the bounding box from the box
    if near is not None:
        dist2[ci, bi] = near  # of the sphere centres, where the narrow phase computed it
    clear = np.sqrt(dist2) - rad  # lower bound of the clearance of the pair
    category = apart.argmax(axis=2) + 1  # the pair's axis of largest separation: 1, 2, 3 for x, y, z
    if len(apart) > n_caps:  # rotated base: robot boxes from the base-frame copy, and distances only
        n_world = cache["n_world"]
        clear = np.concatenate([clear[:n_caps, :n_world], clear[n_caps:, n_world:]], axis=1)
        category = np.zeros(clear.shape, dtype=int)
    else:
        # a pair is bounded along its axis of largest separation (the clearance along it: ``most``) when that
        # keeps at least half of its bound (motion along one axis is on average half the motion)
        axial = most >= 0.5 * clear
        category *= axial
        clear = np.where(axial, most, clear)
    bounds = np.where(category == _CATEGORIES, clear, np.inf).min(axis=2)  # (4, n_caps): per category
    bounds = np.maximum(bounds - EPS, 0.0)
    bounds[0] **= 2
    limits = tuple(map(tuple, bounds.T.tolist()))  # per capsule: squared distance, then along x, y, z
    cache["ref"] = ((float(base[0]), float(base[1]), float(base[2])), n_caps, flat, limits)


def _to_base_frame(points: np.ndarray, base) -> np.ndarray:
    """World points (N, 3) expressed in the frame of base pose (x, y, yaw)."""
    x, y, yaw = (float(v) for v in base)
    c, s = math.cos(yaw), math.sin(yaw)
    return (points - np.array([x, y, 0.0])) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _boxes_in_base_frame(cache: dict, base) -> tuple[np.ndarray, np.ndarray]:
    """World boxes then robot boxes, lo/hi (B, 3). With base yaw 0 the robot boxes
    are shifted into the world; otherwise they stay in the base frame. Cached per base."""
    return _shifted(cache, base)[1:3]


def _box_lists(cache: dict, base) -> tuple[list, list]:
    """``_boxes_in_base_frame`` as lists of (x, y, z) floats."""
    return _shifted(cache, base)[3:]


def _shifted(cache: dict, base) -> tuple:
    key = tuple(float(v) for v in base)
    shifted = cache["shifted"]
    if shifted[0] != key:
        shift = np.array([key[0], key[1], 0.0]) if key[2] == 0.0 else np.zeros(3)
        lo = np.vstack([cache["lo"], cache["robot_lo"] + shift])
        hi = np.vstack([cache["hi"], cache["robot_hi"] + shift])
        shifted = (key, lo, hi, [tuple(v) for v in lo.tolist()], [tuple(v) for v in hi.tolist()])
        cache["shifted"] = shifted  # one assignment: consistent for other threads
    return shifted
