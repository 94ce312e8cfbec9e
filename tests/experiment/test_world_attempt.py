import numpy as np
import pytest

from experiment.world import ItemMode, build_scene, collisions, plan_attempt
from experiment.world import constants as K
from experiment.world.attempt import choose_failure_mode
from experiment.world.state import over_bin_opening

FPS = 30


def _samples(attempt):
    return [attempt.state_at(t) for t in np.arange(0.0, attempt.duration + 1 / FPS, 1 / FPS)]


def _scenes(complexity, n):
    return [build_scene(complexity, (11, i)) for i in range(n)]


@pytest.mark.parametrize("complexity", ["low", "high"])
def test_successful_attempts_deposit_without_collision(complexity):
    slots = set()
    for i, scene in enumerate(_scenes(complexity, 12)):
        attempt = plan_attempt(scene, True, i)
        slots.add(scene.target_slot)
        assert attempt.outcome == "success" and attempt.failure_mode is None
        assert 6.0 <= attempt.duration <= 10.0
        assert attempt.arm_start_time < attempt.grasp_time < attempt.deposit_time < attempt.duration
        for state in _samples(attempt):
            assert collisions(state, scene) == [], state.t
        end = attempt.state_at(attempt.duration)
        assert end.item.mode == ItemMode.IN_BIN
        assert over_bin_opening(end.base, end.item.position)
        assert end.item.position[2] == pytest.approx(K.BIN_FLOOR + scene.target.height / 2)
    assert len(slots) >= 5


def test_item_follows_the_phases():
    scene = build_scene("low", 5)
    attempt = plan_attempt(scene, True, 0)
    assert attempt.state_at(attempt.grasp_time - 0.01).item.mode == ItemMode.ON_SHELF
    held = attempt.state_at((attempt.grasp_time + attempt.deposit_time) / 2)
    assert held.item.mode == ItemMode.GRASPED
    assert held.item.position[2] > scene.target.center[2] + 0.05  # lifted
    start, parked = attempt.state_at(0), attempt.state_at(attempt.arm_start_time)
    assert start.base == scene.start and parked.base == pytest.approx(scene.park)


def test_collision_failures_really_collide():
    for i, scene in enumerate(_scenes("high", 12)):
        attempt = plan_attempt(scene, False, i, failure_mode="collision")
        assert attempt.outcome == "failure" and attempt.failure_mode == "collision"
        t_hit = attempt.failure_time
        assert attempt.grasp_time < t_hit < attempt.duration
        hits = collisions(attempt.state_at(t_hit), scene)
        assert any("/obstacles/" in h for h in hits), hits
        for state in _samples(attempt):
            if state.t < t_hit - 1e-9:
                assert collisions(state, scene) == []
        after = attempt.state_at(t_hit + 0.5)
        assert after.joints == attempt.state_at(attempt.duration).joints  # the arm stopped
        end = attempt.state_at(attempt.duration).item
        assert end.mode == ItemMode.DROPPED
        assert end.position[2] == pytest.approx(end.rest_z) and end.position[2] < after.item.fall_from[2]


@pytest.mark.parametrize("complexity", ["low", "high"])
def test_drop_failures_drop_the_item_outside_the_bin(complexity):
    for i, scene in enumerate(_scenes(complexity, 8)):
        attempt = plan_attempt(scene, False, i, failure_mode="drop")
        assert attempt.failure_mode == "drop" and attempt.deposit_time is None
        t_drop = attempt.failure_time
        assert attempt.state_at(t_drop - 0.01).item.mode == ItemMode.GRASPED
        assert attempt.state_at(t_drop + 0.01).item.mode == ItemMode.DROPPED
        for state in _samples(attempt):
            assert collisions(state, scene) == []
        end = attempt.state_at(attempt.duration)
        assert end.item.mode == ItemMode.DROPPED
        assert end.item.position[2] == pytest.approx(end.item.rest_z)
        assert not over_bin_opening(end.base, end.item.position)
    low = build_scene("low", 1)
    dropped = plan_attempt(low, False, 0).state_at(1e9).item
    assert dropped.position[2] == pytest.approx(low.target.height / 2)  # on the floor


def test_failure_modes_follow_complexity():
    rng = np.random.default_rng(0)
    high, low = build_scene("high", 0), build_scene("low", 0)
    modes = [choose_failure_mode(high, rng) for _ in range(400)]
    assert 0.7 < modes.count("collision") / 400 < 0.9
    assert {choose_failure_mode(low, rng) for _ in range(100)} == {"drop"}
    assert plan_attempt(low, False, 3).failure_mode == "drop"
    with pytest.raises(ValueError, match="obstacles"):
        plan_attempt(low, False, 0, failure_mode="collision")
    with pytest.raises(ValueError, match="failure_mode"):
        plan_attempt(low, False, 0, failure_mode="explode")


def test_attempts_are_deterministic_and_state_at_is_pure():
    scene = build_scene("high", (2, 9))
    a = plan_attempt(scene, False, np.random.default_rng(5))
    b = plan_attempt(build_scene("high", (2, 9)), False, np.random.default_rng(5))
    assert a.events == b.events and a.failure_mode == b.failure_mode
    np.testing.assert_array_equal(a.joints, b.joints)
    t1, t2 = 5.3, 1.1
    first = a.state_at(t1)
    a.state_at(t2)
    assert a.state_at(t1) == first
    assert a.state_at(-3.0) == a.state_at(0.0)
    assert a.state_at(1e9) == a.state_at(a.duration)
