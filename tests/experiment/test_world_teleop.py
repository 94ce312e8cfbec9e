import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiment.world import (
    ItemMode,
    TeleopCommand,
    build_scene,
    collisions,
    scripted_teleop_commands,
    solve_ik,
    tcp_position,
    teleop_start_state,
    teleop_step,
)
from experiment.world import constants as K
from experiment.world.path import bin_release_point
from experiment.world.state import over_bin_opening

DT = 1 / 30


def _run_scripted(scene, state=None, limit=20.0, check=True):
    """Step the scripted teleoperator until the item lands in the bin; returns state, events."""
    state = state or teleop_start_state(scene)
    seen = []
    while state.t < limit:
        state, events = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
        seen += events
        if check:
            assert collisions(state, scene) == [], (state.t, collisions(state, scene))
        if "deposited" in seen and state.item.position[2] <= state.item.rest_z:
            break
    return state, seen


def test_start_state():
    scene = build_scene("high", 3)
    state = teleop_start_state(scene)
    assert state.base == scene.park and state.item.mode == ItemMode.ON_SHELF
    assert state.gripper == K.GRIPPER_MAX
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.t = 1.0


@pytest.mark.parametrize("complexity", ["low", "high"])
@pytest.mark.parametrize("slot", range(K.N_SLOTS))
def test_scripted_controller_collects_every_slot(complexity, slot):
    for seed in (slot, 100 + slot):
        scene = build_scene(complexity, seed, target_slot=slot)
        state, events = _run_scripted(scene, check=seed == slot)
        assert "deposited" in events and "blocked" not in events
        assert state.t <= 20.0
        assert state.item.mode == ItemMode.IN_BIN and over_bin_opening(state.base, state.item.position)


def test_scripted_controller_takes_over_from_any_pose():
    scene = build_scene("high", 4)
    start = teleop_start_state(scene)
    over_bin = solve_ik(start.base, bin_release_point(scene) + (0.0, 0.0, 0.1))
    state = dataclasses.replace(start, joints=tuple(over_bin), gripper=0.0, gripper_target=0.0)
    state, events = _run_scripted(scene, state)
    assert "deposited" in events and state.t <= 20.0


def _hold(scene, state, command, seconds):
    seen = []
    for _ in range(round(seconds / DT)):
        state, events = teleop_step(state, scene, command, DT)
        seen += events
        assert collisions(state, scene) == []
    return state, seen


def test_cannot_push_through_an_obstacle():
    scene = build_scene("high", 8)
    ob = scene.obstacles[0]
    start = teleop_start_state(scene)
    above = dataclasses.replace(start, joints=tuple(solve_ik(start.base, (*ob.center[:2], ob.hi[2] + 0.2))))
    assert collisions(above, scene) == []
    state, events = _hold(scene, above, {"ee_velocity": [0.0, 0.0, -0.3]}, 2.0)
    assert "blocked" in events
    fingertips = tcp_position(state.base, state.joints)[2] - (K.FINGER_LENGTH - K.TCP_OFFSET)
    assert fingertips > ob.hi[2]


def test_cannot_carry_the_item_through_an_obstacle():
    scene = build_scene("high", 8)
    state = teleop_start_state(scene)
    while state.item.mode != ItemMode.GRASPED:
        state, _ = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
    state, events = _hold(scene, state, {"ee_velocity": [0.0, 0.0, 0.1]}, 0.5)
    state, events = _hold(scene, state, {"ee_velocity": [-0.3, 0.0, 0.0]}, 2.0)
    assert "blocked" in events
    assert state.item.mode == ItemMode.GRASPED
    assert state.item.position[0] > scene.obstacles[0].hi[0]


@pytest.mark.parametrize("complexity", ["low", "high"])
def test_joint_motion_cannot_pass_through_the_world(complexity):
    scene = build_scene(complexity, 6)
    state, events = _hold(scene, teleop_start_state(scene), {"joint_velocity": [0.0, -1.0, 0.5, 0.0]}, 3.0)
    assert "blocked" in events


speed = st.floats(-0.6, 0.6)
commands = st.lists(st.tuples(
    st.one_of(st.builds(lambda v: {"ee_velocity": list(v)}, st.tuples(speed, speed, speed)),
              st.builds(lambda v: {"joint_velocity": list(v)}, st.tuples(*[st.floats(-2, 2)] * 4)),
              st.just({})),
    st.sampled_from([None, "open", "close", "toggle"]),
    st.integers(1, 8)), min_size=1, max_size=25)


@settings(max_examples=30, deadline=None)
@given(st.sampled_from(["low", "high"]), st.integers(0, 9), st.integers(0, 200), commands)
def test_no_command_sequence_reaches_a_collision(complexity, seed, lead_in, sequence):
    scene = build_scene(complexity, seed)
    state = teleop_start_state(scene)
    for _ in range(lead_in):  # start somewhere along the way to the item
        state, _ = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
    for command, gripper, repeat in sequence:
        command = dict(command, gripper=gripper) if gripper else command
        for _ in range(repeat):
            state, _ = teleop_step(state, scene, command, DT)
            assert collisions(state, scene) == []


def test_drop_and_retry():
    scene = build_scene("low", 12)
    state = teleop_start_state(scene)
    while state.item.mode != ItemMode.GRASPED:
        state, _ = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
    for _ in range(10):
        state, _ = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
    held_z = state.item.position[2]
    state, events = teleop_step(state, scene, {"gripper": "open"}, DT)
    assert events == ("dropped",) and state.item.mode == ItemMode.DROPPED
    dropped_at = state.item.since
    state, _ = teleop_step(state, scene, {}, 0.2)
    assert state.item.position[2] < held_z  # falling
    state, _ = teleop_step(state, scene, {}, 0.5)
    assert state.item.position[2] == pytest.approx(state.item.rest_z)
    seen = []
    while state.t < dropped_at + K.RESPAWN_DELAY + 0.1:
        state, events = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
        seen += events
    assert seen == ["item_reset"]
    assert state.item.mode == ItemMode.ON_SHELF
    np.testing.assert_allclose(state.item.position, scene.target.center)
    state, events = _run_scripted(scene, state, limit=state.t + 20.0)
    assert "deposited" in events


def test_closing_far_from_the_item_grasps_nothing():
    scene = build_scene("low", 1)
    state, events = teleop_step(teleop_start_state(scene), scene, {"gripper": "close"}, DT)
    assert events == () and state.item.mode == ItemMode.ON_SHELF and state.gripper_target == 0.0
    state, _ = teleop_step(state, scene, {"gripper": "toggle"}, DT)
    assert state.gripper_target == K.GRIPPER_MAX


def test_speeds_are_clamped():
    scene = build_scene("low", 1)
    start = teleop_start_state(scene)
    state, _ = teleop_step(start, scene, {"ee_velocity": [0.0, 50.0, 0.0]}, DT)
    moved = tcp_position(state.base, state.joints) - tcp_position(start.base, start.joints)
    assert np.linalg.norm(moved) <= K.MAX_EE_SPEED * DT * 1.02
    state, _ = teleop_step(start, scene, TeleopCommand(joint_velocity=(9.0, 0.0, 0.0, 0.0)), DT)
    assert state.joints[0] - start.joints[0] == pytest.approx(K.MAX_JOINT_SPEED * DT)


@pytest.mark.parametrize("command", [
    {"ee_velocity": [0.1, 0.0]},
    {"ee_velocity": [0.1, 0.0, math.nan]},
    {"ee_velocity": [0.1, 0.0, math.inf]},
    {"ee_velocity": ["0.1", 0.0, 0.0]},
    {"ee_velocity": [True, 0.0, 0.0]},
    {"ee_velocity": "fast"},
    {"joint_velocity": [0.1, 0.0, 0.0]},
    {"ee_velocity": [0.1, 0.0, 0.0], "joint_velocity": [0.0, 0.0, 0.0, 0.0]},
    {"gripper": "squeeze"},
    {"speed": 3},
    [0.1, 0.0, 0.0],
    None,
])
def test_invalid_commands_raise(command):
    scene = build_scene("low", 0)
    with pytest.raises(ValueError):
        teleop_step(teleop_start_state(scene), scene, command, DT)


@pytest.mark.parametrize("dt", [0.0, -0.1, math.nan, math.inf, 10.0, "0.1", True])
def test_invalid_dt_raises(dt):
    scene = build_scene("low", 0)
    with pytest.raises(ValueError, match="dt"):
        teleop_step(teleop_start_state(scene), scene, {}, dt)


def test_teleop_is_deterministic():
    scene = build_scene("high", 2)
    a, _ = _run_scripted(scene, check=False)
    b, _ = _run_scripted(build_scene("high", 2), check=False)
    assert a == b


def _held(scene):
    state = teleop_start_state(scene)
    while state.item.mode != ItemMode.GRASPED:
        state, _ = teleop_step(state, scene, scripted_teleop_commands(state, scene), DT)
    return state


def test_toggle_releases_a_held_item_of_any_width():
    scenes = [build_scene(complexity, seed) for complexity in ("low", "high") for seed in range(3)]
    assert any(scene.target.width > K.GRIPPER_MAX / 2 for scene in scenes)  # held fingers look "more open than closed"
    for scene in scenes:
        state, events = teleop_step(_held(scene), scene, {"gripper": "toggle"}, DT)
        assert state.item.mode != ItemMode.GRASPED and state.gripper_target == K.GRIPPER_MAX
        assert events in (("dropped",), ("deposited",))
        state, _ = teleop_step(state, scene, {"gripper": "toggle"}, DT)
        assert state.gripper_target == 0.0  # toggling again closes the empty gripper


def test_the_gripper_stays_in_its_workspace_and_can_come_back():
    """Holding Up or Forward stops at the workspace's edge instead of straightening the arm into a singular pose,
    and the opposite key brings the gripper straight back."""
    from experiment.world.robot import mast_xy
    from experiment.world.teleop import hold_command

    scene = build_scene("low", 1)
    state = teleop_start_state(scene)
    up, _ = hold_command(state, scene, TeleopCommand(ee_velocity=(0.0, 0.0, 0.3)), 6.0)
    top = tcp_position(up.base, up.joints)
    assert top[2] <= K.TCP_MAX_Z + 0.02 and up.joints[2] < -0.5  # the elbow stays bent
    down, _ = hold_command(up, scene, TeleopCommand(ee_velocity=(0.0, 0.0, -0.2)), 1.0)
    below = tcp_position(down.base, down.joints)
    assert below[2] == pytest.approx(top[2] - 0.2, abs=0.01) and np.allclose(below[:2], top[:2], atol=0.01)
    out, _ = hold_command(state, scene, TeleopCommand(ee_velocity=(0.3, 0.0, 0.0)), 6.0)
    mx, my = mast_xy(out.base)
    far = tcp_position(out.base, out.joints)
    assert np.hypot(far[0] - mx, far[1] - my) <= K.TCP_MAX_REACH + 0.02
