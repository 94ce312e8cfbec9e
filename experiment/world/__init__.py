"""The server-side robot world of one trial (pure Python + numpy).

A mobile manipulator (base x, y, yaw; 4-DOF arm j1 yaw, j2-j4 pitch; parallel
gripper) collects one grocery item from a shelf into the bin on its base.
High complexity adds 2-3 obstacle boxes in front of the target item.

- ``build_scene(complexity, seed, target_slot=None) -> Scene``
- ``plan_attempt(scene, success, rng) -> Attempt`` with ``state_at(t)``
- ``teleop_start_state(scene)``, ``teleop_step(state, scene, command, dt)``
- ``scripted_teleop_commands(state, scene)`` for bots and tests
- ``collisions(state, scene)``, ``link_poses(state)``, ``scene_boxes(scene)``,
  ``body_shapes(scene)`` for rendering
- kinematics: ``link_frames``, ``tcp_position``, ``jacobian``, ``ik_step``,
  ``solve_ik``; all numbers in ``experiment.world.constants``.

Units: metres, radians, seconds; quaternions are (w, x, y, z).
"""

from experiment.world import constants
from experiment.world.attempt import Attempt, plan_attempt
from experiment.world.collision import collisions
from experiment.world.geometry import Box
from experiment.world.render import FRAME_NAMES, body_shapes, link_poses
from experiment.world.robot import arm_points, ik_step, jacobian, link_frames, solve_ik, tcp_position
from experiment.world.scene import Item, Scene, build_scene, scene_boxes, scene_stamp, transfer_height
from experiment.world.scripted import scripted_teleop_commands
from experiment.world.state import ItemMode, ItemState, WorldState
from experiment.world.teleop import TeleopCommand, WorldEvent, can_grasp, parse_command, teleop_start_state, teleop_step

__all__ = [
    "Attempt", "Box", "FRAME_NAMES", "Item", "ItemMode", "ItemState", "Scene", "TeleopCommand", "WorldEvent",
    "WorldState", "arm_points", "body_shapes", "build_scene", "can_grasp", "collisions", "constants",
    "ik_step", "jacobian", "link_frames", "link_poses", "parse_command", "plan_attempt",
    "scene_boxes", "scene_stamp", "scripted_teleop_commands", "solve_ik", "tcp_position", "teleop_start_state",
    "teleop_step", "transfer_height",
]
