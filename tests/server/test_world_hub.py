"""The server's live worlds: attempt playback, teleoperation stepping, rate limit, frames."""

import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from experiment.engine import PlannedTrial
from experiment.flow import TrialRef
from experiment.task import Complexity
from experiment.world import scripted_teleop_commands
from server.settings import Settings
from server.world.hub import WorldHub
from server.world.playback import world_frame
from server.world.teleop import TrialKey

ROOT = Path(__file__).resolve().parents[2]
PLANNED = PlannedTrial(1, "trust_aware", 3, 3, 1, False, Complexity.HIGH)


def test_attempt_playback_follows_the_planned_trajectory():
    hub = WorldHub(Settings())
    info = hub.attempt(7, "P1", PLANNED, True, started_ago_s=0.0, speed=2.0)
    attempt = hub.attempts.get(7, "P1", PLANNED, True)
    assert info.duration_s == attempt.duration and info.failure_mode is None
    start = hub.playbacks.get("P1").start
    worlds = hub.tick(now=start + 1.5)
    expected = attempt.state_at(3.0)
    assert np.allclose(worlds["P1"].state.joints, expected.joints) and worlds["P1"].state.base == expected.base
    assert worlds["P1"].scene_seed == attempt.scene.seed


def test_a_participant_has_one_live_world():
    hub = WorldHub(Settings())
    first, second = TrialKey("P1", TrialRef(False, 1, 3)), TrialKey("P1", TrialRef(False, 1, 4))
    teleop = hub.teleop(first, hub.scene(1, "P1", PLANNED))
    assert hub.world_of("P1").scene_seed == teleop.scene.seed
    later = hub.teleop(second, hub.scene(1, "P1", PlannedTrial(1, "trust_aware", 4, 4, 1, False, Complexity.LOW)))
    assert len(hub.arms) == 1 and hub.world_of("P1").scene_seed == later.scene.seed != teleop.scene.seed
    hub.arms.end(first)  # ending an older teleoperation leaves the newer one alone
    assert len(hub.arms) == 1
    hub.teleop_over("P1", TrialRef(False, 1, 4))
    assert len(hub.arms) == 0 and hub.world_of("P1") is None
    hub.teleop(first, teleop.scene)
    hub.attempt(1, "P1", PLANNED, True, started_ago_s=0.0, speed=1.0)  # a new attempt replaces it
    assert len(hub.arms) == 0 and set(hub.tick()) == {"P1"}


def test_tick_listeners_get_every_world():
    hub = WorldHub(Settings())
    seen: list[dict] = []
    hub.add_tick_listener(seen.append)
    hub.attempt(7, "P1", PLANNED, False, started_ago_s=0.0, speed=1.0)
    hub.tick()
    hub.remove_tick_listener(seen.append)
    hub.tick()
    assert len(seen) == 1 and set(seen[0]) == {"P1"}


def test_scene_is_deterministic_and_obstacles_only_in_high_complexity():
    hub = WorldHub(Settings())
    high = hub.scene(1, "P1", PLANNED)
    assert high.obstacles and hub.scene(1, "P1", PLANNED).target_slot == high.target_slot
    low = hub.scene(1, "P1", PlannedTrial(1, "trust_aware", 3, 3, 1, False, Complexity.LOW))
    assert low.obstacles == ()


def test_held_inputs_move_the_arm_to_a_deposit():
    hub = WorldHub(Settings())
    key = TrialKey("P1", TrialRef(False, 1, 3))
    session = hub.teleop(key, hub.scene(1, "P1", PLANNED))
    now, events = session.advanced_at, ()
    for seq in range(3000):
        command = scripted_teleop_commands(session.state, session.scene)
        now += 1 / 30
        hub.arms.advance(session, now)
        events = hub.arms.set_input(session, command, seq=seq, client_ms=None,
                               now=now)
        if "deposited" in events:
            break
    assert "deposited" in events


def test_rate_limit_refuses_bursts():
    hub = WorldHub(Settings())
    session = hub.teleop(TrialKey("P1", TrialRef(True, 0, 1)), hub.scene(1, "P1", PLANNED))
    allowed = [hub.arms.allow(session, now=100.0) for _ in range(30)]
    assert sum(allowed) == 10  # the burst, then refused until tokens refill
    assert hub.arms.allow(session, now=100.1)


def test_subscribers_get_the_newest_frame():
    # asyncio.Queue's non-blocking calls need no running loop (and another test's loop may be running).
    hub = WorldHub(Settings())
    hub.attempt(7, "P1", PLANNED, False, started_ago_s=0.0, speed=1.0)
    queue = hub.subscribe("P1")
    hub.tick()
    hub.tick()
    frame = queue.get_nowait()
    assert queue.empty() and "/robot/j1" in frame["poses"]
    hub.unsubscribe("P1", queue)
    assert "P1" not in hub._subscribers


def test_frame_is_json_ready():
    hub = WorldHub(Settings())
    attempt = hub.attempts.get(7, "P1", PLANNED, True)
    frame = world_frame(attempt.state_at(1.0))
    assert set(frame) >= {"t", "base", "joints", "item", "poses"}


def test_attempts_are_planned_once_and_ahead_of_time():
    hub = WorldHub(Settings())
    hub.attempts.prepare(7, "P1", PLANNED, True)
    planned = hub.attempts.get(7, "P1", PLANNED, True)
    # the same trial reached through another route (the row's view of it) gets the same plan
    assert hub.attempts.get(7, "P1", replace(PLANNED, shelf_end=not PLANNED.shelf_end), True) is planned
    assert hub.attempts.get(7, "P1", PLANNED, False) is not planned
    fresh = WorldHub(Settings()).attempts.get(7, "P1", PLANNED, True)
    assert fresh.duration == planned.duration and np.allclose(fresh.joints, planned.joints)


def test_attempts_planned_ahead_in_a_helper_process_are_the_ones_planned_here():
    helper, here = WorldHub(Settings(planner_processes=1)), WorldHub(Settings(planner_processes=0))
    try:
        trials = [replace(PLANNED, trial=n, complexity=c) for n, c in ((1, Complexity.HIGH), (2, Complexity.LOW))]
        for planned in trials:
            helper.attempts.prepare(7, "P1", planned, False)
            helper.attempts.prepare(7, "P1", planned, False)  # asked twice, planned once
        assert len(helper.attempts._planning) <= 2
        deadline = time.monotonic() + 60
        while len(helper.attempts._cache) < len(trials) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(helper.attempts._cache) == len(trials) and not helper.attempts._planning, (
            "the helper process delivered nothing")
        for planned in trials:
            delivered = helper.attempts.get(7, "P1", planned, False)
            planned_here = here.attempts.get(7, "P1", planned, False)
            assert delivered.failure_mode == planned_here.failure_mode and delivered.outcome == planned_here.outcome
            assert np.array_equal(delivered.joints, planned_here.joints) and np.array_equal(delivered.base,
                                                                                          planned_here.base)
            assert delivered.scene.seed == planned_here.scene.seed and delivered.events == planned_here.events
    finally:
        helper.close()
    assert helper.attempts._pool is None


def test_planner_processes_end_with_a_killed_server():
    server = subprocess.Popen([sys.executable, "-c", "import os, sys, time\n"
                               "from server.settings import Settings\n"
                               "from server.world.hub import WorldHub\n"
                               "hub = WorldHub(Settings(planner_processes=1))\n"
                               "print(hub.attempts._planner_pool().submit(os.getpid).result(), flush=True)\n"
                               "time.sleep(600)"], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        helper = int(server.stdout.readline())
        os.kill(helper, 0)  # alive
    finally:
        server.kill()
        server.wait()
        server.stdout.close()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and _alive(helper):
        time.sleep(0.1)
    assert not _alive(helper), "the planner process outlived the server that was killed"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    status = Path(f"/proc/{pid}/stat")
    return not (status.exists() and status.read_text().rsplit(")", 1)[1].split()[0] == "Z")  # a zombie has ended


def test_a_stalled_world_loop_does_not_make_up_the_ticks_it_missed():
    """After the event loop was held for half a second, the loop ticks on at its rate (the arms move by the clock)
    instead of running the 15 missed ticks back to back on a congested loop."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    async def run() -> tuple[int, float]:
        hub = WorldHub(Settings())
        loop_task = asyncio.create_task(hub.run())
        await asyncio.sleep(0.1)
        time.sleep(0.5)  # the event loop is held (a long request, a collection pause)
        before = hub.ticks
        await asyncio.sleep(0)  # the loop's own wake-up runs: one late tick
        await asyncio.sleep(0.01)
        burst = hub.ticks - before
        late = hub.late_s
        loop_task.cancel()
        return burst, late

    with ThreadPoolExecutor(1) as pool:  # a loop of its own: an earlier test may leave one running in this thread
        burst, late = pool.submit(asyncio.run, run()).result()
    assert late > 0.4 and burst <= 2


# -- the physics helper process (server.world.physics) ----------------------------------------------------------------

def _held_arms(hub: WorldHub, n: int, now: float) -> list:
    """``n`` teleoperations, each holding the end effector moving sideways from ``now``, arm i at ``_speed(i)``."""
    from experiment.world.teleop import TeleopCommand

    arms = []
    for i in range(n):
        planned = PlannedTrial(1, "trust_aware", 3 + i, 3 + i, 1, False, Complexity.LOW)
        session = hub.teleop(TrialKey(f"P{i}", TrialRef(False, 1, 3 + i)), hub.scene(1, f"P{i}", planned))
        session.advanced_at = session.last_message = now
        hub.arms.set_input(session, TeleopCommand(ee_velocity=(0.0, _speed(i), 0.0)), seq=0, client_ms=None, now=now)
        arms.append(session)
    return arms


def _speed(i: int) -> float:
    return 0.02 + 0.015 * i


def test_the_physics_helper_computes_what_the_server_computes():
    from experiment.world.teleop import HeldMove, TeleopCommand, hold_moves
    from server.world.physics import SceneShipments, advance_arms

    hub = WorldHub(Settings(planner_processes=0))
    arms = _held_arms(hub, 3, time.monotonic())
    moves = (HeldMove(TeleopCommand(ee_velocity=(0.0, 0.05, 0.0)), 0.1), HeldMove(TeleopCommand(), 0.05, True))
    shipments = SceneShipments()
    jobs = [shipments.job(arm.scene_id, arm.scene, arm.state, arm.rules, moves) for arm in arms]
    assert all(job.scene is not None for job in jobs)
    expected = [hold_moves(arm.state, arm.scene, moves, arm.rules) for arm in arms]
    assert advance_arms(jobs) == expected
    again = [shipments.job(arm.scene_id, arm.scene, arm.state, arm.rules, moves) for arm in arms]
    assert all(job.scene is None for job in again)  # sent once; the helper keeps it
    assert advance_arms(again) == expected


def test_an_arm_a_message_moved_during_the_helpers_batch_keeps_that_advance():
    """The event loop runs while the helper computes: a message that advances an arm meanwhile (here a release)
    wins, and the helper's stale result for that arm is dropped; the other arms take theirs."""
    import asyncio
    from concurrent.futures import Executor, Future, ThreadPoolExecutor

    hub = WorldHub(Settings(planner_processes=0, physics_helper_min_ms=0))
    hub.ticking = True
    t0 = time.monotonic() - 1.0
    arms = _held_arms(hub, 2, t0)
    tick_at = t0 + 1 / 30

    class MessageDuringTheBatch(Executor):
        def submit(self, fn, *args):
            hub.arms.release(arms[0], now=tick_at + 0.01)  # arrives while the helper computes
            future: Future = Future()
            future.set_result(fn(*args))
            return future

    hub.physics.pool = lambda: MessageDuringTheBatch()  # type: ignore[method-assign]
    released = {}

    async def run() -> None:
        await hub.physics.advance(tick_at)

    original_release = hub.arms.release

    def release(session, now=None):
        original_release(session, now)
        released["state"] = session.state

    hub.arms.release = release  # type: ignore[method-assign]
    with ThreadPoolExecutor(1) as pool:  # a loop of its own: an earlier test may leave one running in this thread
        pool.submit(asyncio.run, run()).result()
    assert hub.physics.batches == 1
    assert arms[0].state is released["state"] and arms[0].advanced_at == tick_at + 0.01  # the message's advance
    assert arms[1].advanced_at == tick_at and arms[1].state.t > 0  # the helper's


def test_the_world_loop_moves_many_arms_in_the_physics_helper_process():
    """With the world loop running and enough arms held, the helper process moves them, as far as the held input
    moves them in the time it was held (less any time logged as lost)."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from experiment.world import teleop_start_state
    from experiment.world.robot import arm_points

    hub = WorldHub(Settings(planner_processes=0, physics_helper_min_ms=0))
    held_s = 2.5

    async def run() -> float:
        loop_task = asyncio.create_task(hub.run())
        start = time.monotonic()
        arms = _held_arms(hub, 4, start)
        while time.monotonic() - start < held_s:
            await asyncio.sleep(0.2)
            for arm in arms:
                hub.arms.keepalive(arm)  # as the page does while a key is held
        from experiment.world.teleop import TeleopCommand
        for arm in arms:
            hub.arms.set_input(arm, TeleopCommand(), seq=1, client_ms=None)
        loop_task.cancel()
        return start

    try:
        with ThreadPoolExecutor(1) as pool:
            pool.submit(asyncio.run, run()).result()
        assert hub.physics.batches > 10
        for i, arm in enumerate(hub.arms):
            log = arm.log.take()
            lost_ms = sum(entry.get("lost_ms", 0.0) for entry in log)
            held_ms = log[-1]["server_ms"] - log[0]["server_ms"] - lost_ms
            start = teleop_start_state(arm.scene)
            moved = arm_points(arm.state.base, arm.state.joints).tcp[1] - arm_points(start.base, start.joints).tcp[1]
            assert abs(moved - _speed(i) * held_ms / 1000) < 0.004, (i, moved, held_ms, log)
    finally:
        hub.close()


def test_when_the_physics_helper_fails_the_server_moves_the_arms_itself():
    import asyncio
    from concurrent.futures import Executor, ThreadPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    hub = WorldHub(Settings(planner_processes=0, physics_helper_min_ms=0))
    hub.ticking = True
    t0 = time.monotonic() - 1.0
    arms = _held_arms(hub, 2, t0)

    class DeadHelper(Executor):
        def submit(self, fn, *args):
            raise BrokenProcessPool("the helper process died")

    hub.physics.pool = lambda: DeadHelper()  # type: ignore[method-assign]
    with ThreadPoolExecutor(1) as pool:  # a loop of its own: an earlier test may leave one running in this thread
        pool.submit(asyncio.run, hub.physics.advance(t0 + 1 / 30)).result()
    assert hub.physics.batches == 0 and not hub.physics.in_flight
    assert hub.physics.start(t0 + 2 / 30) is None  # not again before PHYSICS_RETRY_S
    before = [arm.state for arm in arms]
    hub.tick(t0 + 2 / 30)
    assert all(arm.state != state and arm.advanced_at == t0 + 2 / 30 for arm, state in zip(arms, before, strict=True))


def test_the_helper_takes_a_ticks_arms_when_moving_them_here_would_take_long_enough():
    """Where a tick's arms move is decided by what moving them here takes (measured: here, then in the helper), not
    by a fixed number of arms: below ``physics_helper_min_ms`` the round trip costs more than it saves."""
    import asyncio
    from concurrent.futures import Executor, Future, ThreadPoolExecutor

    hub = WorldHub(Settings(planner_processes=0, physics_helper_min_ms=2.0))
    hub.ticking = True
    t0 = time.monotonic() - 1.0
    arms = _held_arms(hub, 3, t0)
    submitted = []

    class Helper(Executor):  # runs the helper's function in place
        def submit(self, fn, *args):
            submitted.append(len(args[0]))
            future: Future = Future()
            future.set_result(fn(*args))
            return future

    hub.physics.pool = lambda: Helper()  # type: ignore[method-assign]
    assert hub.arms.arm_move_s is None and hub.physics.start(t0 + 1 / 30) is None  # nothing measured yet
    hub.tick(t0 + 1 / 30)  # the arms move here, and that is measured
    assert hub.arms.arm_move_s is not None and hub.arms.arm_move_s > 0 and not submitted
    hub.arms.arm_move_s = 0.0006  # three arms: 1.8 ms here
    assert hub.physics.start(t0 + 2 / 30) is None
    hub.arms.arm_move_s = 0.0007  # 2.1 ms
    with ThreadPoolExecutor(1) as pool:  # a loop of its own: an earlier test may leave one running in this thread
        pool.submit(asyncio.run, hub.physics.advance(t0 + 2 / 30)).result()
    assert submitted == [3] and hub.physics.batches == 1
    assert all(arm.advanced_at == t0 + 2 / 30 for arm in arms)
    assert hub.arms.arm_move_s != 0.0007  # the helper's time, per arm, went into the measure
