"""Trajectory building blocks for planned motions (used by ``attempt``).

A ``Path`` is a list of samples at ``SAMPLE_RATE``: time (s), base pose
(3,), joints (4,), gripper gap (m). Segments use minimum-jerk timing.
"""

from __future__ import annotations

import math

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import min_jerk
from experiment.world.robot import mast_xy, solve_ik, tcp_position
from experiment.world.scene import Scene


def ready_joints() -> np.ndarray:
    """Joints (4,) of the ready pose: TCP at ``READY_TCP`` in front of the mast, tool down."""
    rho, z = K.READY_TCP
    q = solve_ik((0.0, 0.0, 0.0), (K.MAST_XY[0] + rho, K.MAST_XY[1], z))
    assert q is not None
    return q


def radial_point(base, rho: float, heading: float, z: float) -> np.ndarray:
    """World point (3,) at radius ``rho`` m and heading rad about the mast, height z m."""
    mx, my = mast_xy(base)
    return np.array([mx + rho * math.cos(heading), my + rho * math.sin(heading), z])


def bin_release_point(scene: Scene, base=None) -> np.ndarray:
    """TCP position (3,) over the bin centre (robot at ``base``, default parked) at
    which the carried item is let go."""
    x, y, yaw = scene.park if base is None else (float(v) for v in base)
    c, s = math.cos(yaw), math.sin(yaw)
    bx, by = K.BIN_XY
    hang = scene.target.height - K.GRASP_DEPTH
    return np.array([x + c * bx - s * by, y + s * bx + c * by,
                     K.BIN_RIM + K.RELEASE_ABOVE_RIM + hang])


class Path:
    """Growing list of trajectory samples; each method appends one segment."""

    def __init__(self, base, joints, gripper: float):
        self.t: list[float] = [0.0]
        self.b: list[np.ndarray] = [np.asarray(base, dtype=float)]
        self.q: list[np.ndarray] = [np.asarray(joints, dtype=float)]
        self.g: list[float] = [float(gripper)]

    @property
    def now(self) -> float:
        return self.t[-1]

    def _segment(self, duration: float, sample) -> None:
        n = max(1, math.ceil(duration * K.SAMPLE_RATE))
        t0 = self.now
        for k in range(1, n + 1):
            b, q, g = sample(min_jerk(k / n), k / n)
            self.t.append(t0 + duration * k / n)
            self.b.append(b)
            self.q.append(q)
            self.g.append(g)

    def hold(self, duration: float, gripper: float | None = None) -> None:
        """Keep still; move the gripper gap linearly to ``gripper`` (m) if given."""
        b, q, g0 = self.b[-1], self.q[-1], self.g[-1]
        g1 = g0 if gripper is None else float(gripper)
        self._segment(duration, lambda s, lin: (b, q, g0 + (g1 - g0) * lin))

    def drive(self, goal, duration: float) -> None:
        """Drive the base to ``goal`` (x, y, yaw), arm still."""
        b0, q, g = self.b[-1], self.q[-1], self.g[-1]
        b1 = np.asarray(goal, dtype=float)
        self._segment(duration, lambda s, lin: (b0 + s * (b1 - b0), q, g))

    def line(self, goal_tcp, duration: float) -> None:
        """Move the TCP along a straight line to ``goal_tcp`` (3,) m, tool down."""
        b, g = self.b[-1], self.g[-1]
        p0, p1 = tcp_position(b, self.q[-1]), np.asarray(goal_tcp, dtype=float)

        def sample(s, lin):
            q = solve_ik(b, p0 + s * (p1 - p0))
            if q is None:
                raise RuntimeError(f"unreachable TCP position {p0 + s * (p1 - p0)}")
            return b, q, g

        self._segment(duration, sample)

    def joints_to(self, goal_tcp, duration: float) -> None:
        """Move in joint space to the IK solution for ``goal_tcp`` (3,) m."""
        b, q0, g = self.b[-1], self.q[-1], self.g[-1]
        q1 = solve_ik(b, goal_tcp)
        if q1 is None:
            raise RuntimeError(f"unreachable TCP position {goal_tcp}")
        self._segment(duration, lambda s, lin: (b, q0 + s * (q1 - q0), g))

    def truncate(self, n: int) -> None:
        """Keep only the first n samples."""
        del self.t[n:], self.b[n:], self.q[n:], self.g[n:]
