"""What a replay is made of: the trial's record as the database holds it (``TrialRecord``), and the rebuilt trial
(``Replay``: its phases, moments, camera presets, the robot over time, and what is missing)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from experiment.flow import TrialRef
from experiment.task import HumanAction, Outcome, RobotAction
from experiment.world import constants as K
from experiment.world.attempt import Attempt, FailureMode
from experiment.world.path import ready_joints
from experiment.world.resimulate import END_SLACK_S, Resimulation, TeleopClock
from experiment.world.scene import Scene
from experiment.world.state import WorldState, as_joints, shelf_item_state
from experiment.world.teleop import teleop_start_state

#: A re-simulated event this close (s) to the logged one is the same event.
EVENT_TOLERANCE_S = 0.5


@dataclass(frozen=True)
class LogBatch:
    """One ``teleop_log`` event: its entries, and when it was written (s since the trial started; None: unknown)."""

    entries: tuple[Mapping[str, Any], ...]
    written_s: float | None = None


@dataclass(frozen=True)
class CameraChange:
    t: float  # s since the trial started
    view: str  # world | local | end_effector


@dataclass(frozen=True)
class TrialRecord:
    """What the database holds of one trial. Times are seconds since the trial started (None: not reached)."""

    study_seed: int
    participant_key: str
    ref: TrialRef
    block_name: str
    complexity: str
    robot_action: RobotAction
    human_action: HumanAction | None
    outcome: Outcome | None
    failure_mode: FailureMode | None
    animation_speed: float
    clock: TeleopClock  # how the teleoperation's time ran
    scene_shown_s: float | None = None
    scene_shown_view: str | None = None
    window_opened_s: float | None = None
    window_opened_by: str | None = None
    decided_s: float | None = None
    decision_time_ms: float | None = None
    attempt_end_s: float | None = None
    teleop_deadline_s: float | None = None
    teleop_success: bool | None = None
    teleop_time_ms: float | None = None
    completed_s: float | None = None
    logs: tuple[LogBatch, ...] = ()
    retries_s: tuple[float, ...] = ()  # a guided practice's new tries began
    camera: tuple[CameraChange, ...] = ()
    initial_view: str = "world"


@dataclass(frozen=True)
class Moment:
    t: float
    kind: str
    text: str


@dataclass(frozen=True)
class Phase:
    kind: str  # announcement | decision | attempt | teleop | done
    start: float
    end: float


@dataclass(frozen=True)
class TeleopPart:
    """One teleoperation log (one arm from the ready pose), placed on the trial's clock at ``origin``."""

    origin: float
    end: float  # trial time up to which it is shown
    resim: Resimulation


@dataclass
class Replay:
    scene: Scene
    recorded: str  # the recorded outcome, in words
    reconstructed: str = ""
    missing: list[str] = field(default_factory=list)
    moments: list[Moment] = field(default_factory=list)
    phases: list[Phase] = field(default_factory=list)
    views: list[CameraChange] = field(default_factory=list)
    attempt: Attempt | None = None
    attempt_start: float = 0.0
    speed: float = 1.0
    parts: list[TeleopPart] = field(default_factory=list)
    teleop_start: float | None = None
    duration: float = 0.0

    @property
    def reproduced(self) -> bool:
        return not self.missing and self.reconstructed == self.recorded

    def stage_at(self, t: float) -> str:
        return next((p.kind for p in reversed(self.phases) if p.start <= t), "announcement")

    def state_at(self, t: float) -> WorldState:
        """The robot and item as the participant's 3D view showed them at trial time ``t``: at rest where the trial
        starts, then the attempt, or the arm parked at the shelf while teleoperated (``server.viewer.live``)."""
        if (part := next((p for p in reversed(self.parts) if p.origin <= t), None)) is not None:
            return part.resim.state_at(min(t, part.end + END_SLACK_S) - part.origin, teleop_start_state(self.scene))
        if self.teleop_start is not None and t >= self.teleop_start:
            return teleop_start_state(self.scene)
        if self.attempt is not None and t >= self.attempt_start:
            return self.attempt.state_at((t - self.attempt_start) * self.speed)
        return resting_state(self.scene)

    def view_at(self, t: float) -> str:
        return next((c.view for c in reversed(self.views) if c.t <= t), "world")


def resting_state(scene: Scene) -> WorldState:
    """The robot at the trial's start pose, arm ready, gripper open (``server.viewer.scene.start_state``)."""
    return WorldState(0.0, scene.start, as_joints(ready_joints()), K.GRIPPER_MAX, K.GRIPPER_MAX,
                      shelf_item_state(scene))


def recorded_outcome(record: TrialRecord) -> str:
    if record.human_action == HumanAction.RELY and record.outcome is not None:
        if record.outcome == Outcome.SUCCESS:
            return "the robot put the item in the bin"
        return f"the robot failed ({record.failure_mode or 'unknown mode'})"
    if record.teleop_success:
        return f"the participant deposited the item after {record.teleop_time_ms / 1000:.1f} s of teleoperation" \
            if record.teleop_time_ms is not None else "the participant deposited the item"
    if record.teleop_success is False:
        return "the item was not deposited within the time limit"
    return "not recorded"


def say_missing(replay: Replay, at: float, text: str) -> None:
    """What the reconstruction cannot show, said in the result and on the timeline where it begins."""
    replay.missing.append(text)
    replay.moments.append(Moment(at, "missing", text[0].upper() + text[1:]))

