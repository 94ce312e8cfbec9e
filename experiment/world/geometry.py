"""Small geometry helpers: quaternions (w, x, y, z), boxes, point-box distances.

Quaternions are plain tuples of 4 floats (w, x, y, z) so that the per-frame
code (30 Hz for hundreds of sessions) avoids numpy's per-call overhead; the
vectorised collision code uses numpy arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
IDENTITY: Quat = (1.0, 0.0, 0.0, 0.0)


def vec3(values) -> Vec3:
    """Three numbers (a sequence, an iterable or a (3,) array) as a Vec3 of floats."""
    x, y, z = values
    return (float(x), float(y), float(z))


def quat(values) -> Quat:
    """Four numbers (w, x, y, z) as a Quat of floats."""
    w, x, y, z = values
    return (float(w), float(x), float(y), float(z))


@dataclass(frozen=True, eq=False)
class Box:
    """A primitive for rendering and collision checks.

    ``center`` (3,) and ``wxyz`` (4,) are in the parent frame: the world for
    ``scene_boxes``, the named robot/item frame for ``body_shapes``. ``size``
    (3,) holds full extents in metres; for ``shape == "cylinder"`` it is
    (diameter, diameter, height) with the axis along local z.
    ``color`` is RGB 0-255.
    """

    name: str
    center: np.ndarray
    size: np.ndarray
    color: tuple[int, int, int]
    shape: str = "box"
    wxyz: np.ndarray = field(default_factory=lambda: np.array(IDENTITY))

    @property
    def lo(self) -> np.ndarray:
        """Lower corner (3,) of the axis-aligned extent (ignores ``wxyz``)."""
        return self.center - self.size / 2

    @property
    def hi(self) -> np.ndarray:
        """Upper corner (3,) of the axis-aligned extent (ignores ``wxyz``)."""
        return self.center + self.size / 2


def box_from_bounds(name: str, lo, hi, color, shape: str = "box") -> Box:
    """A world-aligned ``Box`` from its lower and upper corners (3,) in metres."""
    lo_a, hi_a = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    return Box(name, (lo_a + hi_a) / 2, hi_a - lo_a, color, shape)


def quat_yaw(yaw: float) -> Quat:
    """Rotation about +z by ``yaw`` radians."""
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def quat_yaw_pitch(yaw: float, pitch: float) -> Quat:
    """Rz(yaw) * Ry(-pitch): local x points at elevation ``pitch`` (up > 0)."""
    ca, sa = math.cos(yaw / 2), math.sin(yaw / 2)
    cb, sb = math.cos(-pitch / 2), math.sin(-pitch / 2)
    return (ca * cb, -sa * sb, ca * sb, sa * cb)


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product a * b."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def quat_conj(q: Quat) -> Quat:
    """Inverse of a unit quaternion."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_rotate(q: Quat, v: Vec3) -> Vec3:
    """Rotate vector ``v`` (3,) by unit quaternion ``q``."""
    w, x, y, z = q
    vx, vy, vz = v
    tx = 2 * (y * vz - z * vy)
    ty = 2 * (z * vx - x * vz)
    tz = 2 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty,
            vy + w * ty + z * tx - x * tz,
            vz + w * tz + x * ty - y * tx)


def yaw_of(q: Quat) -> float:
    """Heading (rotation about z) of the local x axis of ``q``, radians."""
    w, x, y, z = q
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def compose(pos: Vec3, q: Quat, rel_pos: Vec3, rel_q: Quat) -> tuple[Vec3, Quat]:
    """World pose of a frame given in the frame (pos, q): (pos (3,), wxyz (4,))."""
    r = quat_rotate(q, rel_pos)
    return (pos[0] + r[0], pos[1] + r[1], pos[2] + r[2]), quat_mul(q, rel_q)


def relative(pos: Vec3, q: Quat, other_pos: Vec3, other_q: Quat) -> tuple[Vec3, Quat]:
    """Pose of (other_pos, other_q) expressed in the frame (pos, q)."""
    inv = quat_conj(q)
    d = (other_pos[0] - pos[0], other_pos[1] - pos[1], other_pos[2] - pos[2])
    return quat_rotate(inv, d), quat_mul(inv, other_q)


def min_jerk(s: float) -> float:
    """Minimum-jerk time scaling of s in [0, 1]: 10s^3 - 15s^4 + 6s^5."""
    s = min(max(float(s), 0.0), 1.0)
    return s * s * s * (10 - 15 * s + 6 * s * s)


def wrap_angle(a: float) -> float:
    """Angle wrapped into [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi
