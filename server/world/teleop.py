"""Teleoperations in progress and the clock that moves their arms.

The server owns the arm and moves it on its own clock from the input the participant holds: ``Teleops.advance``
integrates the held input from where the arm was last moved up to now, until the dead-man time passes without a
message. The world loop (``server.world.hub``) advances every arm each tick; a message advances its own arm first.
"""

from __future__ import annotations

import itertools
import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from threading import RLock
from typing import Any

from experiment.flow import TrialRef
from experiment.world import Scene, WorldState, teleop_start_state
from experiment.world.teleop import (
    DEFAULT_RULES,
    HeldMove,
    TeleopCommand,
    TeleopRules,
    WorldEvent,
    hold_command,
    hold_moves,
)
from server.faults import FaultLog
from server.ratelimit import RateLimiter
from server.settings import Settings

#: A held motion stops this long after the last message (the dead-man time): longer than a keep-alive
#: period of a page whose timers run slow (about 3 a second seen with software rendering), short enough
#: that a stalled page does not carry the arm far.
DEADMAN_S = 0.8
#: What the page is asked to do while an input is held (the dead-man time leaves room for slow timers).
KEEPALIVE_S = 0.2
#: The longest stretch of time one advance makes up for when no world loop runs (messages advance the arm):
#: only a server stalled for longer loses time (the motion is still integrated in small collision-checked
#: steps, so the arm never passes through anything).
MAX_ADVANCE_S = 1.0
#: While the world loop runs, one advance makes up for at most this many of its periods. A saturated event loop
#: ticks late; integrating the whole late interval would make the next tick later still (a spiral: see
#: ``docs/architecture.md``). Past this the arm moves slower than held, and the time lost is logged (``server_lag``).
MAX_ADVANCE_PERIODS = 2.0
#: Simulated time over which a gripper action is applied when it arrives (the fingers start moving).
GRIPPER_ACTION_S = 0.001
#: Teleoperation is sped up by the study's animation speed, but at most this much, which a closed-loop
#: operator can still steer.
MAX_TELEOP_SPEEDUP = 8.0
#: Weight of the latest measurement in ``Teleops.arm_move_s`` (how long an arm's move in a tick takes).
ARM_MOVE_SMOOTHING = 0.05
RATE_BURST = 10  # messages allowed in a burst above the steady rate
#: Entries one teleoperation logs at most (inputs, events, stops). A person changes input a few times a second;
#: at the rate limit (``teleop_rate_limit_hz``, 60/s) for the longest allowed time limit (600 s) a client could log
#: 36,000: this bounds what one socket can make the database store (about 3 MB).
MAX_LOG_ENTRIES = 20_000


class LogEvent(StrEnum):
    """What the server's clock logs of a teleoperation besides its inputs and the world's events (``WorldEvent``)."""

    DEADMAN_STOP = "deadman_stop"  # no message for DEADMAN_S: the held motion stopped
    RESUMED = "resumed"  # a keep-alive after a dead-man stop gave the held motion back
    DISCONNECT_STOP = "disconnect_stop"  # the socket that held the input closed
    FAULT_STOP = "fault_stop"  # advancing the arm failed (a contained fault): the arm stopped
    SERVER_LAG = "server_lag"  # the server was late: the held input moved the arm ``lost_ms`` less
    LOG_CAPPED = "log_capped"  # MAX_LOG_ENTRIES reached: later entries are not kept
    LOG_LOST = "log_lost"  # entries that could not be written (``entries`` of them)


@dataclass(frozen=True)
class TrialKey:
    """A participant's trial: whose (the participant's public id) and which."""

    participant_key: str
    ref: TrialRef


_SCENE_IDS = itertools.count()


@dataclass(frozen=True, slots=True)
class AdvanceStep:
    """A part of advancing an arm: ``move`` up to ``end`` (with ``lost`` real seconds not made up for), or the
    dead-man stop at ``end`` (``move`` None)."""

    end: float
    move: HeldMove | None
    lost: float = 0.0


class TeleopLog:
    """A teleoperation's entries not yet written to the event log, in order (appended by the arm's clock, drained by
    ``server.services.teleop_log.TeleopLogWriter`` alone).

    Between two entries the held input moved the arm for the time between them, less the ``lost_ms`` logged there:
    the log reconstructs the teleoperation. Past ``MAX_LOG_ENTRIES`` one ``log_capped`` entry says so and later ones
    are not kept.
    """

    def __init__(self, started: float) -> None:
        self.started = started
        self._entries: list[dict[str, Any]] = []
        self._kept = 0
        self._lost_s = 0.0  # real time the arm did not move for (the server was late), not yet logged
        self._lost_at = 0.0
        self.write_failures = 0  # writes of these entries that failed in a row

    def server_ms(self, now: float) -> float:
        return round((now - self.started) * 1000, 1)

    def append(self, entry: dict[str, Any]) -> None:
        if self._kept >= MAX_LOG_ENTRIES:
            return
        self._log_lost_time()
        self._kept += 1
        self._entries.append(entry if self._kept < MAX_LOG_ENTRIES else
                             {"server_ms": entry.get("server_ms"), "event": LogEvent.LOG_CAPPED,
                              "max_entries": MAX_LOG_ENTRIES})

    def event(self, now: float, event: LogEvent | WorldEvent, **fields: Any) -> None:
        self.append({"server_ms": self.server_ms(now), "event": event, **fields})

    def lose_time(self, seconds: float, now: float) -> None:
        self._lost_s += seconds
        self._lost_at = now

    def take(self) -> list[dict[str, Any]]:
        """The entries logged since the last call (to be written to the event log)."""
        self._log_lost_time()
        batch, self._entries = self._entries, []
        return batch

    def __iter__(self) -> Iterator[dict[str, Any]]:
        """The entries not yet taken."""
        return iter(list(self._entries))

    def put_back(self, entries: list[dict[str, Any]]) -> None:
        """Entries taken but not written: they go before the newer ones, for the next write."""
        self._entries[:0] = entries

    def _log_lost_time(self) -> None:
        if self._lost_s > 0:
            self._entries.append({"server_ms": self.server_ms(self._lost_at), "event": LogEvent.SERVER_LAG,
                                  "lost_ms": round(self._lost_s * 1000, 1)})
            self._lost_s = 0.0


@dataclass
class TeleopSession:
    """One teleoperation in progress (in memory; a restart starts the arm from its ready pose again).

    ``held`` is the motion input the participant holds now (never a gripper action), integrated over time by
    ``Teleops.advance`` until the dead-man time passes without a message.
    """

    key: TrialKey
    scene: Scene
    state: WorldState
    rules: TeleopRules = DEFAULT_RULES
    speedup: float = 1.0  # simulated seconds per real second
    started: float = field(default_factory=time.monotonic)
    advanced_at: float = field(default_factory=time.monotonic)  # the arm has been moved up to this moment
    last_message: float = field(default_factory=time.monotonic)
    held: TeleopCommand = TeleopCommand()
    stopped: TeleopCommand | None = None  # the input the dead-man stop took away (a keep-alive gives it back)
    input_seq: int | None = None
    messages: int = 0
    version: int = 0  # counts changes of the world (a socket pushes a world message when it moved on)
    blocked: bool = False  # the latest motion was refused by a collision
    recent_events: deque = field(default_factory=lambda: deque(maxlen=64))  # (version, WorldEvent)
    scene_id: int = field(default_factory=lambda: next(_SCENE_IDS))  # names the scene to the physics helper
    log: TeleopLog = field(init=False)

    def __post_init__(self) -> None:
        self.log = TeleopLog(self.started)

    @property
    def participant_key(self) -> str:
        return self.key.participant_key

    @property
    def moving(self) -> bool:
        return self.held.moves

    def server_ms(self, now: float) -> float:
        return self.log.server_ms(now)

    def events_since(self, version: int) -> list[WorldEvent]:
        return list(dict.fromkeys(event for v, event in self.recent_events if v > version))

    def record(self, now: float, state: WorldState, events: tuple[WorldEvent, ...]) -> None:
        """The arm's new state and the world's events on the way to it."""
        changed = state != self.state
        self.state = state
        blocked = WorldEvent.BLOCKED in events
        if changed or events or blocked != self.blocked:
            self.version += 1
        for event in events:
            if event != WorldEvent.BLOCKED or not self.blocked:  # a push against an obstacle is logged once
                self.log.event(now, event)
            self.recent_events.append((self.version, event))
        self.blocked = blocked

    def stop_motion(self, now: float, event: LogEvent) -> None:
        """The held motion ends (``event`` says why)."""
        self.held = TeleopCommand()
        self.version += 1
        self.log.event(now, event)


class Teleops:
    """The arms under teleoperation in this process (one per participant) and the clock that moves them.

    ``lock`` is the world's (``WorldHub``): a teleoperation and a playback of the same participant replace each other
    under it.
    """

    def __init__(self, settings: Settings, faults: FaultLog, lock: RLock) -> None:
        self.settings, self.faults, self._lock = settings, faults, lock
        self._by_participant: dict[str, TeleopSession] = {}
        self._limit = RateLimiter(settings.teleop_rate_limit_hz, RATE_BURST)
        self.ticking = False  # the world loop runs: one advance makes up for at most MAX_ADVANCE_PERIODS of it
        self.arm_move_s: float | None = None  # what one arm's move in a tick takes (smoothed; None: not measured yet)

    # -- which arms ------------------------------------------------------------------------------------------------
    def start(self, key: TrialKey, scene: Scene, rules: TeleopRules, speed: float) -> TeleopSession:
        """The teleoperation of a trial, started from the ready pose the first time it is asked for."""
        with self._lock:
            session = self._by_participant.get(key.participant_key)
            if session is None or session.key != key:
                session = self._by_participant[key.participant_key] = TeleopSession(
                    key, scene, teleop_start_state(scene), rules, min(speed, MAX_TELEOP_SPEEDUP))
            return session

    def get(self, participant_key: str) -> TeleopSession | None:
        return self._by_participant.get(participant_key)

    def drop(self, participant_key: str) -> TeleopSession | None:
        with self._lock:
            return self._by_participant.pop(participant_key, None)

    def end(self, key: TrialKey) -> None:
        with self._lock:
            if (session := self._by_participant.get(key.participant_key)) is not None and session.key == key:
                del self._by_participant[key.participant_key]

    def is_current(self, session: TeleopSession) -> bool:
        """Whether ``session`` is still its participant's teleoperation (not ended, nor replaced by a newer one)."""
        with self._lock:
            return self._by_participant.get(session.participant_key) is session

    def teleoperated(self, participant_keys: Iterable[str]) -> set[str]:
        """Those of ``participant_keys`` whose live world is a teleoperation."""
        with self._lock:
            return {key for key in participant_keys if key in self._by_participant}

    def keys(self) -> set[str]:
        return set(self._by_participant)

    def __len__(self) -> int:
        return len(self._by_participant)

    def __iter__(self) -> Iterator[TeleopSession]:
        return iter(list(self._by_participant.values()))

    # -- the participant's messages ----------------------------------------------------------------------------------
    def allow(self, session: TeleopSession, now: float | None = None) -> bool:
        """Whether the participant may send this command: ``teleop_rate_limit_hz`` a second, a small burst."""
        return self._limit.take(session.participant_key, now) == 0

    def set_input(self, session: TeleopSession, command: TeleopCommand, *, seq: int, client_ms: float | None,
                  now: float | None = None) -> tuple[WorldEvent, ...]:
        """The participant's new input: the arm moves under the old one up to now, then holds the new motion; a
        gripper action is applied at once. Returns the events of the gripper action."""
        now = time.monotonic() if now is None else now
        held = command.motion
        with self._lock:
            if held != session.held or command.gripper is not None or session.stopped is not None:
                advanced = self._advance(session, now)  # the old input moved the arm up to now
            else:
                advanced = self._catch_up_deadman(session, now)
            session.last_message, session.input_seq, session.messages = now, seq, session.messages + 1
            session.stopped = None
            session.log.append({"server_ms": session.server_ms(now), "client_ms": client_ms, "seq": seq,
                                "input": command.as_dict()})
            if not advanced:  # the arm failed and stopped: a new input does not set it moving again
                return ()
            if held != session.held:
                session.held = held
                session.version += 1
            if command.gripper is None:
                return ()
            state, events = hold_command(session.state, session.scene, command, GRIPPER_ACTION_S * session.speedup,
                                         session.rules)
            session.record(now, state, events)
            return events

    def keepalive(self, session: TeleopSession, now: float | None = None) -> None:
        """A message that only says the input is still held: after a dead-man stop (the page stalled for longer
        than ``DEADMAN_S``, then came back) the held input moves the arm again."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if session.stopped is not None:
                self._advance(session, now)  # resuming: nothing held moved the arm up to now
            else:
                self._catch_up_deadman(session, now)
            session.last_message, session.messages = now, session.messages + 1
            if session.stopped is not None:
                session.held, session.stopped = session.stopped, None
                session.version += 1
                session.log.event(now, LogEvent.RESUMED)

    def release(self, session: TeleopSession, now: float | None = None) -> None:
        """The socket that held the input closed: the arm stops at once."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._advance(session, now)
            session.stopped = None
            if session.moving:
                session.stop_motion(now, LogEvent.DISCONNECT_STOP)

    # -- the clock ---------------------------------------------------------------------------------------------------
    def advance(self, session: TeleopSession, now: float | None = None) -> None:
        """Move the arm from where it was last moved to ``now`` under the held input (the server's clock).

        The held motion stops ``DEADMAN_S`` after the last message; a gap longer than ``MAX_ADVANCE_PERIODS`` of
        the world loop (``MAX_ADVANCE_S`` without it: a stalled server) is not made up for, so the arm never jumps
        and a late server does not do more physics per tick.
        """
        now = time.monotonic() if now is None else now
        with self._lock:
            self._advance(session, now)

    def _advance(self, session: TeleopSession, now: float) -> bool:
        """Move the arm up to ``now``: a step that fails (a bug, or an input no check foresaw) stops that
        participant's arm, is logged and recorded, and leaves every other arm moving (False: it failed). A
        teleoperation that fails again with nothing held is ended (its trial's time limit then resolves it, as for
        a closed tab)."""
        try:
            steps = self.plan(session, now)
            moves = tuple(step.move for step in steps if step.move is not None)
            start = time.perf_counter()
            results = hold_moves(session.state, session.scene, moves, session.rules)
            if moves:
                self.measured_arm_moves(time.perf_counter() - start, 1)
            self.apply(session, steps, results, now)
            return True
        except Exception as exc:  # noqa: BLE001 -- contained to this participant
            session.advanced_at = now  # the failed interval is not tried again
            if session.moving or session.stopped is not None:
                session.stopped = None
                session.stop_motion(now, LogEvent.FAULT_STOP)
            elif self._by_participant.get(session.participant_key) is session:
                del self._by_participant[session.participant_key]
            # recorded once contained: whoever reads the fault (the load report, a test) finds the arm stopped
            self.faults.record("world", exc, participant=session.participant_key)
            return False

    def measured_arm_moves(self, seconds: float, arms: int) -> None:
        """Note what moving ``arms`` arms took (here or in the helper): it decides where the next ticks' go."""
        per_arm = seconds / arms
        known = self.arm_move_s
        self.arm_move_s = per_arm if known is None else known + ARM_MOVE_SMOOTHING * (per_arm - known)

    def plan(self, session: TeleopSession, now: float) -> list[AdvanceStep]:
        """What advancing ``session`` to ``now`` takes (computing nothing): the held input up to the dead-man stop
        if one is due, the stop, then the held input (or, with nothing held, only what settles by itself)."""
        if now <= session.advanced_at:
            return []
        steps: list[AdvanceStep] = []
        start, held = session.advanced_at, session.held
        if session.moving and now >= (deadman_at := session.last_message + DEADMAN_S):
            stop = max(start, deadman_at)
            steps += self._held_step(session, held, start, stop, if_settling=False)
            steps.append(AdvanceStep(stop, None))
            start, held = stop, TeleopCommand()
        steps += self._held_step(session, held, start, now, if_settling=not held.moves)
        return steps

    def _held_step(self, session: TeleopSession, held: TeleopCommand, start: float, end: float, *, if_settling: bool
                   ) -> list[AdvanceStep]:
        longest = MAX_ADVANCE_PERIODS / self.settings.world_hz if self.ticking else MAX_ADVANCE_S
        real = end - start
        if real <= 0:
            return []
        lost = max(0.0, real - longest)
        return [AdvanceStep(end, HeldMove(held, (real - lost) * session.speedup, if_settling), lost)]

    @staticmethod
    def apply(session: TeleopSession, steps: list[AdvanceStep],
              results: list[tuple[WorldState, tuple[WorldEvent, ...]] | None], now: float) -> None:
        """Record an advance planned by ``plan`` with its moves' results (``hold_moves``), in order."""
        moved = iter(results)
        for step in steps:
            if step.move is None:  # the dead-man stop
                held = session.held
                session.stop_motion(step.end, LogEvent.DEADMAN_STOP)
                session.stopped = held
            elif (result := next(moved)) is not None:
                if step.lost:
                    session.log.lose_time(step.lost, step.end)
                session.record(step.end, *result)
        session.advanced_at = max(session.advanced_at, now)

    def _catch_up_deadman(self, session: TeleopSession, now: float) -> bool:
        """Before a message that leaves the held input as it is: apply a dead-man stop that is due.

        Otherwise nothing is computed here: the held input moves the arm the same whether the interval is
        integrated now or at the next world tick, and a person's page sends many keep-alives per change.
        """
        if session.moving and now >= session.last_message + DEADMAN_S:
            return self._advance(session, now)
        return True
