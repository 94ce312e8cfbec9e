"""The 3D view's camera presets (server.viewer.cameras): pure geometry, no server.

Page aspects: the 3D view measured in the participant page is 848x530 at 1280x720 and 1488x928 at 1920x1080.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from experiment.world import build_scene, link_poses, teleop_start_state
from experiment.world import constants as K
from experiment.world.render import body_shapes
from experiment.world.robot import arm_points, finger_centers, solve_ik
from experiment.world.scene import scene_boxes, transfer_height
from server.viewer.cameras import (
    EE_FOV_DEG,
    LOCAL_FRAMING,
    PAGE_ASPECT,
    WORLD_FRAMING,
    Framing,
    box_corners,
    camera_for,
    end_effector_camera,
    frame_points,
    local_camera,
    project,
    view_axes,
    world_camera,
)
from server.viewer.scene import BIN_BOX, MARKER_HEIGHT, pose_tuples, start_state, state_poses

PAGE_ASPECTS = (848 / 530, 1488 / 928)
EPS = 1e-9


def in_view(projected: np.ndarray, margin: float = 0.0) -> bool:
    return bool((projected[:, 2] > 0.05).all() and (np.abs(projected[:, :2]) <= 1 - margin + EPS).all())


# --- the fitting itself -------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(12))
def test_frame_points_fits_tightly_and_centres(seed):
    """Any points, any angle: all in view with the margin, one pair of edges touched, the other pair centred."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(int(rng.integers(2, 40)), 3)) * rng.uniform(0.1, 3.0, size=3) + rng.normal(size=3) * 5
    framing = Framing(yaw_deg=float(rng.uniform(-180, 180)), pitch_deg=float(rng.uniform(-70, 20)),
                      vfov_deg=float(rng.uniform(20, 90)), margin=float(rng.uniform(0, 0.2)), aspect=1.0)
    aspect = float(rng.uniform(0.7, 2.4))
    position, look_at = frame_points(points, framing, aspect)
    projected = project(points, position, look_at, framing.vfov_deg, aspect)
    assert in_view(projected, framing.margin)
    edge = 1 - framing.margin
    x, y = projected[:, 0], projected[:, 1]
    spans = [(x.min(), x.max()), (y.min(), y.max())]
    tight = [np.isclose(lo, -edge, atol=1e-6) and np.isclose(hi, edge, atol=1e-6) for lo, hi in spans]
    assert any(tight), f"no pair of edges touched: {spans}"
    for lo, hi in spans:  # the other pair: centred
        assert lo == pytest.approx(-hi, abs=1e-6)
    _, _, forward = view_axes(framing.yaw_deg, framing.pitch_deg)  # the angle is the framing's
    sight = (np.asarray(look_at) - position) / np.linalg.norm(np.asarray(look_at) - position)
    assert sight == pytest.approx(forward, abs=1e-9)


# --- world ---------------------------------------------------------------------------------------------------

def trial_points(scene) -> np.ndarray:
    """What a trial's world view must show: shelf, items, obstacles, the target and its arrow, and the robot
    parked with its arm at the ready pose, over the item at the carrying height and down at the item."""
    static = [b for b in scene_boxes(scene) if b.name != "/floor"]
    points = [box_corners(b) for b in static]
    start = teleop_start_state(scene)
    grasp = scene.target.grasp_point()
    arm_poses = [start.joints, solve_ik(scene.park, grasp),
                 solve_ik(scene.park, (grasp[0], grasp[1], transfer_height(scene)))]
    for joints in arm_poses:
        assert joints is not None
        frames = link_poses(dataclasses.replace(start, joints=tuple(float(q) for q in joints)))
        points += [box_corners(shape, *frames[shape.name.rsplit("/", 1)[0]]) for shape in body_shapes(scene)]
    top = scene.target.center[2] + scene.target.height / 2
    points.append(np.array([[scene.target.center[0], scene.target.center[1], top + MARKER_HEIGHT]]))
    return np.concatenate(points)


@pytest.mark.parametrize("aspect", PAGE_ASPECTS, ids=["1280x720", "1920x1080"])
@pytest.mark.parametrize("complexity", ["low", "high"])
@pytest.mark.parametrize("slot", range(K.N_SLOTS))
def test_the_world_view_frames_robot_target_and_bin_in_every_trial(slot, complexity, aspect):
    scene = build_scene(complexity, 100 + slot, target_slot=slot)
    assert bool(scene.obstacles) == (complexity == "high")
    position, look_at = world_camera(MARKER_HEIGHT, PAGE_ASPECT)
    projected = project(trial_points(scene), position, look_at, WORLD_FRAMING.vfov_deg, aspect)
    assert in_view(projected, WORLD_FRAMING.margin), (projected[:, :2].min(axis=0), projected[:, :2].max(axis=0))
    height = projected[:, 1].max() - projected[:, 1].min()
    width = projected[:, 0].max() - projected[:, 0].min()
    # the view is fitted to every trial's robot at its start and parked, and the shelf, at once; the parked robot
    # and the shelf of one trial fill half the height and a good part of the width (the robot's drive to the shelf,
    # in view too, takes the rest)
    assert height > 0.45 * 2, f"the trial fills {height / 2:.0%} of the view's height"
    assert width > 0.25 * 2, f"the trial fills {width / 2:.0%} of the view's width"


#: The 3D view's height in the 1280x720 page (px): 848x530.
VIEW_HEIGHT_PX = 530
#: The largest share of the view one body may cover (its outline's box, within the view), and the least distance
#: (m, along the line of sight) of any body from the camera: nothing near the camera fills a part of the view.
MOST_COVERED, NEAREST_M = 0.15, 1.5


def decision_window_bodies(scene) -> dict[str, np.ndarray]:
    """The corners of every body the view shows while the participant decides, by name: the robot at rest where it
    starts the trial, as the view shows it (``server.viewer.scene.start_state``), the shelf, the items (the target
    in its slot) and the obstacles."""
    frames = link_poses(start_state(scene))
    bodies = {shape.name: box_corners(shape, *frames[shape.name.rsplit("/", 1)[0]]) for shape in body_shapes(scene)}
    return bodies | {box.name: box_corners(box) for box in scene_boxes(scene) if box.name != "/floor"}


def covered_share(projected: np.ndarray) -> float:
    """The share of the view that the box around a body's projected corners covers, within the view."""
    x, y = np.clip(projected[:, 0], -1, 1), np.clip(projected[:, 1], -1, 1)
    return float(np.ptp(x) * np.ptp(y) / 4)


@pytest.mark.parametrize("aspect", PAGE_ASPECTS, ids=["1280x720", "1920x1080"])
@pytest.mark.parametrize("complexity", ["low", "high"])
@pytest.mark.parametrize("slot", range(K.N_SLOTS))
def test_in_the_decision_window_the_world_view_shows_the_robot_the_shelf_and_the_target(slot, complexity, aspect):
    """Issue 37: while the participant decides, the robot stands where it starts (DRIVE_DISTANCE behind its
    parking place). Its base and arm, the shelf and the target (item and marker) are all in the picture with the
    framing's margin, the target is big enough to see, and no body is near the camera (a grey arm segment filled a
    corner of the view and the robot was out of it)."""
    scene = build_scene(complexity, 200 + slot, target_slot=slot)
    position, look_at = world_camera(MARKER_HEIGHT, PAGE_ASPECT)
    bodies = decision_window_bodies(scene)
    top = scene.target.center[2] + scene.target.height / 2
    marker = np.array([[scene.target.center[0], scene.target.center[1], top + MARKER_HEIGHT]])
    parts = {"the robot's base": [b for n, b in bodies.items() if n.startswith("/robot/base/")],
             "the robot's mast and arm": [b for n, b in bodies.items() if n.startswith("/robot/")
                                          and not n.startswith("/robot/base/")],
             "the shelf": [b for n, b in bodies.items() if n.startswith("/shelf/")],
             "the target": [bodies["/items/target/geom"], marker]}
    for what, boxes in parts.items():
        assert boxes, what
        projected = project(np.concatenate(boxes), position, look_at, WORLD_FRAMING.vfov_deg, aspect)
        assert in_view(projected, WORLD_FRAMING.margin), (what, projected[:, :2].min(axis=0),
                                                          projected[:, :2].max(axis=0))
    for name, corners in bodies.items():
        projected = project(corners, position, look_at, WORLD_FRAMING.vfov_deg, aspect)
        assert projected[:, 2].min() > NEAREST_M, f"{name} is {projected[:, 2].min():.2f} m from the camera"
        assert covered_share(projected) < MOST_COVERED, f"{name} covers {covered_share(projected):.0%} of the view"
    item = project(bodies["/items/target/geom"], position, look_at, WORLD_FRAMING.vfov_deg, aspect)
    assert np.ptp(item[:, 1]) / 2 * VIEW_HEIGHT_PX > 15, "the target item is too small to see"


def test_the_world_view_is_one_pose_with_a_stable_angle():
    position, look_at = world_camera(MARKER_HEIGHT)
    sight = np.subtract(look_at, position) / np.linalg.norm(np.subtract(look_at, position))
    assert sight == pytest.approx(view_axes(WORLD_FRAMING.yaw_deg, WORLD_FRAMING.pitch_deg)[2])
    poses = pose_tuples(state_poses(teleop_start_state(build_scene("high", 1, target_slot=5))))
    assert camera_for("world", poses, marker_height=MARKER_HEIGHT) == (position, look_at, (0.0, 0.0, 1.0))
    other = pose_tuples(state_poses(teleop_start_state(build_scene("low", 2, target_slot=0))))
    assert camera_for("world", other, marker_height=MARKER_HEIGHT) == (position, look_at, (0.0, 0.0, 1.0))


# --- following the gripper ---------------------------------------------------------------------------------

def gripper_at(scene, tcp) -> dict:
    joints = solve_ik(scene.park, tcp)
    assert joints is not None, tcp
    return pose_tuples(state_poses(dataclasses.replace(teleop_start_state(scene),
                                                       joints=tuple(float(q) for q in joints))))


def item_corners(scene, center=None) -> np.ndarray:
    """(8, 3): the target item's corners, in its slot or centred at ``center``."""
    geom = next(b for b in body_shapes(scene) if b.name == "/items/target/geom")
    return box_corners(geom, scene.target.center if center is None else center)


@pytest.mark.parametrize("slot", range(K.N_SLOTS))
def test_the_local_view_keeps_the_item_in_view_with_the_gripper_high_above_it(slot):
    scene = build_scene("high", 7, target_slot=slot)
    grasp = scene.target.grasp_point()
    item = item_corners(scene)
    poses_list = [pose_tuples(state_poses(teleop_start_state(scene)))]  # the start: the ready pose
    poses_list += [gripper_at(scene, (grasp[0], grasp[1], min(grasp[2] + rise, K.TCP_MAX_Z)))
                   for rise in (0.0, 0.1, 0.3, 0.6, 0.9)]
    for poses in poses_list:
        position, look_at = local_camera(poses, item)
        tcp = np.array(poses["/robot/palm"][0]) - np.array([0.0, 0.0, K.TCP_OFFSET])
        projected = project(np.concatenate([item, [tcp]]), position, look_at, LOCAL_FRAMING.vfov_deg, PAGE_ASPECT)
        assert in_view(projected, LOCAL_FRAMING.margin)
        assert np.linalg.norm(np.subtract(look_at, position)) < 2.0  # still a close view of the gripper area


def test_the_local_view_shows_the_bin_while_the_item_is_held():
    scene = build_scene("low", 7, target_slot=6)
    poses = gripper_at(scene, (scene.park[0] + 0.1, scene.park[1] + 0.3, 1.0))
    bin_corners = box_corners(BIN_BOX, *poses["/robot/base"])
    position, look_at = local_camera(poses, bin_corners)
    assert in_view(project(bin_corners, position, look_at, LOCAL_FRAMING.vfov_deg, PAGE_ASPECT), LOCAL_FRAMING.margin)


@pytest.mark.parametrize("slot", [0, 3, 4, 7])
def test_the_end_effector_view_centres_what_is_under_the_gripper(slot):
    """The item right under the gripper stays in view from grasping height to 0.8 m above it, the fingertips
    show, and a held item leaves the lower half of the view free."""
    scene = build_scene("low", 11, target_slot=slot)
    grasp = scene.target.grasp_point()
    item_top = scene.target.center + [0.0, 0.0, scene.target.height / 2]
    for rise in (0.02, 0.05, 0.2, 0.4, 0.8):
        tcp = np.array([grasp[0], grasp[1], grasp[2] + rise])
        if tcp[2] > K.TCP_MAX_Z:
            continue
        poses = gripper_at(scene, tcp)
        eye, look, up = end_effector_camera(poses)
        joints = solve_ik(scene.park, tcp)
        arm = arm_points(scene.park, joints)
        tips = [np.add(c, np.multiply(arm.tool_x, K.FINGER_LENGTH / 2)) for c in finger_centers(arm, K.GRIPPER_MAX)]
        projected = project(np.array([item_top, *tips]), eye, look, EE_FOV_DEG, PAGE_ASPECT, up)
        assert in_view(projected), (rise, projected)
        assert abs(projected[0, 0]) < 0.05  # the item under the gripper is on the view's vertical centre line
        assert projected[1:, 1] == pytest.approx([projected[1, 1]] * 2) and projected[1, 1] > 0.3  # tips at the top
        palm = project(np.array([poses["/robot/palm"][0]]), eye, look, EE_FOV_DEG, PAGE_ASPECT, up)
        assert not in_view(palm)  # the palm does not block the view
        held = tcp - np.array([0.0, 0.0, scene.target.height / 2 - K.GRASP_DEPTH])  # its grasp point at the TCP
        corners = project(item_corners(scene, held), eye, look, EE_FOV_DEG, PAGE_ASPECT, up)
        assert corners[:, 1].min() > -0.1  # a held item covers the upper middle; what is under it shows below


def test_presets_reject_unknown_views():
    poses = pose_tuples(state_poses(teleop_start_state(build_scene("low", 1))))
    with pytest.raises(ValueError, match="unknown view"):
        camera_for("top", poses, marker_height=MARKER_HEIGHT)
