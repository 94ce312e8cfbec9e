"""The teleoperation physics' shortcuts agree with the straightforward computations they replace.

- ``collisions`` (temporal coherence: ``surely_free``, contacts remembered) and ``collides`` (a pair
  lately in contact tried first) against the plain broad + narrow phase over every pair, on random walks
  of the arm near the shelf, the obstacles and the robot's own body (also with the item held, and with a
  turned base); every pose ``surely_free`` lets through must have no contact.
- ``arm_points`` (inlined, remembered per pose) and ``ik_step`` (unrolled) against the loops they
  replaced, to the last bit.
- ``teleop_step`` gives the same states and events with its per-scene caches as with none.
"""

import math
from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from experiment.world import (
    ItemMode,
    build_scene,
    collisions,
    robot,
    scripted_teleop_commands,
    solve_ik,
    teleop_start_state,
    teleop_step,
)
from experiment.world import constants as K
from experiment.world.collision import CAPSULES, _cache, collides, surely_free
from experiment.world.geometry import quat_yaw_pitch
from experiment.world.robot import arm_points, ik_step
from experiment.world.state import ItemState, grasp_offset, held_pose, item_axis

# --- the straightforward versions --------------------------------------------------------------------

def _along(p, length, cp, sp, pitch):
    c = math.cos(pitch) * length
    return p[0] + c * cp, p[1] + c * sp, p[2] + math.sin(pitch) * length


def plain_arm_points(base, joints):
    x, y, yaw = base
    c, s = math.cos(yaw), math.sin(yaw)
    mx, my = x + c * K.MAST_XY[0] - s * K.MAST_XY[1], y + s * K.MAST_XY[0] + c * K.MAST_XY[1]
    q1, q2, q3, q4 = (float(v) for v in joints)
    psi = float(base[2]) + q1
    cp, sp = math.cos(psi), math.sin(psi)
    a2, a3, a4 = q2, q2 + q3, q2 + q3 + q4
    shoulder = (mx, my, K.SHOULDER_Z)
    elbow = _along(shoulder, K.UPPER_ARM, cp, sp, a2)
    wrist = _along(elbow, K.FOREARM, cp, sp, a3)
    palm = _along(wrist, K.WRIST_LINK, cp, sp, a4)
    tcp = _along(palm, K.TCP_OFFSET, cp, sp, a4)
    tool_x = (math.cos(a4) * cp, math.cos(a4) * sp, math.sin(a4))
    return robot.ArmPoints((mx, my, K.BASE_TOP), psi, shoulder, elbow, wrist, palm, tcp,
                           tool_x, (-sp, cp, 0.0), (a2, a3, a4))


def _plain_solve_spd(a, b):
    n = len(b)
    for i in range(n):
        ai = a[i]
        for r in range(i + 1, n):
            ar = a[r]
            f = ar[i] / ai[i]
            for c in range(i, n):
                ar[c] -= f * ai[c]
            b[r] -= f * b[i]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):
        s = b[i]
        for c in range(i + 1, n):
            s -= a[i][c] * x[c]
        x[i] = s / a[i][i]
    return x


def _plain_dls(jac, task, free, qdot):
    lk = [0.0 if f else r for f, r in zip(free, qdot, strict=True)]
    jf = [[x if f else 0.0 for x, f in zip(row, free, strict=True)] for row in jac]
    rhs = [t - (r[0] * lk[0] + r[1] * lk[1] + r[2] * lk[2] + r[3] * lk[3]) for t, r in zip(task, jac, strict=True)]
    a = [[r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + r[3] * s[3] for s in jf] for r in jf]
    for i in range(4):
        a[i][i] += K.IK_DAMPING ** 2
    y0, y1, y2, y3 = _plain_solve_spd(a, rhs)
    return [lk[i] + jf[0][i] * y0 + jf[1][i] * y1 + jf[2][i] * y2 + jf[3][i] * y3 for i in range(4)]


def plain_ik_step(joints, target_velocity, dt, base_yaw=0.0):
    q = [float(v) for v in joints]
    v = [float(x) for x in target_velocity]
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if n > K.MAX_EE_SPEED:
        v = [x * K.MAX_EE_SPEED / n for x in v]
    w = K.TOOL_PITCH_WEIGHT
    pitch_rate = min(1.0, max(-1.0, K.TOOL_PITCH_GAIN * (K.TOOL_PITCH - q[1] - q[2] - q[3])))
    jac = robot._jacobian_rows(*q, float(base_yaw)) + [[0.0, w, w, w]]
    task = v + [w * pitch_rate]
    lo, hi = K.JOINT_LOWER, K.JOINT_UPPER
    free = [True] * 4
    qdot = [0.0] * 4
    for _ in range(4):
        qdot = _plain_dls(jac, task, free, qdot)
        peak = max(abs(x) for x in qdot)
        if peak > K.MAX_JOINT_SPEED:
            qdot = [x * (K.MAX_JOINT_SPEED / peak) for x in qdot]
        out = [free[i] and not lo[i] <= q[i] + qdot[i] * dt <= hi[i] for i in range(4)]
        if not any(out):
            break
        for i in range(4):
            if out[i]:
                free[i] = False
                qdot[i] = (min(hi[i], max(lo[i], q[i] + qdot[i] * dt)) - q[i]) / dt
    return np.array([min(hi[i], max(lo[i], q[i] + qdot[i] * dt)) for i in range(4)])


def plain_collisions(state, scene):
    """Every (capsule, box) pair through the broad phase, then the spheres of those that pass."""
    cache = _cache(scene)  # the static part: boxes, radii, sphere positions
    pts = plain_arm_points(state.base, state.joints)
    (xx, xy, xz), (yx, yy, yz) = pts.tool_x, pts.side_y
    px, py, pz = pts.palm
    off = state.gripper / 2 + K.FINGER_RADIUS
    fl, pw = K.FINGER_LENGTH, K.PALM_HALF_WIDTH
    lx, ly, lz = px + off * yx, py + off * yy, pz + off * yz
    rx, ry, rz = px - off * yx, py - off * yy, pz - off * yz
    cx, cy, cz = state.item.position
    ax, ay, az = item_axis(state.item)
    h = cache["item_half"]
    segs = np.array([*pts.shoulder, *pts.elbow, *pts.elbow, *pts.wrist, *pts.wrist, *pts.palm,
                     px - pw * yx, py - pw * yy, pz - pw * yz, px + pw * yx, py + pw * yy, pz + pw * yz,
                     lx, ly, lz, lx + fl * xx, ly + fl * xy, lz + fl * xz,
                     rx, ry, rz, rx + fl * xx, ry + fl * xy, rz + fl * xz,
                     cx - h * ax, cy - h * ay, cz - h * az, cx + h * ax, cy + h * ay, cz + h * az]).reshape(7, 2, 3)
    n_caps = 7 if state.item.mode == ItemMode.GRASPED else 6
    x, y, yaw = (float(v) for v in state.base)
    shift = np.array([x, y, 0.0]) if yaw == 0.0 else np.zeros(3)
    lo = np.vstack([cache["lo"], cache["robot_lo"] + shift])
    hi = np.vstack([cache["hi"], cache["robot_hi"] + shift])
    ends = segs[:n_caps]
    if yaw != 0.0:
        c, s = math.cos(yaw), math.sin(yaw)
        local = (ends.reshape(-1, 3) - np.array([x, y, 0.0])) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        ends = np.concatenate([segs[:n_caps], local.reshape(-1, 2, 3)])
    rad = cache["radius"][cache["capsule_of"][n_caps][:len(ends)]][:, None]
    cmin, cmax = ends.min(axis=1) - rad, ends.max(axis=1) + rad
    over = np.all((lo[None] <= cmax[:, None]) & (hi[None] >= cmin[:, None]), axis=2)
    if len(ends) > n_caps:
        over[:n_caps, cache["n_world"]:] = False
        over[n_caps:, :cache["n_world"]] = False
    ci, bi = np.nonzero(over)
    if ci.size == 0:
        return []
    caps = ci % n_caps
    p0 = ends[ci, 0]
    points = p0[:, None, :] + cache["t_padded"][caps][:, :, None] * (ends[ci, 1] - p0)[:, None, :]
    d = points - np.minimum(np.maximum(points, lo[bi][:, None, :]), hi[bi][:, None, :])
    hit = np.any(np.einsum("kmj,kmj->km", d, d) < cache["r2"][caps][:, None], axis=1)
    names = cache["names"]
    return sorted({f"{CAPSULES[c]} vs {names[b]}" for c, b in zip(caps[hit].tolist(), bi[hit].tolist(), strict=True)})


# --- collisions ----------------------------------------------------------------------------------------

def _near(scene, rng):
    """A TCP target near something to hit: an obstacle's top or side, a board, an item, the bin, the base."""
    target = scene.target.grasp_point()
    choices = [target + (0.0, 0.0, 0.05), target + (-0.1, 0.0, -0.02),
               (K.SHELF_FRONT_X + 0.03, target[1], K.LOWER_BOARD_TOP + 0.03),
               (K.SHELF_FRONT_X - 0.05, target[1] + 0.3, K.UPPER_BOARD_TOP + 0.02)]
    for ob in scene.obstacles:
        choices += [(ob.center[0], ob.center[1], ob.hi[2] + 0.025), (ob.lo[0] - 0.02, ob.center[1], ob.hi[2] - 0.05)]
    x, y, _ = scene.park
    choices += [(x - 0.12, y + 0.1, K.BIN_RIM + 0.04), (x + 0.35, y, K.BASE_TOP + 0.03)]
    return np.asarray(choices[int(rng.integers(len(choices)))], dtype=float) + rng.normal(0.0, 0.02, 3)


def _grasped_item(scene, base, joints):
    """The target item held as teleoperation holds it (grasped at the grasp pose, the base parked)."""
    grasp = solve_ik(scene.park, scene.target.grasp_point())
    pts = arm_points(scene.park, tuple(grasp.tolist()))
    on_shelf = ItemState(ItemMode.ON_SHELF, tuple(float(v) for v in scene.target.center))
    grip = grasp_offset(pts.palm, quat_yaw_pitch(pts.psi, pts.pitches[2]), on_shelf)
    pos, q = held_pose(base, joints, grip)
    return ItemState(ItemMode.GRASPED, pos, q, 0.0, grip)


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(["low", "high"]), st.integers(0, 30), st.integers(0, 2**32 - 1),
       st.sampled_from([0.0, 0.0, 0.4, -2.0]), st.booleans(), st.floats(0.002, 0.05))
def test_shortcuts_agree_with_the_full_check(complexity, seed, walk_seed, yaw, held, step):
    scene = build_scene(complexity, seed)
    rng = np.random.default_rng(walk_seed)
    base = (scene.park[0], scene.park[1], yaw) if yaw == 0.0 else (1.0, -0.3, yaw)
    start = teleop_start_state(scene)
    joints = solve_ik(base, _near(scene, rng))
    q = np.array(start.joints) if joints is None else joints
    gripper = float(rng.uniform(0.0, K.GRIPPER_MAX))
    seen = {"free": 0, "contact": 0, "skipped": 0}
    for k in range(40):  # a random walk: small joint and finger moves, now and then a jump
        q = q + rng.normal(0.0, step, 4) if k % 15 else q + rng.normal(0.0, 0.3, 4)
        q = np.clip(q, robot.LOWER, robot.UPPER)
        gripper = float(np.clip(gripper + rng.normal(0.0, 0.005), 0.0, K.GRIPPER_MAX))
        joints = tuple(q.tolist())
        item = _grasped_item(scene, base, joints) if held else start.item
        state = replace(start, base=base, joints=joints, gripper=gripper, item=item)
        expected = plain_collisions(state, scene)
        if surely_free(state, scene):
            assert expected == [], (k, expected)
            seen["skipped"] += 1
        assert collides(state, scene) == bool(expected)
        assert collisions(state, scene) == expected
        assert collides(state, scene) == bool(expected)
        seen["contact" if expected else "free"] += 1
    assert seen["free"] + seen["contact"] == 40


def test_the_walks_reach_contacts_and_skips():
    """The property above is not vacuous: near things the walks both touch and skip checks."""
    scene = build_scene("high", 3)
    rng = np.random.default_rng(0)
    counts = {"contact": 0, "skipped": 0}
    for _ in range(30):
        q = solve_ik(scene.park, _near(scene, rng))
        if q is None:
            continue
        for _ in range(10):
            q = np.clip(q + rng.normal(0.0, 0.01, 4), robot.LOWER, robot.UPPER)
            state = replace(teleop_start_state(scene), joints=tuple(q.tolist()))
            counts["skipped"] += surely_free(state, scene)
            hits = collisions(state, scene)
            assert hits == plain_collisions(state, scene)
            counts["contact"] += bool(hits)
    assert counts["contact"] >= 10 and counts["skipped"] >= 10, counts


def test_surely_free_needs_a_reference_of_the_same_kind():
    scene = build_scene("low", 5)
    state = teleop_start_state(scene)
    assert not surely_free(state, build_scene("low", 5))  # nothing checked yet
    assert collisions(state, scene) == [] and surely_free(state, scene)
    assert not surely_free(replace(state, base=(state.base[0] + 0.001, *state.base[1:])), scene)
    held = replace(state, item=_grasped_item(scene, state.base, state.joints))
    assert not surely_free(held, scene)  # the held item has no clearance yet
    x, y, _ = scene.park
    into_base = replace(state, joints=tuple(solve_ik(scene.park, (x + 0.3, y, K.BASE_TOP)).tolist()))
    assert plain_collisions(into_base, scene) and not surely_free(into_base, scene)


# --- kinematics --------------------------------------------------------------------------------------

joints_around_limits = st.tuples(*[st.floats(lo - 0.1, hi + 0.1)
                                   for lo, hi in zip(K.JOINT_LOWER, K.JOINT_UPPER, strict=True)])
velocities = st.tuples(*[st.floats(-1.0, 1.0)] * 3) | st.tuples(*[st.sampled_from([0.0, -0.0, 0.3, -0.3])] * 3)


@settings(max_examples=300, deadline=None)
@given(joints_around_limits, velocities, st.sampled_from([1 / 30, 1 / 60, 0.01, 0.2, 0.5]),
       st.floats(-math.pi, math.pi), st.tuples(st.floats(-2, 2), st.floats(-2, 2)))
def test_kinematics_match_the_loops_bit_for_bit(joints, velocity, dt, yaw, xy):
    base = (*xy, yaw)
    assert repr(arm_points(base, joints)) == repr(plain_arm_points(base, joints))
    assert repr(arm_points(base, joints)) == repr(plain_arm_points(base, joints))  # remembered
    assert ik_step(joints, velocity, dt, yaw).tobytes() == plain_ik_step(joints, velocity, dt, yaw).tobytes()


def test_arm_points_does_not_remember_arrays():
    q = np.array([0.1, 0.5, -1.0, -1.0])
    before = arm_points((0.0, 0.0, 0.0), q)
    q[0] = 0.7
    assert arm_points((0.0, 0.0, 0.0), q) == plain_arm_points((0.0, 0.0, 0.0), q) != before


# --- teleoperation --------------------------------------------------------------------------------------

def test_teleop_steps_are_the_same_without_caches():
    """The reference pose, the contacts kept and the likely pairs change no state or event."""
    for complexity, seed in (("high", 8), ("low", 2)):
        scene, fresh = build_scene(complexity, seed), build_scene(complexity, seed)
        state = teleop_start_state(scene)
        commands = [scripted_teleop_commands] * 150 + [{"ee_velocity": [0.0, 0.0, -0.3]}] * 20 + \
            [{"ee_velocity": [0.3, 0.1, 0.0]}] * 20 + [{"joint_velocity": [0.0, -1.0, 0.5, 0.0]}] * 20
        for k, command in enumerate(commands):
            if callable(command):
                command = command(state, scene)
            dt = 1 / 30 if k % 3 else 0.021
            expected = teleop_step(state, fresh, command, dt)
            fresh.collision_cache.clear()
            got = teleop_step(state, scene, command, dt)
            assert got == expected, k
            state = got[0]
