"""A teleoperation re-simulated from its log (the entries ``server.world.teleop.TeleopLog`` writes).

The server moves the arm on its own clock from the input the participant holds, so the log reconstructs it:
between two entries the held input moved the arm for the time between them, less the ``lost_ms`` a ``server_lag``
entry logs (the server was late); a gripper action is applied at its entry; a dead-man, disconnect or fault stop
ends the held motion and ``resumed`` gives it back. ``resimulate`` replays one log (one teleoperation, its clock
from 0) in steps of at most ``1 / sample_hz`` real seconds, as the server's world loop does, and returns the states
on the way and the world's events as the re-simulation met them, beside the ones the log holds, so a caller can
check one against the other.

The integration is split differently from the server's (which advanced at its ticks and messages), so positions may
differ in the last digits and a "blocked" push may be seen on another step: ``blocked`` is not compared.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from experiment.world.scene import Scene
from experiment.world.state import WorldState
from experiment.world.teleop import (
    DEFAULT_RULES,
    HeldMove,
    TeleopCommand,
    TeleopRules,
    WorldEvent,
    hold_command,
    hold_moves,
    parse_command,
    teleop_start_state,
)

#: The log's entries that end the held motion (``server.world.teleop.LogEvent``'s values).
STOPS = ("deadman_stop", "disconnect_stop", "fault_stop")
RESUMED = "resumed"
SERVER_LAG = "server_lag"
#: Entries after which the log is incomplete: it was capped, or entries could not be written.
INCOMPLETE = ("log_capped", "log_lost")
#: An entry this little after the end (s) still belongs to it: the end (e.g. a deposit's ``teleop_time_ms``) is taken
#: just after its entry was logged, and entries' times are rounded to 0.1 ms.
END_SLACK_S = 0.001
#: The world's events the re-simulation must meet as the log has them (``blocked`` depends on the step split).
COMPARED = (WorldEvent.ALIGNED, WorldEvent.GRASPED, WorldEvent.DROPPED, WorldEvent.ITEM_RESET, WorldEvent.DEPOSITED)


@dataclass(frozen=True)
class TeleopClock:
    """How the server's clock turned real time into simulated time (``server.world.teleop``)."""

    speedup: float  # simulated seconds per real second: the study's animation speed, capped
    gripper_action_s: float  # simulated time over which a gripper action is applied at its entry, per speedup
    rules: TeleopRules = DEFAULT_RULES


@dataclass
class Resimulation:
    """One log re-simulated. Times are seconds on the log's clock (``server_ms`` / 1000)."""

    samples: list[tuple[float, WorldState]] = field(default_factory=list)  # the arm after each step
    events: list[tuple[float, WorldEvent]] = field(default_factory=list)  # met by the re-simulation (COMPARED)
    logged: list[tuple[float, WorldEvent]] = field(default_factory=list)  # what the log says happened (COMPARED)
    inputs: list[tuple[float, TeleopCommand]] = field(default_factory=list)
    stops: list[tuple[float, str]] = field(default_factory=list)  # stops and resumptions of the held motion
    lost_s: float = 0.0  # real time the arm did not move because the server was late
    last_entry_s: float = 0.0
    held_at_end: bool = False  # a motion was still held after the last entry
    incomplete: tuple[float, str] | None = None  # (when, why) the log stops being complete
    invalid: int = 0  # entries that could not be read (left out)

    def first(self, event: WorldEvent, *, logged: bool = False) -> float | None:
        return next((t for t, e in (self.logged if logged else self.events) if e == event), None)

    def state_at(self, t: float, start: WorldState) -> WorldState:
        """The arm at log time ``t``: the last step's state at or before it (``start`` before the first)."""
        lo, hi = 0, len(self.samples)
        while lo < hi:
            mid = (lo + hi) // 2
            if self.samples[mid][0] <= t:
                lo = mid + 1
            else:
                hi = mid
        return self.samples[lo - 1][1] if lo else start


def resimulate(scene: Scene, entries: Sequence[Mapping[str, Any]], clock: TeleopClock, *, until_s: float,
               sample_hz: float = 30.0) -> Resimulation:
    """Replay ``entries`` (in logged order) from the ready pose up to log time ``until_s``; entries after it are
    left out. After the last entry the held input goes on moving the arm up to ``until_s``."""
    out = Resimulation()
    run = _Run(scene, clock, out, sample_hz)
    for entry in entries:
        at = _seconds(entry)
        if at is None:
            out.invalid += 1
            continue
        if at > until_s + END_SLACK_S:
            break
        lost = _lost(entry)
        run.advance(at, lost)
        out.last_entry_s = at
        event = entry.get("event")
        if event in INCOMPLETE:
            out.incomplete = (at, str(event))
            break
        run.apply(at, entry)
    else:
        run.advance(until_s, 0.0)
    out.held_at_end = run.held.moves
    return out


def _seconds(entry: Mapping[str, Any]) -> float | None:
    value = entry.get("server_ms")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        return None
    return float(value) / 1000


def _lost(entry: Mapping[str, Any]) -> float:
    value = entry.get("lost_ms") if entry.get("event") == SERVER_LAG else None
    return float(value) / 1000 if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0 else 0.0


class _Run:
    """The re-simulation's moving parts: the arm, the held input and the one a stop took away."""

    def __init__(self, scene: Scene, clock: TeleopClock, out: Resimulation, sample_hz: float):
        self.scene, self.clock, self.out, self.step_s = scene, clock, out, 1.0 / sample_hz
        self.state = teleop_start_state(scene)
        self.held: TeleopCommand = TeleopCommand()
        self.stopped: TeleopCommand | None = None  # the input a dead-man stop took away (``resumed`` gives it back)
        self.at = 0.0
        out.samples.append((0.0, self.state))

    def advance(self, to: float, lost: float) -> None:
        """The held input moves the arm from ``self.at`` to ``to``, less ``lost`` real seconds, in steps."""
        real = to - self.at
        if real <= 0:
            return
        lost = min(lost, real)
        self.out.lost_s += lost
        share = (real - lost) / real
        steps = max(1, math.ceil(real / self.step_s - 1e-9))
        for i in range(1, steps + 1):
            end = self.at + real * i / steps
            duration = real / steps * share * self.clock.speedup
            if duration <= 1e-9:
                continue
            moved = hold_moves(self.state, self.scene, [HeldMove(self.held, duration, not self.held.moves)],
                               self.clock.rules)[0]
            if moved is not None:
                self._moved(end, *moved)
        self.at = to

    def apply(self, at: float, entry: Mapping[str, Any]) -> None:
        event = entry.get("event")
        if "input" in entry:
            try:
                command = parse_command(entry["input"])
            except ValueError:
                self.out.invalid += 1
                return
            self.out.inputs.append((at, command))
            self.stopped = None
            if command.gripper is not None:
                self._moved(at, *hold_command(self.state, self.scene, command,
                                              self.clock.gripper_action_s * self.clock.speedup, self.clock.rules))
            self.held = command.motion
        elif event in STOPS:
            self.stopped = self.held if event == "deadman_stop" else None
            self.held = TeleopCommand()
            self.out.stops.append((at, str(event)))
        elif event == RESUMED and self.stopped is not None:
            self.held, self.stopped = self.stopped, None
            self.out.stops.append((at, RESUMED))
        elif event in COMPARED:
            self.out.logged.append((at, WorldEvent(event)))

    def _moved(self, at: float, state: WorldState, events: tuple[WorldEvent, ...]) -> None:
        self.state = state
        self.out.samples.append((at, state))
        self.out.events += [(at, event) for event in events if event in COMPARED]
