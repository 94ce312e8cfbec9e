"""The teleoperation of a rebuilt trial: its logs (one per arm from the ready pose) placed on the trial's clock,
re-simulated (``experiment.world.resimulate``), listed, and checked against the recorded deposit or time limit."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from experiment.replay.timeline import (
    EVENT_TOLERANCE_S,
    Moment,
    Phase,
    Replay,
    TeleopPart,
    TrialRecord,
    say_missing,
)
from experiment.task import RobotAction
from experiment.world.resimulate import Resimulation, resimulate
from experiment.world.teleop import WorldEvent


def replay_teleop(record: TrialRecord, replay: Replay) -> None:
    """The teleoperation phase: from the Intervene press (or the trial's start when the robot asked) to the deposit or
    the time limit, each log re-simulated where it lies on the trial's clock."""
    entry = 0.0 if record.robot_action == RobotAction.ASK else (record.decided_s or 0.0)
    end = record.teleop_deadline_s
    runs = _runs(record, entry)
    if not runs:
        say_missing(replay, entry, "there is no teleoperation log of this trial")
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
        say_missing(replay, at, f"the input log ends at {at:.1f} s; the recorded outcome ({replay.recorded}) is not "
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
        say_missing(replay, end, f"the input log is incomplete from {end:.1f} s on "
                                 f"({resim.incomplete[1].replace('_', ' ')}); what followed is not reconstructed")
    elif not last:
        end = stopped
        if not any(abs(r - until) < 1.0 for r in record.retries_s):
            say_missing(replay, end, f"the input log ends at {end:.1f} s; at {until:.1f} s the arm was back at its "
                                     "ready pose (a new teleoperation: the server restarted); what happened in between "
                                     "is not in the log")
    elif record.teleop_success and resim.first(WorldEvent.DEPOSITED, logged=True) is None:
        end = stopped
        say_missing(replay, end, f"the input log ends at {end:.1f} s, before the recorded deposit at {until:.1f} s; "
                                 "what happened in between is not in the log")
    elif not record.teleop_success and resim.held_at_end:
        end = stopped  # a motion held and no stop logged after it: the log was cut
        say_missing(replay, end, f"the input log ends at {end:.1f} s with a motion held and no stop after it (the "
                                 f"log was cut short, e.g. the server stopped); what happened until {until:.1f} s is "
                                 "not in the log")
    if end < until:
        resim.samples = [s for s in resim.samples if s[0] <= end - run.origin]
        resim.events = [e for e in resim.events if e[0] <= end - run.origin]
    _check_events(replay, resim, run.origin)
    return TeleopPart(run.origin, end, resim)


def _check_events(replay: Replay, resim: Resimulation, origin: float) -> None:
    """The world's events the re-simulation met must be the logged ones, at about the logged times."""
    met, logged = [e for _, e in resim.events], [e for _, e in resim.logged]
    if met[:len(logged)] != logged and met != logged[:len(met)]:
        say_missing(replay, origin + (resim.logged or resim.events)[0][0],
                    f"the re-simulation diverges from the log: it meets {_names(met)}, the log has {_names(logged)}")
        return
    for (t_met, event), (t_logged, _) in zip(resim.events, resim.logged, strict=False):
        if abs(t_met - t_logged) > EVENT_TOLERANCE_S:
            say_missing(replay, origin + t_logged, f"the re-simulation meets {event} at {origin + t_met:.1f} s, the "
                                                   f"log at {origin + t_logged:.1f} s")
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

