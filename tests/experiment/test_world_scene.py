import dataclasses

import numpy as np
import pytest

from experiment.task import Complexity
from experiment.world import (
    FRAME_NAMES,
    body_shapes,
    build_scene,
    collisions,
    link_poses,
    scene_boxes,
    solve_ik,
    teleop_start_state,
)
from experiment.world import constants as K
from experiment.world.robot import arm_points

SEEDS = range(40)


def _boxes(scene):
    return [(b.name, b.center.tolist(), b.size.tolist(), b.shape, b.color) for b in scene_boxes(scene)]


@pytest.mark.parametrize("complexity", ["low", "high"])
def test_same_seed_same_scene(complexity):
    a, b = build_scene(complexity, (7, 3)), build_scene(complexity, (7, 3))
    assert _boxes(a) == _boxes(b)
    assert a.target_slot == b.target_slot and a.park == b.park
    assert any(_boxes(build_scene(complexity, s)) != _boxes(a) for s in range(5))


def test_obstacles_exist_exactly_in_high_complexity():
    for seed in SEEDS:
        low, high = build_scene("low", seed), build_scene("high", seed)
        assert low.obstacles == ()
        assert not any(b.name.startswith("/obstacles/") for b in scene_boxes(low))
        assert 2 <= len(high.obstacles) <= 3


def test_the_main_obstacle_blocks_the_way_to_the_target():
    for seed in SEEDS:
        scene = build_scene("high", seed)
        target, blocker = scene.target, scene.obstacles[0]
        mast_x = arm_points(scene.park, np.zeros(4)).mast[0]
        assert mast_x < blocker.lo[0] < blocker.hi[0] < target.center[0]
        assert blocker.lo[1] < target.center[1] < blocker.hi[1]
        assert blocker.hi[2] > target.center[2] + target.height / 2


def test_target_slot_is_seeded_and_can_be_chosen():
    slots = {build_scene("low", s).target_slot for s in SEEDS}
    assert slots == set(range(K.N_SLOTS))
    scene = build_scene("high", 1, target_slot=5)
    assert scene.target_slot == 5 and scene.target.name == "/items/5"
    assert "/items/5" not in {b.name for b in scene_boxes(scene)}  # the target moves: not static
    with pytest.raises(ValueError, match="slot"):
        build_scene("low", 1, target_slot=K.N_SLOTS)


def test_complexity_accepts_the_task_enum_and_rejects_junk():
    assert build_scene(Complexity.HIGH, 0).complexity == "high"
    with pytest.raises(ValueError, match="complexity"):
        build_scene("medium", 0)


def test_scene_boxes_have_unique_stable_names():
    scene = build_scene("high", 3)
    names = [b.name for b in scene_boxes(scene)]
    assert len(names) == len(set(names))
    assert names[0] == "/floor" and "/shelf/board_0" in names and "/shelf/board_1" in names
    assert "/obstacles/0" in names
    for b in scene_boxes(scene):
        assert b.center.shape == (3,) and b.size.shape == (3,) and np.all(b.size > 0)


def test_link_poses_cover_the_robot_and_the_item():
    scene = build_scene("low", 2)
    poses = link_poses(teleop_start_state(scene))
    assert tuple(poses) == FRAME_NAMES
    for pos, wxyz in poses.values():
        assert pos.shape == (3,) and wxyz.shape == (4,)
        assert np.linalg.norm(wxyz) == pytest.approx(1.0)
    np.testing.assert_allclose(poses["/items/target"][0], scene.target.center)
    parents = {s.name.rsplit("/", 1)[0] for s in body_shapes(scene)}
    assert parents <= set(FRAME_NAMES)


def test_start_states_are_collision_free():
    for seed in range(10):
        for c in ("low", "high"):
            scene = build_scene(c, seed)
            assert collisions(teleop_start_state(scene), scene) == []


def _reach(scene, state, point):
    q = solve_ik(state.base, point)
    assert q is not None
    return dataclasses.replace(state, joints=tuple(q))


@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_collisions_name_what_touches_what(yaw):
    scene = build_scene("high", 4)
    base = (scene.park[0] - 0.5, scene.park[1], yaw)  # away from the shelf
    state = dataclasses.replace(teleop_start_state(scene), base=base)
    assert collisions(state, scene) == []
    c, s = np.cos(yaw), np.sin(yaw)
    bin_xy = np.array(base[:2]) + np.array([[c, -s], [s, c]]) @ np.array(K.BIN_XY)
    inside_bin = _reach(scene, state, (*bin_xy, K.BIN_RIM - 0.05))
    hits = collisions(inside_bin, scene)
    assert any(h.endswith(" vs /robot/bin") for h in hits)
    assert all(" vs " in h for h in hits)


def test_collisions_with_obstacles_and_shelf():
    scene = build_scene("high", 4)
    start = teleop_start_state(scene)
    ob = scene.obstacles[0]
    into_obstacle = _reach(scene, start, (ob.center[0], ob.center[1], ob.hi[2] - 0.02))
    assert any("/obstacles/0" in h for h in collisions(into_obstacle, scene))
    board = scene.shelf[4]
    assert board.name == "/shelf/board_0"
    x, y = K.SHELF_FRONT_X + 0.05, scene.target.center[1]
    into_board = _reach(scene, start, (x, y, board.hi[2] + 0.005))
    assert any(h.endswith("vs /shelf/board_0") for h in collisions(into_board, scene))
