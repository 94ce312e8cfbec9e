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
from experiment.world.geometry import Quat, Vec3, quat_yaw, quat_yaw_pitch

LOWER = np.array(K.JOINT_LOWER)
UPPER = np.array(K.JOINT_UPPER)
_LOWER, _UPPER = tuple(map(float, LOWER)), tuple(map(float, UPPER))


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


def _along(p: Vec3, length: float, cp: float, sp: float, pitch: float) -> Vec3:
    c = math.cos(pitch) * length
    return p[0] + c * cp, p[1] + c * sp, p[2] + math.sin(pitch) * length


def arm_points(base, joints) -> ArmPoints:
    """Forward kinematics of the key points for base (3,) and joints (4,)."""
    mx, my = mast_xy(base)
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
    return ArmPoints((mx, my, K.BASE_TOP), psi, shoulder, elbow, wrist, palm, tcp,
                     tool_x, (-sp, cp, 0.0), (a2, a3, a4))


def tcp_position(base, joints) -> np.ndarray:
    """World position (3,) of the tool centre point (between the fingertips)."""
    return np.array(arm_points(base, joints).tcp)


def finger_centers(pts: ArmPoints, opening: float) -> tuple[Vec3, Vec3]:
    """Centres (3,) of the left and right finger for a gap of ``opening`` m."""
    half = K.FINGER_LENGTH / 2
    off = opening / 2 + K.FINGER_RADIUS
    c = tuple(pts.palm[i] + half * pts.tool_x[i] for i in range(3))
    left = tuple(c[i] + off * pts.side_y[i] for i in range(3))
    right = tuple(c[i] - off * pts.side_y[i] for i in range(3))
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
    return np.array(_jacobian_rows(*(float(v) for v in joints), float(base_yaw)))


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
    q = [float(v) for v in joints]
    v = [float(x) for x in target_velocity]
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if n > K.MAX_EE_SPEED:
        v = [x * K.MAX_EE_SPEED / n for x in v]
    w = K.TOOL_PITCH_WEIGHT
    pitch_rate = min(1.0, max(-1.0, K.TOOL_PITCH_GAIN * (K.TOOL_PITCH - q[1] - q[2] - q[3])))
    jac = _jacobian_rows(*q, float(base_yaw)) + [[0.0, w, w, w]]
    task = v + [w * pitch_rate]
    lo, hi = K.JOINT_LOWER, K.JOINT_UPPER
    free = [True] * 4
    qdot = [0.0] * 4
    for _ in range(4):
        qdot = _dls(jac, task, free, qdot)
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


def _dls(jac: list[list[float]], task: list[float], free: list[bool],
         qdot: list[float]) -> list[float]:
    """Joint rates (4,) with jac (4x4) @ qdot ~= task (4,), DLS over the free joints.

    Locked joints keep their rate from ``qdot``; the free ones get
    J_f^T (J_f J_f^T + lambda^2 I)^-1 (task - J qdot_locked).
    """
    lk = [0.0 if f else r for f, r in zip(free, qdot)]
    jf = [[x if f else 0.0 for x, f in zip(row, free)] for row in jac]
    rhs = [t - (r[0] * lk[0] + r[1] * lk[1] + r[2] * lk[2] + r[3] * lk[3]) for t, r in zip(task, jac)]
    a = [[r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + r[3] * s[3] for s in jf] for r in jf]
    for i in range(4):
        a[i][i] += K.IK_DAMPING ** 2
    y0, y1, y2, y3 = _solve_spd(a, rhs)
    return [lk[i] + jf[0][i] * y0 + jf[1][i] * y1 + jf[2][i] * y2 + jf[3][i] * y3 for i in range(4)]


def _solve_spd(a: list[list[float]], b: list[float]) -> list[float]:
    """Solve a x = b (Gaussian elimination; a symmetric positive definite, no pivoting needed)."""
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
    if any(v < lo - 1e-9 or v > hi + 1e-9 for v, lo, hi in zip(q, _LOWER, _UPPER)):
        return None
    return np.array(q)


def radial(base, point) -> tuple[float, float]:
    """(radius m, heading rad) of a world point (3,) about the mast axis."""
    mx, my = mast_xy(base)
    dx, dy = float(point[0]) - mx, float(point[1]) - my
    return math.hypot(dx, dy), math.atan2(dy, dx)
