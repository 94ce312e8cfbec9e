"""What the teleoperation messages carry of the world: the arm's state, the guidance, the trial's scene
(``server.teleop_messages``)."""

from __future__ import annotations

import math
from typing import Any

from experiment.world import constants as K
from experiment.world.guidance import SHAPE_NAMES, color_name, describe_target, guidance
from experiment.world.path import bin_release_point
from experiment.world.robot import arm_points
from experiment.world.scene import Scene, scene_boxes, transfer_height
from experiment.world.teleop import TeleopRules
from server.services import wording
from server.teleop_messages import BinInfo, BoxInfo, GuidanceView, ItemView, SceneInfo, TargetInfo, WorldView
from server.world.teleop import TeleopSession


def _vec(values: Any) -> tuple[float, ...]:
    return tuple(round(float(v), 6) for v in values)


def world_view(state: Any) -> WorldView:
    item = state.item
    return WorldView(t=round(state.t, 6), base=_vec(state.base), joints=_vec(state.joints),
                     gripper=round(state.gripper, 6), gripper_target=round(state.gripper_target, 6),
                     tcp=_vec(arm_points(state.base, state.joints).tcp),
                     item=ItemView(mode=item.mode.value, position=_vec(item.position), wxyz=_vec(item.wxyz)))


def guidance_view(teleop: TeleopSession, language: str = "en") -> GuidanceView:
    """The guidance, its sentence in ``language`` (the participant's)."""
    g = guidance(teleop.state, teleop.scene, teleop.rules)
    text = wording.guidance_text(g.message, wording.translator(language))
    return GuidanceView(step=g.step.value, text=text, can_grasp=g.can_grasp, over_bin=g.over_bin,
                        blocked=teleop.blocked, grasp_distance=round(g.grasp_distance, 6), to_grasp=_vec(g.to_grasp),
                        to_bin=_vec(g.to_bin))


def _box(box: Any) -> BoxInfo:
    return BoxInfo(name=box.name, center=_vec(box.center), size=_vec(box.size))


def scene_info(scene: Scene, rules: TeleopRules) -> SceneInfo:
    """What a client needs to know of the trial's world to steer: target, obstacles, shelf, bin."""
    target = scene.target
    x, y, yaw = scene.park
    c, s = math.cos(yaw), math.sin(yaw)
    bx, by = K.BIN_XY
    opening = (K.BIN_SIZE[0] - 2 * K.BIN_WALL, K.BIN_SIZE[1] - 2 * K.BIN_WALL)
    others = [b for b in scene_boxes(scene) if b.name.startswith("/items/")]
    return SceneInfo(
        complexity=scene.complexity, seed=str(scene.seed), target_slot=target.slot,
        target=TargetInfo(slot=target.slot, description=describe_target(scene), color=color_name(target.color),
                          shape=SHAPE_NAMES[target.shape], center=_vec(target.center), size=_vec(target.size),
                          grasp_point=_vec(target.grasp_point())),
        obstacles=[_box(b) for b in scene.obstacles], shelf=[_box(b) for b in scene.shelf],
        other_items=[_box(b) for b in others],
        bin=BinInfo(opening_center=(round(x + c * bx - s * by, 6), round(y + s * bx + c * by, 6), K.BIN_RIM),
                    opening_size=opening, rim_z=K.BIN_RIM, yaw=yaw,
                    release_point=_vec(bin_release_point(scene, scene.park))),
        clear_height=round(transfer_height(scene), 6))
