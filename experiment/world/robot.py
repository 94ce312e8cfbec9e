"""The mobile manipulator: forward kinematics, Jacobian and inverse kinematics.

Base pose ``base = (x, y, yaw)`` on the floor (m, m, rad). Arm joints
``q = (q1, q2, q3, q4)``: q1 yaw about the mast axis, q2 shoulder pitch, q3
elbow pitch, q4 wrist pitch (rad; pitch > 0 raises the next link). The
shoulder sits on the yaw axis, so the arm moves in one vertical plane at
heading ``psi = yaw + q1``; link directions in that plane have elevations
``q2``, ``q2 + q3`` and ``q2 + q3 + q4`` (the tool pitch). Link frames have
x along the link, y horizontal (to the left of the arm plane).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import Quat, Vec3, quat_yaw, quat_yaw_pitch, vec3

LOWER = np.array(K.JOINT_LOWER)
UPPER = np.array(K.JOINT_UPPER)
_LOWER, _UPPER = tuple(map(float, LOWER)), tuple(map(float, UPPER))
_MAST_X, _MAST_Y = K.MAST_XY
_UPPER_ARM, _FOREARM, _WRIST_LINK, _TCP_OFFSET = K.UPPER_ARM, K.FOREARM, K.WRIST_LINK, K.TCP_OFFSET
_SHOULDER_Z, _BASE_TOP = K.SHOULDER_Z, K.BASE_TOP
_DAMPING2 = K.IK_DAMPING ** 2


class ArmPoints(NamedTuple):
    """Key points (3-tuples, m) and angles (rad) of one arm configuration."""

    mast: Vec3  # mast axis at the base top
    psi: float  # heading of the arm plane
    shoulder: Vec3
    elbow: Vec3
    wrist: Vec3
    palm: Vec3
    tcp: Vec3
    tool_x: Vec3  # unit tool axis (palm -> TCP)
    side_y: Vec3  # unit horizontal axis across the gripper
    pitches: tuple[float, float, float]  # elevations of upper arm, forearm, tool


def mast_xy(base) -> tuple[float, float]:
    """World (x, y) of the mast axis for base pose (3,)."""
    x, y, yaw = base
    c, s = math.cos(yaw), math.sin(yaw)
    return x + c * K.MAST_XY[0] - s * K.MAST_XY[1], y + s * K.MAST_XY[0] + c * K.MAST_XY[1]


#: The last few ``arm_points`` results for (base, joints) tuples, by identity, newest first: a teleoperation
#: substep asks for the points of the same poses several times (the state's, then the candidate's for the
#: held item and for the collision check, which is the next substep's state). Replaced by single
#: assignments (consistent for other threads); only tuples (immutable) are kept.
_recent_points: tuple = ()


def arm_points(base, joints) -> ArmPoints:
    """Forward kinematics of the key points for base (3,) and joints (4,)."""
    global _recent_points
    for b, q, pts in _recent_points:
        if q is joints and b is base:
            return pts
    pts = _arm_points(base, joints)
    if type(joints) is tuple and type(base) is tuple:
        _recent_points = ((base, joints, pts), *_recent_points[:2])
    return pts


def _arm_points(base, joints) -> ArmPoints:
    # ``mast_xy`` and ``_along`` inlined (the same operations in the same order)
    x, y, yaw = base
    c, s = math.cos(yaw), math.sin(yaw)
    mx, my = x + c * _MAST_X - s * _MAST_Y, y + s * _MAST_X + c * _MAST_Y
    q1, q2, q3, q4 = map(float, joints)
    psi = float(base[2]) + q1
    cp, sp = math.cos(psi), math.sin(psi)
    a3 = q2 + q3
    a4 = a3 + q4
    c = math.cos(q2) * _UPPER_ARM
    ex, ey, ez = mx + c * cp, my + c * sp, _SHOULDER_Z + math.sin(q2) * _UPPER_ARM
    c = math.cos(a3) * _FOREARM
    wx, wy, wz = ex + c * cp, ey + c * sp, ez + math.sin(a3) * _FOREARM
    c4, s4 = math.cos(a4), math.sin(a4)
    c = c4 * _WRIST_LINK
    px, py, pz = wx + c * cp, wy + c * sp, wz + s4 * _WRIST_LINK
    c = c4 * _TCP_OFFSET
    return ArmPoints((mx, my, _BASE_TOP), psi, (mx, my, _SHOULDER_Z), (ex, ey, ez), (wx, wy, wz),
                     (px, py, pz), (px + c * cp, py + c * sp, pz + s4 * _TCP_OFFSET),
                     (c4 * cp, c4 * sp, s4), (-sp, cp, 0.0), (q2, a3, a4))


def tcp_position(base, joints) -> np.ndarray:
    """World position (3,) of the tool centre point (between the fingertips)."""
    return np.array(arm_points(base, joints).tcp)


def finger_centers(pts: ArmPoints, opening: float) -> tuple[Vec3, Vec3]:
    """Centres (3,) of the left and right finger for a gap of ``opening`` m."""
    half = K.FINGER_LENGTH / 2
    off = opening / 2 + K.FINGER_RADIUS
    c = tuple(pts.palm[i] + half * pts.tool_x[i] for i in range(3))
    left = vec3(c[i] + off * pts.side_y[i] for i in range(3))
    right = vec3(c[i] - off * pts.side_y[i] for i in range(3))
    return left, right


def link_frames(base, joints, opening: float) -> dict[str, tuple[Vec3, Quat]]:
    """World pose (position (3,), wxyz (4,)) of every robot frame.

    Frames: ``/robot/base`` (floor, base heading), ``/robot/mast`` (mast foot
    on the base top), ``/robot/j1`` (mast top, arm heading), ``/robot/j2``..
    ``/robot/j4`` (at each pitch joint, x along its link), ``/robot/palm``
    and the two finger centres, all with x along the tool axis.
    """
    pts = arm_points(base, joints)
    a2, a3, a4 = pts.pitches
    tool_q = quat_yaw_pitch(pts.psi, a4)
    left, right = finger_centers(pts, opening)
    base_q = quat_yaw(float(base[2]))
    return {
        "/robot/base": ((float(base[0]), float(base[1]), 0.0), base_q),
        "/robot/mast": (pts.mast, base_q),
        "/robot/j1": ((pts.mast[0], pts.mast[1], K.MAST_TOP), quat_yaw(pts.psi)),
        "/robot/j2": (pts.shoulder, quat_yaw_pitch(pts.psi, a2)),
        "/robot/j3": (pts.elbow, quat_yaw_pitch(pts.psi, a3)),
        "/robot/j4": (pts.wrist, tool_q),
        "/robot/palm": (pts.palm, tool_q),
        "/robot/finger_left": (left, tool_q),
        "/robot/finger_right": (right, tool_q),
    }


def _jacobian_rows(q1: float, q2: float, q3: float, q4: float, base_yaw: float) -> list[list[float]]:
    """d(TCP)/d(joints) as 3 rows of 4 floats (m/rad), world frame."""
    psi = base_yaw + q1
    cp, sp = math.cos(psi), math.sin(psi)
    a2, a3, a4 = q2, q2 + q3, q2 + q3 + q4
    lt = K.TOOL_LENGTH
    rho = K.UPPER_ARM * math.cos(a2) + K.FOREARM * math.cos(a3) + lt * math.cos(a4)
    # (d rho, d z) for rotating joint k: contributions of links k.. end
    r4, z4 = -lt * math.sin(a4), lt * math.cos(a4)
    r3, z3 = r4 - K.FOREARM * math.sin(a3), z4 + K.FOREARM * math.cos(a3)
    r2, z2 = r3 - K.UPPER_ARM * math.sin(a2), z3 + K.UPPER_ARM * math.cos(a2)
    return [[-rho * sp, r2 * cp, r3 * cp, r4 * cp],
            [rho * cp, r2 * sp, r3 * sp, r4 * sp],
            [0.0, z2, z3, z4]]


def jacobian(joints, base_yaw: float = 0.0) -> np.ndarray:
    """d(TCP position)/d(joints): (3, 4) in m/rad, world frame."""
    q1, q2, q3, q4 = (float(v) for v in joints)
    return np.array(_jacobian_rows(q1, q2, q3, q4, float(base_yaw)))


def ik_step(joints, target_velocity, dt: float, base_yaw: float = 0.0) -> np.ndarray:
    """One damped-least-squares step of Cartesian velocity control.

    joints (4,) rad; target_velocity (3,) m/s of the TCP in the world frame
    (clamped to ``MAX_EE_SPEED``); dt s. A fourth, weighted task row holds the
    tool pitch at ``TOOL_PITCH`` (gripper pointing down). Joints that would
    leave their limits are locked at the limit and the rest re-solved; the
    joint rates are scaled together (not clipped one by one) so that none
    exceeds ``MAX_JOINT_SPEED`` and the direction of motion is kept.
    Returns the new joints (4,), within the limits. (Plain floats inside:
    for a 4x4 system numpy's call overhead costs more than the arithmetic.)
    """
    return np.array(ik_step_floats(joints, target_velocity, dt, base_yaw))


def ik_step_floats(joints, target_velocity, dt: float, base_yaw: float = 0.0) -> list[float]:
    """``ik_step`` returning a list of 4 floats (for callers that want no array)."""
    q = [float(v) for v in joints]
    q0, q1, q2, q3 = q
    v0, v1, v2 = map(float, target_velocity)
    n = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if n > K.MAX_EE_SPEED:
        v0, v1, v2 = v0 * K.MAX_EE_SPEED / n, v1 * K.MAX_EE_SPEED / n, v2 * K.MAX_EE_SPEED / n
    w = K.TOOL_PITCH_WEIGHT
    pitch_rate = min(1.0, max(-1.0, K.TOOL_PITCH_GAIN * (K.TOOL_PITCH - q1 - q2 - q3)))
    jac = _jacobian_rows(q0, q1, q2, q3, float(base_yaw))
    jac.append([0.0, w, w, w])
    task = [v0, v1, v2, w * pitch_rate]
    lo, hi = K.JOINT_LOWER, K.JOINT_UPPER
    lo0, lo1, lo2, lo3 = lo
    hi0, hi1, hi2, hi3 = hi
    free = [True] * 4
    qdot = [0.0] * 4
    mjs = K.MAX_JOINT_SPEED
    for _ in range(4):
        qdot = _dls(jac, task, free, qdot)
        d0, d1, d2, d3 = qdot
        peak = max(abs(d0), abs(d1), abs(d2), abs(d3))
        if peak > mjs:
            scale = mjs / peak
            d0, d1, d2, d3 = qdot = [d0 * scale, d1 * scale, d2 * scale, d3 * scale]
        if ((not free[0] or lo0 <= q0 + d0 * dt <= hi0) and (not free[1] or lo1 <= q1 + d1 * dt <= hi1)
                and (not free[2] or lo2 <= q2 + d2 * dt <= hi2) and (not free[3] or lo3 <= q3 + d3 * dt <= hi3)):
            break
        out = [free[i] and not lo[i] <= q[i] + qdot[i] * dt <= hi[i] for i in range(4)]
        for i in range(4):
            if out[i]:
                free[i] = False
                qdot[i] = (min(hi[i], max(lo[i], q[i] + qdot[i] * dt)) - q[i]) / dt
    d0, d1, d2, d3 = qdot
    return [min(hi0, max(lo0, q0 + d0 * dt)), min(hi1, max(lo1, q1 + d1 * dt)),
            min(hi2, max(lo2, q2 + d2 * dt)), min(hi3, max(lo3, q3 + d3 * dt))]


def _dls(jac: list[list[float]], task: list[float], free: list[bool],
         qdot: list[float]) -> list[float]:
    """Joint rates (4,) with jac (4x4) @ qdot ~= task (4,), DLS over the free joints.

    Locked joints keep their rate from ``qdot``; the free ones get
    J_f^T (J_f J_f^T + lambda^2 I)^-1 (task - J qdot_locked).
    Unrolled by hand (the operations and their order are those of the loops it replaced: products with
    the zeros of locked joints included, so that results stay the same to the last bit).
    """
    f0, f1, f2, f3 = free
    l0 = 0.0 if f0 else qdot[0]
    l1 = 0.0 if f1 else qdot[1]
    l2 = 0.0 if f2 else qdot[2]
    l3 = 0.0 if f3 else qdot[3]
    (j00, j01, j02, j03), (j10, j11, j12, j13), (j20, j21, j22, j23), (j30, j31, j32, j33) = jac
    b0 = task[0] - (j00 * l0 + j01 * l1 + j02 * l2 + j03 * l3)
    b1 = task[1] - (j10 * l0 + j11 * l1 + j12 * l2 + j13 * l3)
    b2 = task[2] - (j20 * l0 + j21 * l1 + j22 * l2 + j23 * l3)
    b3 = task[3] - (j30 * l0 + j31 * l1 + j32 * l2 + j33 * l3)
    if not f0:
        j00 = j10 = j20 = j30 = 0.0
    if not f1:
        j01 = j11 = j21 = j31 = 0.0
    if not f2:
        j02 = j12 = j22 = j32 = 0.0
    if not f3:
        j03 = j13 = j23 = j33 = 0.0
    d2 = _DAMPING2
    # a = J_f J_f^T + d2 I (symmetric: a[i][j] and a[j][i] are the same products)
    a00 = j00 * j00 + j01 * j01 + j02 * j02 + j03 * j03 + d2
    a01 = j00 * j10 + j01 * j11 + j02 * j12 + j03 * j13
    a02 = j00 * j20 + j01 * j21 + j02 * j22 + j03 * j23
    a03 = j00 * j30 + j01 * j31 + j02 * j32 + j03 * j33
    a11 = j10 * j10 + j11 * j11 + j12 * j12 + j13 * j13 + d2
    a12 = j10 * j20 + j11 * j21 + j12 * j22 + j13 * j23
    a13 = j10 * j30 + j11 * j31 + j12 * j32 + j13 * j33
    a22 = j20 * j20 + j21 * j21 + j22 * j22 + j23 * j23 + d2
    a23 = j20 * j30 + j21 * j31 + j22 * j32 + j23 * j33
    a33 = j30 * j30 + j31 * j31 + j32 * j32 + j33 * j33 + d2
    a10, a20, a30, a21, a31, a32 = a01, a02, a03, a12, a13, a23
    # Gaussian elimination without pivoting (a is symmetric positive definite), then back substitution
    f = a10 / a00
    a11 -= f * a01
    a12 -= f * a02
    a13 -= f * a03
    b1 -= f * b0
    f = a20 / a00
    a21 -= f * a01
    a22 -= f * a02
    a23 -= f * a03
    b2 -= f * b0
    f = a30 / a00
    a31 -= f * a01
    a32 -= f * a02
    a33 -= f * a03
    b3 -= f * b0
    f = a21 / a11
    a22 -= f * a12
    a23 -= f * a13
    b2 -= f * b1
    f = a31 / a11
    a32 -= f * a12
    a33 -= f * a13
    b3 -= f * b1
    f = a32 / a22
    a33 -= f * a23
    b3 -= f * b2
    y3 = b3 / a33
    y2 = (b2 - a23 * y3) / a22
    y1 = (b1 - a12 * y2 - a13 * y3) / a11
    y0 = (b0 - a01 * y1 - a02 * y2 - a03 * y3) / a00
    return [l0 + j00 * y0 + j10 * y1 + j20 * y2 + j30 * y3,
            l1 + j01 * y0 + j11 * y1 + j21 * y2 + j31 * y3,
            l2 + j02 * y0 + j12 * y1 + j22 * y2 + j32 * y3,
            l3 + j03 * y0 + j13 * y1 + j23 * y2 + j33 * y3]


def solve_ik(base, tcp, pitch: float = K.TOOL_PITCH) -> np.ndarray | None:
    """Closed-form elbow-up IK: joints (4,) putting the TCP at ``tcp`` (3,) m.

    The tool keeps elevation ``pitch`` (rad). Returns None if the point is out
    of reach or the solution breaks a joint limit.
    """
    mx, my = mast_xy(base)
    dx, dy = float(tcp[0]) - mx, float(tcp[1]) - my
    rho = math.hypot(dx, dy)
    psi = math.atan2(dy, dx) if rho > 1e-9 else float(base[2])
    q1 = (psi - float(base[2]) + math.pi) % (2 * math.pi) - math.pi
    wr = rho - K.TOOL_LENGTH * math.cos(pitch)
    wz = float(tcp[2]) - K.SHOULDER_Z - K.TOOL_LENGTH * math.sin(pitch)
    c3 = (wr * wr + wz * wz - K.UPPER_ARM ** 2 - K.FOREARM ** 2) / (2 * K.UPPER_ARM * K.FOREARM)
    if not -1.0 <= c3 <= 1.0:
        return None
    q3 = -math.acos(c3)
    q2 = math.atan2(wz, wr) - math.atan2(K.FOREARM * math.sin(q3), K.UPPER_ARM + K.FOREARM * math.cos(q3))
    q = (q1, q2, q3, pitch - q2 - q3)
    # Plain float comparisons: this runs hundreds of times per planned attempt, and numpy's per-call
    # overhead on four numbers dominated it.
    if any(v < lo - 1e-9 or v > hi + 1e-9 for v, lo, hi in zip(q, _LOWER, _UPPER, strict=True)):
        return None
    return np.array(q)


def radial(base, point) -> tuple[float, float]:
    """(radius m, heading rad) of a world point (3,) about the mast axis."""
    mx, my = mast_xy(base)
    dx, dy = float(point[0]) - mx, float(point[1]) - my
    return math.hypot(dx, dy), math.atan2(dy, dx)
