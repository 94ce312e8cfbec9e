"""A scripted teleoperator for bots and tests: a stateless state machine.

It reads the phase from the world state, so it can take over at any
moment (also after a drop and reset):

- item on the shelf: open the gripper; if the arm points elsewhere, rise to
  the swing height, pull in and turn; rise to ``transfer_height`` (over the
  obstacles) before moving sideways; go above the item; descend; close.
- item held: rise, pull in, turn towards the bin (joint command on j1),
  move over the bin, open.
- item dropped (waiting for the reset) or deposited: no motion.
"""

from __future__ import annotations

import math

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import wrap_angle
from experiment.world.path import bin_release_point, radial_point
from experiment.world.robot import arm_points, radial
from experiment.world.scene import Scene, transfer_height
from experiment.world.state import ItemMode, WorldState
from experiment.world.teleop import TeleopCommand

GAIN = 4.0  # 1/s, proportional gain of the Cartesian moves
YAW_GAIN = 3.0  # 1/s, proportional gain of the j1 turn
TOL = 0.008  # m, position tolerance of a waypoint
XY_TOL = 0.015  # m, horizontal tolerance before descending
HEADING_TOL = 0.04  # rad


def _toward(tcp: np.ndarray, goal, gripper: str | None = None) -> TeleopCommand:
    e = np.asarray(goal, dtype=float) - tcp
    n = float(np.linalg.norm(e))
    v = e * min(GAIN, K.MAX_EE_SPEED / n) if n > 1e-12 else np.zeros(3)
    return TeleopCommand(ee_velocity=tuple(v.tolist()), gripper=gripper)


def _turn(state: WorldState, tcp: np.ndarray, heading: float, z_clear: float,
          gripper: str | None) -> TeleopCommand:
    """Rise to the swing height, pull in to ``RETRACT_RADIUS``, then turn j1 to ``heading``."""
    rho, now = radial(state.base, tcp)
    z = max(z_clear, K.SWING_MIN_Z)
    if tcp[2] < z - 0.02:
        return _toward(tcp, (tcp[0], tcp[1], z), gripper)
    if rho > K.RETRACT_RADIUS + 0.02:
        return _toward(tcp, radial_point(state.base, K.RETRACT_RADIUS, now, z), gripper)
    rate = float(np.clip(YAW_GAIN * wrap_angle(heading - now), -K.MAX_JOINT_SPEED, K.MAX_JOINT_SPEED))
    return TeleopCommand(joint_velocity=(rate, 0.0, 0.0, 0.0), gripper=gripper)


def scripted_teleop_commands(state: WorldState, scene: Scene) -> TeleopCommand:
    """The next command of the scripted teleoperator for ``state`` in ``scene``."""
    if state.item.mode in (ItemMode.DROPPED, ItemMode.IN_BIN):
        return TeleopCommand()
    tcp = np.array(arm_points(state.base, state.joints).tcp)
    z_clear = transfer_height(scene)
    if state.item.mode == ItemMode.ON_SHELF:
        return _to_item(state, scene, tcp, z_clear)
    return _to_bin(state, scene, tcp, z_clear)


def _to_item(state: WorldState, scene: Scene, tcp: np.ndarray, z_clear: float) -> TeleopCommand:
    grasp = scene.target.grasp_point()
    gripper = "open" if state.gripper_target < K.GRIPPER_MAX else None
    _, heading = radial(state.base, tcp)
    _, goal_heading = radial(state.base, grasp)
    if abs(wrap_angle(heading - goal_heading)) > HEADING_TOL:
        return _turn(state, tcp, goal_heading, z_clear, gripper)
    if math.dist(tcp[:2], grasp[:2]) > XY_TOL:
        if tcp[2] < z_clear - 0.02:
            return _toward(tcp, (tcp[0], tcp[1], z_clear), gripper)
        return _toward(tcp, (grasp[0], grasp[1], z_clear), gripper)
    if np.linalg.norm(grasp - tcp) > TOL or state.gripper < K.GRIPPER_MAX:
        return _toward(tcp, grasp, gripper)
    return TeleopCommand(gripper="close")


def _to_bin(state: WorldState, scene: Scene, tcp: np.ndarray, z_clear: float) -> TeleopCommand:
    target = bin_release_point(scene, state.base)
    _, heading = radial(state.base, tcp)
    _, goal_heading = radial(state.base, target)
    if abs(wrap_angle(heading - goal_heading)) > HEADING_TOL:
        return _turn(state, tcp, goal_heading, z_clear, None)
    if np.linalg.norm(target - tcp) > TOL:
        return _toward(tcp, target)
    return TeleopCommand(gripper="open")
