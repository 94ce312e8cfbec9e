"""Rendering hooks: moving frames with their poses, and the shapes attached to them.

A renderer (viser) creates ``scene_boxes(scene)`` once in world coordinates,
creates one frame per ``link_poses`` name with the ``body_shapes(scene)``
children (``center``/``wxyz`` relative to the parent frame, the name minus
its last component), then updates only the frame poses at 30 Hz.
"""

from __future__ import annotations

import math

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import Box, box_from_bounds
from experiment.world.robot import link_frames
from experiment.world.scene import Scene
from experiment.world.state import WorldState

ROBOT_COLOR = (70, 75, 85)
ARM_COLOR = (235, 235, 240)
ACCENT_COLOR = (255, 150, 0)
BIN_COLOR = (40, 110, 190)
FRAME_NAMES = ("/robot/base", "/robot/mast", "/robot/j1", "/robot/j2", "/robot/j3",
               "/robot/j4", "/robot/palm", "/robot/finger_left", "/robot/finger_right",
               "/items/target")


def link_poses(state: WorldState) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World pose of every moving frame: name -> (position (3,) m, wxyz (4,)).

    Names are ``FRAME_NAMES``: the robot frames of ``robot.link_frames`` and
    ``/items/target`` (the centre of the target item).
    """
    frames = link_frames(state.base, state.joints, state.gripper)
    frames["/items/target"] = (state.item.position, state.item.wxyz)
    return {k: (np.array(p, dtype=float), np.array(q, dtype=float)) for k, (p, q) in frames.items()}


def _bin_shapes() -> list[Box]:
    bx, by = K.BIN_XY
    sx, sy, sz = K.BIN_SIZE
    w, z0, z1 = K.BIN_WALL, K.BASE_TOP, K.BIN_RIM
    x0, x1, y0, y1 = bx - sx / 2, bx + sx / 2, by - sy / 2, by + sy / 2
    parts = [("bin_floor", (x0, y0, z0), (x1, y1, z0 + w)),
             ("bin_wall_0", (x0, y0, z0), (x0 + w, y1, z1)),
             ("bin_wall_1", (x1 - w, y0, z0), (x1, y1, z1)),
             ("bin_wall_2", (x0, y0, z0), (x1, y0 + w, z1)),
             ("bin_wall_3", (x0, y1 - w, z0), (x1, y1, z1))]
    return [box_from_bounds(f"/robot/base/{n}", lo, hi, BIN_COLOR) for n, lo, hi in parts]


def _base_shapes() -> list[Box]:
    body = box_from_bounds("/robot/base/body", (-K.BASE_LENGTH / 2, -K.BASE_WIDTH / 2, K.BASE_BOTTOM),
                           (K.BASE_LENGTH / 2, K.BASE_WIDTH / 2, K.BASE_TOP), ROBOT_COLOR)
    axle = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])  # cylinder axis -> y
    d = 2 * K.WHEEL_RADIUS
    wheels = [Box(f"/robot/base/wheel_{i}", np.array([sx * K.WHEEL_X, sy * K.BASE_WIDTH / 2, K.WHEEL_RADIUS]),
                  np.array([d, d, K.WHEEL_WIDTH]), (30, 30, 30), "cylinder", axle)
              for i, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1)))]
    return [body, *wheels, *_bin_shapes()]


def _arm_shapes() -> list[Box]:
    """Mast, joint housing, links (as thick as their collision capsules), palm, fingers."""
    def link(name: str, length: float, color=ARM_COLOR) -> Box:
        d = 2 * K.LINK_RADII[name.rsplit("/", 1)[0]]
        return Box(name, np.array([length / 2, 0.0, 0.0]), np.array([length, d, d]), color)

    mast_h = K.MAST_TOP - K.BASE_TOP
    housing_h = K.SHOULDER_Z - K.MAST_TOP
    palm_d = 2 * K.LINK_RADII["/robot/palm"]
    finger = np.array([K.FINGER_LENGTH, 2 * K.FINGER_RADIUS, 2 * K.FINGER_RADIUS])
    return [
        Box("/robot/mast/column", np.array([0.0, 0.0, mast_h / 2]),
            np.array([K.MAST_WIDTH, K.MAST_WIDTH, mast_h]), ROBOT_COLOR),
        Box("/robot/j1/housing", np.array([0.0, 0.0, housing_h / 2]),
            np.array([K.J1_HOUSING_DIAMETER, K.J1_HOUSING_DIAMETER, housing_h]), ACCENT_COLOR, "cylinder"),
        link("/robot/j2/link", K.UPPER_ARM),
        link("/robot/j3/link", K.FOREARM),
        link("/robot/j4/link", K.WRIST_LINK, ACCENT_COLOR),
        Box("/robot/palm/plate", np.zeros(3), np.array([palm_d, 2 * K.PALM_HALF_WIDTH, palm_d]), ROBOT_COLOR),
        Box("/robot/finger_left/geom", np.zeros(3), finger.copy(), ROBOT_COLOR),
        Box("/robot/finger_right/geom", np.zeros(3), finger.copy(), ROBOT_COLOR),
    ]


def body_shapes(scene: Scene) -> list[Box]:
    """Shapes attached to the moving frames of ``link_poses`` (parent = name's dirname).

    ``center``/``wxyz`` are in the parent frame; the target item's shape is
    ``/items/target/geom``.
    """
    it = scene.target
    item = Box("/items/target/geom", np.zeros(3), it.size.copy(), it.color, it.shape)
    return [*_base_shapes(), *_arm_shapes(), item]
