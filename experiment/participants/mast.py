"""Where the arm turns about, as a person comes to know it from the poses the page shows.

The mast (the axis the arm turns about) is not sent: it is estimated from the TCP positions and joint angles seen,
by least squares over the arm's pose (the TCP lies in the vertical plane through the mast at heading
``base yaw + j1``, at a horizontal reach that is a sum of link projections).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np


def as_vector(value) -> np.ndarray:
    return np.asarray(value, dtype=float)


def wrap_angle(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def heading_of(world: Mapping[str, Any]) -> float:
    """The arm's heading (rad, world frame): base yaw + j1."""
    return float(world["base"][2]) + float(world["joints"][0])


class MastEstimate:
    """Where the mast axis is (world x, y), from the arm poses seen (least squares, see the module's docstring).

    Unknowns: mast x, y and the horizontal projections' lengths of the upper arm and forearm. Each pose
    seen gives tcp_xy = mast + (L2 cos q2 + L3 cos(q2 + q3)) (cos h, sin h) with h = base yaw + j1 (the
    tool points down, so it adds no reach). A weak prior (the base's origin, 0.5 m links) holds it
    while the poses seen are too alike.
    """

    PRIOR_WEIGHT = 0.03

    def __init__(self, base: Iterable[float]):
        base = list(base)
        self.prior = np.array([base[0], base[1], 0.5, 0.5])
        w2 = self.PRIOR_WEIGHT ** 2
        self.ata = np.eye(4) * w2
        self.atb = self.prior * w2
        self.last_joints: np.ndarray | None = None
        self.count = 0
        self._solution = self.prior.copy()

    def add(self, tcp: Iterable[float], world: Mapping[str, Any]) -> None:
        joints = as_vector(world["joints"])
        if self.last_joints is not None and float(np.abs(joints - self.last_joints).sum()) < 0.004:
            return
        self.last_joints = joints
        h = heading_of(world)
        c2, c3 = math.cos(joints[1]), math.cos(joints[1] + joints[2])
        tcp = list(tcp)
        for row, value in (((1.0, 0.0, math.cos(h) * c2, math.cos(h) * c3), tcp[0]),
                           ((0.0, 1.0, math.sin(h) * c2, math.sin(h) * c3), tcp[1])):
            r = np.array(row)
            self.ata += np.outer(r, r)
            self.atb += r * value
        self.count += 1
        self._solution = np.linalg.solve(self.ata, self.atb)

    @property
    def xy(self) -> np.ndarray:
        return self._solution[:2]

    def radial(self, point: Iterable[float]) -> tuple[float, float]:
        """(reach m, heading rad) of a world point about the estimated mast axis."""
        p = list(point)
        dx, dy = p[0] - self._solution[0], p[1] - self._solution[1]
        return math.hypot(dx, dy), math.atan2(dy, dx)
