"""A trial rebuilt from its record (``experiment.replay``): the attempt planned again from the seeds, the
teleoperation re-simulated from a log written as the server's clock writes it, and what a cut log is said to miss."""

from __future__ import annotations

from typing import Any

import pytest

from experiment.flow import TrialRef
from experiment.replay import TrialRecord, reconstruct, resting_state
from experiment.task import HumanAction, Outcome, RobotAction
from experiment.world import scripted_teleop_commands
from experiment.world.attempt import FailureMode
from experiment.world.resimulate import TeleopClock, resimulate
from experiment.world.teleop import TeleopCommand, WorldEvent, hold_command, teleop_start_state
from experiment.world.trial import trial_attempt, trial_scene

SEED, KEY, BLOCK = 11, "Ptest", "practice"
CLOCK = TeleopClock(speedup=2.0, gripper_action_s=0.001)


def record(**fields: Any) -> TrialRecord:
    base: dict[str, Any] = dict(study_seed=SEED, participant_key=KEY, ref=TrialRef(True, 0, 1), block_name=BLOCK,
                                complexity="high", robot_action=RobotAction.AUTO, human_action=None, outcome=None,
                                failure_mode=None, animation_speed=2.0, clock=CLOCK,
                                scene_shown_s=0.3, scene_shown_view="3d", window_opened_s=0.3,
                                window_opened_by="3d", decided_s=4.3)
    return TrialRecord(**(base | fields))


def live_log(complexity: str = "high", tick_s: float = 1 / 45, decide_s: float = 0.1,
             limit_s: float = 60.0) -> tuple[list[dict[str, Any]], float]:
    """A teleoperation as the server runs it: the scripted operator changes its input every ``decide_s`` (real s),
    the clock advances the arm every ``tick_s`` (not the re-simulation's step), inputs and world events logged with
    their times. Returns the entries and the deposit's time (s)."""
    scene = trial_scene(SEED, KEY, BLOCK, 1, complexity)
    state, held, now, entries = teleop_start_state(scene), TeleopCommand(), 0.0, []
    next_decision = 0.0
    while now < limit_s:
        if now >= next_decision - 1e-9:
            command = scripted_teleop_commands(state, scene)
            if command != held or command.gripper is not None:
                entries.append({"server_ms": round(now * 1000, 1), "input": command.as_dict()})
                if command.gripper is not None:
                    state, events = hold_command(state, scene, command, CLOCK.gripper_action_s * CLOCK.speedup)
                    entries += [{"server_ms": round(now * 1000, 1), "event": e} for e in events]
                    if WorldEvent.DEPOSITED in events:
                        return entries, now
                held = command.motion
            next_decision += decide_s
        state, events = hold_command(state, scene, held, tick_s * CLOCK.speedup)
        now += tick_s
        entries += [{"server_ms": round(now * 1000, 1), "event": e} for e in events if e != WorldEvent.BLOCKED]
    raise AssertionError("the scripted operator did not deposit")


@pytest.fixture(scope="module")
def logged() -> tuple[list[dict[str, Any]], float]:
    return live_log()


@pytest.mark.parametrize(("outcome", "mode"), [(Outcome.SUCCESS, None), (Outcome.FAILURE, FailureMode.COLLISION),
                                               (Outcome.FAILURE, FailureMode.DROP)])
def test_a_relied_on_attempt_is_planned_again_from_the_seeds(outcome, mode):
    attempt = trial_attempt(SEED, KEY, BLOCK, 1, "high", outcome == Outcome.SUCCESS)
    recorded_mode = attempt.failure_mode if mode is not None else None  # the seeds decide the mode of this one
    end = 4.3 + attempt.duration / 2.0
    replay = reconstruct(record(human_action=HumanAction.RELY, outcome=outcome, failure_mode=recorded_mode,
                                attempt_end_s=end, completed_s=end + 0.01))
    assert replay.reproduced, replay.missing
    assert [p.kind for p in replay.phases] == ["announcement", "decision", "attempt"]
    assert replay.state_at(1.0) == resting_state(replay.scene)  # at rest where the trial starts until the decision
    assert replay.state_at(end + 5) == attempt.state_at(attempt.duration)  # the last pose holds
    kinds = [m.kind for m in replay.moments]
    assert kinds[:4] == ["announcement", "scene_shown", "window_opened", "rely"] and kinds[-1] == "completed"
    assert ("attempt_deposit" in kinds) == (outcome == Outcome.SUCCESS)


def test_another_failure_mode_than_the_recorded_one_is_said_not_to_be_what_the_participant_saw():
    attempt = trial_attempt(SEED, KEY, BLOCK, 1, "high", False)
    other = FailureMode.DROP if attempt.failure_mode == FailureMode.COLLISION else FailureMode.COLLISION
    replay = reconstruct(record(human_action=HumanAction.RELY, outcome=Outcome.FAILURE, failure_mode=other,
                                completed_s=20.0))
    assert not replay.reproduced and "not what the participant saw" in replay.missing[0]


def test_a_log_re_simulated_at_another_step_split_meets_the_logged_events(logged):
    entries, deposit_s = logged
    scene = trial_scene(SEED, KEY, BLOCK, 1, "high")
    resim = resimulate(scene, entries, CLOCK, until_s=deposit_s)
    assert [e for _, e in resim.events] == [e for _, e in resim.logged] == [WorldEvent.GRASPED, WorldEvent.DEPOSITED]
    assert all(abs(a - b) < 1e-6 for (a, _), (b, _) in zip(resim.events, resim.logged, strict=True))
    assert resim.samples[-1][1].item.mode == "in_bin"


def teleop_record(entries: list[dict[str, Any]], deposit_s: float | None, *, limit_s: float = 60.0,
                  **fields: Any) -> TrialRecord:
    """An intervention at 4.3 s whose teleoperation log is ``entries`` (its clock starts with the intervention)."""
    from experiment.replay import LogBatch

    success = deposit_s is not None
    given: dict[str, Any] = dict(human_action=HumanAction.INTERVENE, outcome=Outcome.NONE, teleop_success=success,
                                 teleop_time_ms=deposit_s * 1000 if success else limit_s * 1000,
                                 teleop_deadline_s=4.3 + limit_s, completed_s=4.3 + (deposit_s or limit_s),
                                 logs=(LogBatch(tuple(entries), None),))
    return record(**(given | fields))


def test_an_intervention_is_re_simulated_to_the_recorded_deposit(logged):
    entries, deposit_s = logged
    replay = reconstruct(teleop_record(entries, deposit_s))
    assert replay.reproduced, replay.missing
    assert replay.state_at(4.3 + deposit_s + 0.5).item.mode == "in_bin"
    assert replay.state_at(4.29) == resting_state(replay.scene)  # the decision window: where the trial starts
    assert replay.state_at(4.3) == teleop_start_state(replay.scene)  # then parked at the shelf, the arm ready
    kinds = [m.kind for m in replay.moments]
    assert {"intervene", "teleop_start", "teleop_inputs", "gripper", "grasped", "deposited"} <= set(kinds)


def test_a_log_cut_short_says_what_is_missing_instead_of_inventing_it(logged):
    entries, deposit_s = logged
    cut = [e for e in entries if e["server_ms"] < 0.6 * deposit_s * 1000]  # the last second or so was never written
    replay = reconstruct(teleop_record(cut, deposit_s))
    assert not replay.reproduced
    last = cut[-1]["server_ms"] / 1000
    assert f"the input log ends at {4.3 + last:.1f} s" in replay.missing[0]
    assert any(m.kind == "missing" for m in replay.moments)
    # the arm is shown where the log leaves it, not moved on by an input no one can tell was still held
    assert replay.state_at(4.3 + deposit_s) == replay.state_at(4.3 + last)


def test_a_time_limit_failure_with_a_held_motion_and_no_stop_is_a_cut_log(logged):
    entries, deposit_s = logged
    cut = [e for e in entries if e["server_ms"] < 0.5 * deposit_s * 1000]
    assert "input" in cut[-1] or any("input" in e for e in cut)
    replay = reconstruct(teleop_record(cut, None))
    assert not replay.reproduced and "with a motion held and no stop" in replay.missing[0]
    stopped = [*cut, {"server_ms": cut[-1]["server_ms"] + 1, "event": "disconnect_stop"}]
    assert reconstruct(teleop_record(stopped, None)).reproduced  # the page left: the arm stood still until the limit


@pytest.mark.parametrize("why", ["log_capped", "log_lost"])
def test_a_capped_or_lost_log_says_so(logged, why):
    entries, deposit_s = logged
    half = len(entries) // 2
    replay = reconstruct(teleop_record([*entries[:half], {"server_ms": entries[half]["server_ms"], "event": why}],
                                       deposit_s))
    assert not replay.reproduced and why.replace("_", " ") in replay.missing[0]


def test_a_guided_practice_retry_starts_a_second_log_from_the_ready_pose(logged):
    """The first try ran out (the socket closed: a disconnect stop), the second deposited: two logs, each placed on
    the trial's clock (the retry, and the deposit's time on its own clock), nothing missing."""
    from experiment.replay import LogBatch

    entries, deposit_s = logged
    first = [*entries[:len(entries) // 3], {"server_ms": entries[len(entries) // 3]["server_ms"],
                                             "event": "disconnect_stop"}]
    retry, origin = 4.3 + 30.0, 4.3 + 30.4
    replay = reconstruct(teleop_record(entries, deposit_s, completed_s=origin + deposit_s, retries_s=(retry,),
                                       logs=(LogBatch(tuple(first), 4.3 + first[-1]["server_ms"] / 1000 + 0.4),
                                             LogBatch(tuple(entries), origin + deposit_s + 0.01))))
    assert replay.reproduced, replay.missing
    assert [p.origin for p in replay.parts] == [4.3, pytest.approx(origin)]
    assert replay.state_at(origin) == teleop_start_state(replay.scene)
    assert [m.kind for m in replay.moments].count("teleop_start") == 2


def test_a_log_whose_clock_starts_again_without_a_retry_says_the_server_restarted(logged):
    from experiment.replay import LogBatch

    entries, deposit_s = logged
    first = entries[:len(entries) // 3]  # cut: the server was killed, its last entries were never written
    origin = 4.3 + 20.0
    replay = reconstruct(teleop_record(entries, deposit_s, completed_s=origin + deposit_s,
                                       logs=(LogBatch(tuple(first), 4.3 + first[-1]["server_ms"] / 1000 + 0.4),
                                             LogBatch(tuple(entries), origin + deposit_s + 0.01))))
    assert replay.reconstructed == replay.recorded and not replay.reproduced
    assert "the server restarted" in replay.missing[0]


def test_the_camera_presets_the_participant_chose_are_replayed():
    from experiment.replay import CameraChange

    replay = reconstruct(record(human_action=HumanAction.RELY, outcome=Outcome.SUCCESS, completed_s=40.0,
                                initial_view="end_effector", camera=(CameraChange(5.0, "local"),)))
    assert [replay.view_at(t) for t in (0.0, 4.9, 5.0, 30.0)] == ["end_effector", "end_effector", "local", "local"]
    assert any(m.kind == "camera" and m.t == 5.0 and "local" in m.text for m in replay.moments)
