import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiment.world import constants as K
from experiment.world.geometry import quat_rotate
from experiment.world.robot import LOWER, UPPER, arm_points, ik_step, jacobian, link_frames, solve_ik, tcp_position

BASE = (1.5, -0.2, 0.3)
joints_in_limits = st.tuples(*[st.floats(lo, hi) for lo, hi in zip(K.JOINT_LOWER, K.JOINT_UPPER, strict=True)])
# TCP targets in the working region: radius from the mast, heading, height
workspace = st.tuples(st.floats(0.25, 0.7), st.floats(-2.5, 2.5), st.floats(0.5, 1.2))
unit_dirs = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.2)


def _point(rho, heading, z, base=BASE):
    mx, my = arm_points(base, np.zeros(4)).mast[:2]
    return np.array([mx + rho * math.cos(heading), my + rho * math.sin(heading), z])


def test_link_frames_chain_is_consistent():
    q = np.array([0.4, 0.9, -1.4, -0.8])
    frames = link_frames(BASE, q, 0.06)
    for parent, child, length in (("/robot/j2", "/robot/j3", K.UPPER_ARM),
                                  ("/robot/j3", "/robot/j4", K.FOREARM),
                                  ("/robot/j4", "/robot/palm", K.WRIST_LINK)):
        p, quat = frames[parent]
        expected = np.add(p, quat_rotate(quat, (length, 0.0, 0.0)))
        np.testing.assert_allclose(frames[child][0], expected, atol=1e-12)
    palm, quat = frames["/robot/palm"]
    np.testing.assert_allclose(tcp_position(BASE, q), np.add(palm, quat_rotate(quat, (K.TCP_OFFSET, 0, 0))))
    left, right = frames["/robot/finger_left"][0], frames["/robot/finger_right"][0]
    assert math.dist(left, right) == pytest.approx(0.06 + 2 * K.FINGER_RADIUS)
    for p, quat in frames.values():
        assert len(p) == 3 and np.linalg.norm(quat) == pytest.approx(1.0)


def test_shoulder_sits_on_the_mast_axis_above_the_base():
    frames = link_frames(BASE, np.zeros(4), 0.1)
    np.testing.assert_allclose(frames["/robot/j2"][0][:2], frames["/robot/mast"][0][:2])
    assert frames["/robot/j2"][0][2] == K.SHOULDER_Z


@settings(max_examples=60, deadline=None)
@given(joints_in_limits, st.floats(-math.pi, math.pi))
def test_jacobian_matches_finite_differences(q, yaw):
    q = np.array(q)
    base = (0.3, 0.1, yaw)
    eps = 1e-6
    numeric = np.column_stack([(tcp_position(base, q + eps * e) - tcp_position(base, q - eps * e)) / (2 * eps)
                               for e in np.eye(4)])
    np.testing.assert_allclose(jacobian(q, yaw), numeric, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(workspace)
def test_closed_form_ik_reaches_the_point_with_the_tool_down(target):
    p = _point(*target)
    q = solve_ik(BASE, p)
    assert q is not None
    np.testing.assert_allclose(tcp_position(BASE, q), p, atol=1e-9)
    assert sum(arm_points(BASE, q).pitches[2:]) == pytest.approx(K.TOOL_PITCH)
    assert np.all(q >= LOWER) and np.all(q <= UPPER)


def test_ik_returns_none_out_of_reach():
    assert solve_ik(BASE, _point(1.5, 0.0, 1.0)) is None


@settings(max_examples=80, deadline=None)
@given(workspace, unit_dirs, st.floats(0.02, K.MAX_EE_SPEED))
def test_ik_step_moves_the_tcp_in_the_commanded_direction(target, direction, speed):
    q = solve_ik(BASE, _point(*target))
    v = np.array(direction) / np.linalg.norm(direction) * speed
    dt = 1 / 30
    q2 = ik_step(q, v, dt, base_yaw=BASE[2])
    step = tcp_position(BASE, q2) - tcp_position(BASE, q)
    if np.any(np.isclose(q2, LOWER) | np.isclose(q2, UPPER)):
        assert step @ v >= 0  # a limit may stop it, never reverse it
        return
    assert step @ v / (np.linalg.norm(step) * speed) > 0.95
    assert np.linalg.norm(step) == pytest.approx(speed * dt, rel=0.1)


@settings(max_examples=40, deadline=None)
@given(joints_in_limits, unit_dirs, st.floats(0.0, 50.0))
def test_ik_step_respects_joint_limits_and_speeds(q, direction, speed):
    q = np.array(q)
    v = np.array(direction) / np.linalg.norm(direction) * speed
    dt = 1 / 30
    for _ in range(40):
        q2 = ik_step(q, v, dt)
        assert np.all(q2 >= LOWER) and np.all(q2 <= UPPER)
        assert np.all(np.abs(q2 - q) <= K.MAX_JOINT_SPEED * dt + 1e-12)
        q = q2


def test_ik_step_clamps_the_tcp_speed():
    q = solve_ik(BASE, _point(0.45, 0.0, 0.9))
    dt = 1 / 30
    step = tcp_position(BASE, ik_step(q, (5.0, 0.0, 0.0), dt, BASE[2])) - tcp_position(BASE, q)
    assert np.linalg.norm(step) <= K.MAX_EE_SPEED * dt * 1.02


def test_ik_step_brings_the_gripper_back_to_pointing_down():
    q = np.array([0.0, 0.8, -1.5, 0.3])
    for _ in range(90):
        q = ik_step(q, (0.0, 0.0, 0.0), 1 / 30)
    assert float(q[1] + q[2] + q[3]) == pytest.approx(K.TOOL_PITCH, abs=0.01)
