"""A trial reconstructed from what the database holds: its timeline, and the robot as the participant saw it.

Every trial's scene and autonomous attempt are deterministic in the study seed (``experiment.world.trial``) and the
teleoperation's input is logged (``experiment.world.resimulate``), so a ``TrialRecord`` (the trial's row, its
teleoperation log and camera events, times in seconds since the trial started) is enough to rebuild:

- the scene; the phases (the robot's announcement, the decision window from the moment the scene was shown, the
  autonomous attempt played at the study's animation speed, or the teleoperation re-simulated from its log);
- the moments worth listing (scene shown, Intervene pressed, the attempt's grasp and collision or drop, the
  teleoperation's gripper actions, stops and world events, the deposit or the time limit) and the camera presets;
- the outcome the reconstruction reaches, checked against the recorded one. Where it does not reach it (a log that
  ends early: a crash, a capped or lost log) ``missing`` says what is missing, and the reconstruction stops where
  the log stops instead of showing what did not happen.

Older data: a log's clock is placed on the trial's by the trial's times (exact for a deposit: ``teleop_time_ms`` is
on the log's clock) and, after a restart, by when its entries were written (within about a second).
"""

from __future__ import annotations

from experiment.replay.teleop import replay_teleop
from experiment.replay.timeline import (
    CameraChange,
    LogBatch,
    Moment,
    Phase,
    Replay,
    TeleopPart,
    TrialRecord,
    recorded_outcome,
    resting_state,
    say_missing,
)
from experiment.task import HumanAction, Outcome, RobotAction
from experiment.world.trial import trial_attempt, trial_scene

#: The replay goes on this long after the trial's last moment.
TAIL_S = 1.0

__all__ = ["CameraChange", "LogBatch", "Moment", "Phase", "Replay", "TeleopPart", "TrialRecord", "reconstruct",
           "recorded_outcome", "resting_state"]


def reconstruct(record: TrialRecord) -> Replay:
    """The trial's timeline, its robot over time, and the outcome the reconstruction reaches (module docstring)."""
    scene = trial_scene(record.study_seed, record.participant_key, record.block_name, record.ref.trial,
                        record.complexity)
    replay = Replay(scene, recorded_outcome(record), speed=record.animation_speed)
    _decision(record, replay)
    if record.human_action == HumanAction.RELY:
        _attempt(record, replay)
    elif record.human_action == HumanAction.INTERVENE:
        replay_teleop(record, replay)
    else:
        replay.reconstructed = "no decision recorded"
    last = max([p.end for p in replay.phases] + [m.t for m in replay.moments], default=0.0)
    if record.completed_s is not None:
        late = record.completed_s - last
        replay.moments.append(Moment(min(record.completed_s, last + TAIL_S / 2), "completed",
                                     f"Trial recorded: {replay.recorded}"
                                     + (f" (stored {late:.0f} s later)" if late > TAIL_S / 2 else "")))
    else:
        replay.missing.append("the trial has no recorded outcome (it did not finish)")
    if not replay.missing and replay.reconstructed != replay.recorded:
        say_missing(replay, last, f"the reconstruction ends in {replay.reconstructed}, not in the recorded outcome "
                                  f"({replay.recorded}): what is shown is not what the participant saw")
    replay.views = [CameraChange(0.0, record.initial_view), *sorted(record.camera, key=lambda c: c.t)]
    replay.moments += [Moment(c.t, "camera", f"Camera: {c.view.replace('_', ' ')} view") for c in record.camera]
    replay.duration = max([last + TAIL_S] + [m.t + TAIL_S for m in replay.moments])
    replay.moments.sort(key=lambda m: m.t)
    return replay


def _decision(record: TrialRecord, replay: Replay) -> None:
    moments = replay.moments
    if record.robot_action == RobotAction.ASK:
        moments.append(Moment(0.0, "announcement", "The robot asks the participant to collect the item"))
    else:
        moments.append(Moment(0.0, "announcement", "The robot announces it will collect the item by itself"))
    if record.scene_shown_s is not None:
        moments.append(Moment(record.scene_shown_s, "scene_shown",
                              f"Scene shown on the participant's screen ({record.scene_shown_view or '?'} view)"))
    opened, decided = record.window_opened_s, record.decided_s
    replay.phases.append(Phase("announcement", 0.0, opened if opened is not None else decided or 0.0))
    if opened is not None:
        by = "the wait limit: no proof the scene was shown" if record.window_opened_by == "wait_limit" \
            else f"the {record.window_opened_by} view's proof"
        moments.append(Moment(opened, "window_opened", f"Decision window opens (by {by})"))
        replay.phases.append(Phase("decision", opened, decided if decided is not None else opened))
    if decided is None or record.robot_action == RobotAction.ASK:
        return
    if record.human_action == HumanAction.RELY:
        moments.append(Moment(decided, "rely", "No intervention: the window closed, the robot tries"))
    elif record.human_action == HumanAction.INTERVENE:
        after = f" ({record.decision_time_ms:.0f} ms into the window)" if record.decision_time_ms is not None else ""
        moments.append(Moment(decided, "intervene", f"Intervene pressed{after}"))


ATTEMPT_MOMENTS = {"arm_start": "The robot parks; its arm starts", "grasp": "The robot grasps the item",
                   "collision": "The arm hits an obstacle", "drop": "The item slips out of the gripper",
                   "deposit": "The robot puts the item in the bin"}


def _attempt(record: TrialRecord, replay: Replay) -> None:
    """The autonomous attempt, planned again from the seeds, played from the decision at the animation speed."""
    start = record.decided_s or 0.0
    success = record.outcome == Outcome.SUCCESS
    attempt = trial_attempt(record.study_seed, record.participant_key, record.block_name, record.ref.trial,
                            record.complexity, success)
    replay.attempt, replay.attempt_start = attempt, start
    end = start + attempt.duration / record.animation_speed
    replay.phases.append(Phase("attempt", start, end))
    for name, text in ATTEMPT_MOMENTS.items():
        if (at := attempt.events.get(name)) is not None:
            replay.moments.append(Moment(start + at / record.animation_speed, f"attempt_{name}", text))
    replay.moments.append(Moment(end, "attempt_end", "The robot's attempt ends"))
    replay.reconstructed = ("the robot put the item in the bin" if attempt.outcome == "success"
                            else f"the robot failed ({attempt.failure_mode})")
    if record.attempt_end_s is not None and abs(record.attempt_end_s - end) > 0.01:
        replay.missing.append(f"the recorded attempt ends at {record.attempt_end_s:.2f} s, the planned one at "
                              f"{end:.2f} s: the attempt shown may not be the one the participant saw")

