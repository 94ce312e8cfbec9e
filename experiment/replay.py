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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from experiment.flow import TrialRef
from experiment.task import HumanAction, Outcome, RobotAction
from experiment.world import constants as K
from experiment.world.attempt import Attempt, FailureMode
from experiment.world.path import ready_joints
from experiment.world.resimulate import END_SLACK_S, Resimulation, TeleopClock, resimulate
from experiment.world.scene import Scene
from experiment.world.state import WorldState, as_joints, shelf_item_state
from experiment.world.teleop import WorldEvent, teleop_start_state
from experiment.world.trial import trial_attempt, trial_scene

#: A re-simulated event this close (s) to the logged one is the same event.
EVENT_TOLERANCE_S = 0.5
#: The replay goes on this long after the trial's last moment.
TAIL_S = 1.0


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


def reconstruct(record: TrialRecord) -> Replay:
    """The trial's timeline, its robot over time, and the outcome the reconstruction reaches (module docstring)."""
    scene = trial_scene(record.study_seed, record.participant_key, record.block_name, record.ref.trial,
                        record.complexity)
    replay = Replay(scene, recorded_outcome(record), speed=record.animation_speed)
    _decision(record, replay)
    if record.human_action == HumanAction.RELY:
        _attempt(record, replay)
    elif record.human_action == HumanAction.INTERVENE:
        _teleop(record, replay)
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
        _missing(replay, last, f"the reconstruction ends in {replay.reconstructed}, not in the recorded outcome "
                               f"({replay.recorded}): what is shown is not what the participant saw")
    replay.views = [CameraChange(0.0, record.initial_view), *sorted(record.camera, key=lambda c: c.t)]
    replay.moments += [Moment(c.t, "camera", f"Camera: {c.view.replace('_', ' ')} view") for c in record.camera]
    replay.duration = max([last + TAIL_S] + [m.t + TAIL_S for m in replay.moments])
    replay.moments.sort(key=lambda m: m.t)
    return replay


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


def _teleop(record: TrialRecord, replay: Replay) -> None:
    entry = 0.0 if record.robot_action == RobotAction.ASK else (record.decided_s or 0.0)
    end = record.teleop_deadline_s
    runs = _runs(record, entry)
    if not runs:
        replay.missing.append("there is no teleoperation log of this trial")
        runs = [_Run(entry, [])]
    replay.teleop_start = entry
    replay.phases.append(Phase("teleop", entry, _teleop_end(record, runs) or end or entry))
    for k, run in enumerate(runs):
        last = k == len(runs) - 1
        until = (_teleop_end(record, runs) if last else runs[k + 1].origin) or run.origin + run.last_s
        part = _part(record, replay, run, until, last)
        replay.parts.append(part)
        _teleop_moments(replay, part, first=k == 0)
    final = replay.parts[-1].resim
    deposited = final.first(WorldEvent.DEPOSITED)
    if deposited is not None:
        replay.reconstructed = f"the participant deposited the item after {deposited:.1f} s of teleoperation"
    else:
        replay.reconstructed = "the item was not deposited within the time limit" if record.teleop_success is False \
            else "the item was not deposited"
    if record.teleop_success and record.teleop_time_ms is not None and deposited is not None \
            and abs(deposited - record.teleop_time_ms / 1000) <= EVENT_TOLERANCE_S:
        replay.reconstructed = replay.recorded  # the same deposit (its time on the log's clock, to the tolerance)
    if not replay.reproduced and not replay.missing:
        at = replay.parts[-1].origin + final.last_entry_s
        _missing(replay, at, f"the input log ends at {at:.1f} s; the recorded outcome ({replay.recorded}) is not "
                             "reproduced")
    if end is not None and record.teleop_success is False:
        replay.moments.append(Moment(end, "time_limit", "Time limit: the item was not deposited"))


@dataclass
class _Run:
    """The entries of one teleoperation log (its clock from 0), and where its 0 lies on the trial's clock."""

    origin: float
    entries: list[Mapping[str, Any]]
    origin_bound: float | None = None  # its latest possible origin, from when its entries were written

    @property
    def last_s(self) -> float:
        return max((float(e["server_ms"]) / 1000 for e in self.entries if _ms(e) is not None), default=0.0)


def _ms(entry: Mapping[str, Any]) -> float | None:
    value = entry.get("server_ms")
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _runs(record: TrialRecord, entry: float) -> list[_Run]:
    """The logs of the trial's teleoperations: a new one starts when the log's clock goes back (a new arm: the server
    restarted) or after a guided practice's new try."""
    runs: list[_Run] = []
    last_ms, tries = -1.0, -1
    for batch in record.logs:
        entries = [e for e in batch.entries if isinstance(e, Mapping) and _ms(e) is not None]
        if not entries:
            continue
        first, top = _ms(entries[0]) or 0.0, max(_ms(e) or 0.0 for e in entries)
        bound = None if batch.written_s is None else batch.written_s - top / 1000
        tried = sum(1 for r in record.retries_s if bound is not None and r < bound)
        if not runs or first < last_ms or tried != tries:
            origin = entry if not runs else max(record.retries_s[tried - 1] if tried > 0 else entry,
                                                bound if bound is not None else entry)
            runs.append(_Run(origin, [], bound))
        run = runs[-1]
        run.entries += entries
        if bound is not None:
            run.origin_bound = bound if run.origin_bound is None else min(run.origin_bound, bound)
        last_ms, tries = max(_ms(e) or 0.0 for e in entries), tried
    if runs and record.teleop_success and record.teleop_time_ms is not None and record.completed_s is not None:
        runs[-1].origin = record.completed_s - record.teleop_time_ms / 1000  # exact: the deposit's time is on its clock
    return runs


def _teleop_end(record: TrialRecord, runs: Sequence[_Run]) -> float | None:
    """When the teleoperation ended on the trial's clock: the deposit, or the time limit."""
    if record.teleop_success and record.teleop_time_ms is not None and runs:
        return runs[-1].origin + record.teleop_time_ms / 1000
    return record.teleop_deadline_s


def _part(record: TrialRecord, replay: Replay, run: _Run, until: float, last: bool) -> TeleopPart:
    """One log re-simulated up to ``until`` (trial time), or up to where the log stops when it is cut short."""
    resim = resimulate(replay.scene, run.entries, record.clock, until_s=max(0.0, until - run.origin))
    stopped = run.origin + resim.last_entry_s
    end = until
    if resim.incomplete is not None:
        end = run.origin + resim.incomplete[0]
        _missing(replay, end, f"the input log is incomplete from {end:.1f} s on "
                              f"({resim.incomplete[1].replace('_', ' ')}); what followed is not reconstructed")
    elif not last:
        end = stopped
        if not any(abs(r - until) < 1.0 for r in record.retries_s):
            _missing(replay, end, f"the input log ends at {end:.1f} s; at {until:.1f} s the arm was back at its ready "
                                  "pose (a new teleoperation: the server restarted); what happened in between is not "
                                  "in the log")
    elif record.teleop_success and resim.first(WorldEvent.DEPOSITED, logged=True) is None:
        end = stopped
        _missing(replay, end, f"the input log ends at {end:.1f} s, before the recorded deposit at {until:.1f} s; what "
                              "happened in between is not in the log")
    elif not record.teleop_success and resim.held_at_end:
        end = stopped  # a motion held and no stop logged after it: the log was cut
        _missing(replay, end, f"the input log ends at {end:.1f} s with a motion held and no stop after it (the log "
                              f"was cut short, e.g. the server stopped); what happened until {until:.1f} s is not in "
                              "the log")
    if end < until:
        resim.samples = [s for s in resim.samples if s[0] <= end - run.origin]
        resim.events = [e for e in resim.events if e[0] <= end - run.origin]
    _check_events(replay, resim, run.origin)
    return TeleopPart(run.origin, end, resim)


def _check_events(replay: Replay, resim: Resimulation, origin: float) -> None:
    """The world's events the re-simulation met must be the logged ones, at about the logged times."""
    met, logged = [e for _, e in resim.events], [e for _, e in resim.logged]
    if met[:len(logged)] != logged and met != logged[:len(met)]:
        _missing(replay, origin + (resim.logged or resim.events)[0][0],
                 f"the re-simulation diverges from the log: it meets {_names(met)}, the log has {_names(logged)}")
        return
    for (t_met, event), (t_logged, _) in zip(resim.events, resim.logged, strict=False):
        if abs(t_met - t_logged) > EVENT_TOLERANCE_S:
            _missing(replay, origin + t_logged,
                     f"the re-simulation meets {event} at {origin + t_met:.1f} s, the log at {origin + t_logged:.1f} s")
            return


def _names(events: Sequence[WorldEvent]) -> str:
    return ", ".join(events) if events else "no event"


EVENT_TEXT = {WorldEvent.ALIGNED: "The assistance aligns the gripper", WorldEvent.GRASPED: "Item grasped",
              WorldEvent.DROPPED: "Item dropped", WorldEvent.ITEM_RESET: "The item is back on its shelf",
              WorldEvent.DEPOSITED: "Item deposited in the bin"}
STOP_TEXT = {"deadman_stop": "Dead-man stop: no message from the page, the arm stops",
             "disconnect_stop": "The page disconnected: the arm stops", "fault_stop": "A server fault stopped the arm",
             "resumed": "The page is back: the held motion resumes"}


def _teleop_moments(replay: Replay, part: TeleopPart, *, first: bool) -> None:
    resim, at = part.resim, part.origin
    moments = replay.moments
    text = "Teleoperation: the participant takes the arm" if first else "A new teleoperation: the arm starts again"
    moments.append(Moment(at, "teleop_start", text))
    inputs = [c for t, c in resim.inputs if at + t <= part.end]
    motions = sum(c.moves for c in inputs)
    gripper = [(t, c) for t, c in resim.inputs if c.gripper is not None and at + t <= part.end]
    moments.append(Moment(at, "teleop_inputs", f"{len(inputs)} inputs: {motions} motions "
                          f"({sum(c.ee_velocity is not None for c in inputs)} of the hand, "
                          f"{sum(c.joint_velocity is not None for c in inputs)} of the joints), "
                          f"{len(gripper)} gripper actions"))
    moments += [Moment(at + t, "gripper", f"Gripper: {c.gripper}") for t, c in gripper]
    moments += [Moment(at + t, "stop", STOP_TEXT[s]) for t, s in resim.stops if at + t <= part.end]
    moments += [Moment(at + t, str(e), EVENT_TEXT[e]) for t, e in resim.events]
    if resim.lost_s > 0:
        moments.append(Moment(at, "server_lag", f"The server was late: the arm moved {resim.lost_s:.2f} s less "
                                                "than the input was held"))


def _missing(replay: Replay, at: float, text: str) -> None:
    """What the reconstruction cannot show, said in the result and on the timeline where it begins."""
    replay.missing.append(text)
    replay.moments.append(Moment(at, "missing", text[0].upper() + text[1:]))
