"""The live robot worlds of active sessions (server memory, rebuilt on demand).

Every trial's scene and autonomous attempt are deterministic in (study seed,
participant, block, trial), so nothing here needs to survive a restart: the
database holds the trial's stage and deadlines, and the world of any trial
can be rebuilt from them. The server owns the arm and moves it on its own
clock from the input the participant holds (``advance``); a 30 Hz loop
advances every teleoperated arm and computes the pose of every watched world
for the viewers.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from threading import Lock
from typing import Any

from fastapi import FastAPI

from experiment.engine import PlannedTrial
from experiment.world import Attempt, Scene, WorldState, link_poses, teleop_start_state
from experiment.world.teleop import (DEFAULT_RULES, HeldMove, TeleopCommand, TeleopRules, hold_command, hold_moves,
                                     settling)
from experiment.world.trial import trial_attempt, trial_scene
from server.world.physics import SceneShipments, timed_advance_arms, warm_up
from server.world.processes import helper_pool
from server.faults import FaultLog
from server.ratelimit import RateLimiter
from server.services.trials import AttemptInfo
from server.settings import Settings

logger = logging.getLogger(__name__)

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
#: While the world loop runs, one advance makes up for at most this many of its periods. A saturated event
#: loop ticks late; integrating the whole late interval would make the next tick later still (every held arm
#: doing more physics per tick: a spiral that froze the server at 100 participants). Past this, the arm moves
#: slower than held (time the server was late is lost and logged as ``server_lag``): the participant sees a
#: slower arm, and the server's physics per second falls as its ticks slow down.
MAX_ADVANCE_PERIODS = 2.0
#: Simulated time over which a gripper action is applied when it arrives (the fingers start moving).
GRIPPER_ACTION_S = 0.001
#: Teleoperation is sped up by the study's animation speed, but at most this much, which a closed-loop
#: operator can still steer.
MAX_TELEOP_SPEEDUP = 8.0
#: After the physics helper failed, how long the arms move in the server before a new helper is started.
PHYSICS_RETRY_S = 10.0
#: Weight of the latest measurement in ``WorldHub.arm_move_s`` (how long an arm's move in a tick takes).
ARM_MOVE_SMOOTHING = 0.05
#: A world tick that starts this share of a period after its time counts as late (the event loop held it up; 10 ms
#: at 30 Hz): the figure the server's load report gives (``server.loadmeter``). A share, not a time: at the
#: ``world_hz`` a deployment sets (up to 240), late means the same part of a tick. The 3D view pacer sheds frames
#: only from a later start (``server.viewer.manager.LATE_STEP_PERIODS``).
LATE_TICK_PERIODS = 0.3
RATE_BURST = 10  # messages allowed in a burst above the steady rate
#: Entries one teleoperation logs at most (inputs, events, stops). A person changes input a few times a second;
#: at the rate limit (``teleop_rate_limit_hz``, 60/s) for the longest allowed time limit (600 s) a client could log
#: 36,000: this bounds what one socket can make the database store (about 3 MB).
MAX_LOG_ENTRIES = 20_000
#: Planned attempts kept (about two per active session): planning one takes milliseconds of CPU, which a
#: request would otherwise spend holding the database.
ATTEMPT_CACHE_SIZE = 1024


@dataclass(frozen=True)
class TrialKey:
    participant_key: str
    practice: bool
    block: int
    trial: int


_SCENE_IDS = itertools.count()


@dataclass(frozen=True, slots=True)
class AdvanceStep:
    """A part of advancing an arm: ``move`` up to ``end`` (with ``lost`` real seconds not made up for), or the
    dead-man stop at ``end`` (``move`` None)."""

    end: float
    move: HeldMove | None
    lost: float = 0.0


@dataclass
class TeleopSession:
    """One teleoperation in progress (in memory; a restart starts the arm from its ready pose again).

    The server's clock moves the arm: ``held`` is the motion input the participant holds now, integrated
    over time by ``WorldHub.advance`` until the dead-man time passes without a message.
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
    recent_events: deque = field(default_factory=lambda: deque(maxlen=64))  # (version, event)
    log: list[dict[str, Any]] = field(default_factory=list)  # entries not yet written to the event log
    scene_id: int = field(default_factory=lambda: next(_SCENE_IDS))  # names the scene to the physics helper
    lost_s: float = 0.0  # real time the arm did not move for (the server was late), not yet logged
    lost_at: float = 0.0  # when time was last lost
    logged: int = 0  # entries logged so far (``MAX_LOG_ENTRIES``)
    log_write_failures: int = 0  # writes of this session's entries that failed in a row (``TeleopLogWriter``)

    @property
    def participant_key(self) -> str:
        return self.key.participant_key

    @property
    def moving(self) -> bool:
        return _is_motion(self.held)

    def server_ms(self, now: float) -> float:
        return round((now - self.started) * 1000, 1)

    def take_log(self) -> list[dict[str, Any]]:
        """The entries logged since the last call (to be written to the event log)."""
        self._log_lost_time()
        batch, self.log = self.log, []
        return batch

    def append_log(self, entry: dict[str, Any]) -> None:
        """Log an entry, after the time lost before it (so that between two entries the held input moved the arm
        for the time between them less the ``lost_ms`` logged there: the log reconstructs the teleoperation).
        Past ``MAX_LOG_ENTRIES`` one ``log_capped`` entry says so and later ones are not kept."""
        if self.logged >= MAX_LOG_ENTRIES:
            return
        self._log_lost_time()
        self.logged += 1
        self.log.append(entry if self.logged < MAX_LOG_ENTRIES else
                        {"server_ms": entry.get("server_ms"), "event": "log_capped", "max_entries": MAX_LOG_ENTRIES})

    def lose_time(self, seconds: float, now: float) -> None:
        self.lost_s += seconds
        self.lost_at = now

    def _log_lost_time(self) -> None:
        if self.lost_s > 0:
            self.log.append({"server_ms": self.server_ms(self.lost_at), "event": "server_lag",
                             "lost_ms": round(self.lost_s * 1000, 1)})
            self.lost_s = 0.0

    def events_since(self, version: int) -> list[str]:
        return list(dict.fromkeys(name for v, name in self.recent_events if v > version))

    def _record(self, now: float, state: WorldState, events: tuple[str, ...]) -> None:
        changed = state != self.state
        self.state = state
        blocked = "blocked" in events
        if changed or events or blocked != self.blocked:
            self.version += 1
        for name in events:
            if name != "blocked" or not self.blocked:  # a push against an obstacle is logged once, not per step
                self.append_log({"server_ms": self.server_ms(now), "event": name})
            self.recent_events.append((self.version, name))
        self.blocked = blocked
@dataclass(frozen=True)
class LiveWorld:
    """A participant's world at one moment, with the seed of the trial scene it belongs to."""

    scene_seed: int
    state: WorldState


TickListener = Callable[[dict[str, LiveWorld]], None]
#: The participant keys a tick listener needs worlds for (None: every live world).
WantedKeys = Callable[[], Iterable[str]] | None


class WorldHub:
    """Scenes, attempts and teleoperations of the sessions this process serves.

    A participant has at most one live world: starting a teleoperation replaces
    the participant's playback and any older teleoperation, and starting a
    playback replaces the participant's teleoperation.
    """

    def __init__(self, settings: Settings, faults: FaultLog | None = None):
        self.settings = settings
        self.faults = faults or FaultLog()  # contained failures of one session's step (``server.faults``)
        self._teleops: dict[str, TeleopSession] = {}  # by participant key
        self._playbacks: dict[str, Playback] = {}
        self._subscribers: dict[str, list[asyncio.Queue]] = {}
        self._tick_listeners: list[tuple[TickListener, WantedKeys]] = []
        self._attempts: OrderedDict[tuple, Any] = OrderedDict()
        self._teleop_limit = RateLimiter(settings.teleop_rate_limit_hz, RATE_BURST)
        self._planning: set[tuple] = set()  # attempts the planner processes are working on
        self._planner: ProcessPoolExecutor | None = None
        self._physics: ProcessPoolExecutor | None = None  # the helper process moving many arms (``server.physics``)
        self._physics_scenes = SceneShipments()  # the scenes (``TeleopSession.scene_id``) the helper has
        self._physics_started: Future | None = None
        self._physics_retry_at = 0.0  # after a helper failed, the arms move here until then
        self._physics_batch: asyncio.Task | None = None  # the batch the helper is computing
        self._in_flight: set[int] = set()  # the sessions (ids) in it
        self.physics_batches = 0  # ticks whose arms the helper moved
        self.arm_move_s: float | None = None  # what one arm's move in a tick takes (smoothed; None: not measured yet)
        self._lock = Lock()
        self.ticks = 0
        self.ticking = False  # the 30 Hz loop runs (``run``): it advances every teleoperated arm
        self.late_s = 0.0  # how late the loop's latest tick started: the event loop is that congested
        self.late_ticks = 0  # ticks that started LATE_TICK_PERIODS late or more (``server.loadmeter`` reads them)
        self.latest_start_s = 0.0  # the latest start of a tick since ``take_latest_start`` (the loop's worst hold-up)
        self._tick_waiters: dict[int, list[asyncio.Future]] = {}  # by the tick (``ticks``) they wait for
        #: Told of every playback started (a ``Playback``) or dropped (None), by participant key, outside the lock:
        #: the 3D view process plays the same attempts (``server.viewer.remote``).
        self.playback_listener: Callable[[str, Playback | None], None] | None = None

    @property
    def period_s(self) -> float:
        """The world loop's period (s): lateness is judged as a share of it."""
        return 1.0 / self.settings.world_hz

    def note_start(self, late_s: float) -> None:
        """Count a tick of the loop that started ``late_s`` after its time (the load report's figures)."""
        self.late_s = late_s
        self.late_ticks += late_s >= LATE_TICK_PERIODS * self.period_s
        self.latest_start_s = max(self.latest_start_s, late_s)

    # -- scenes and autonomous attempts ------------------------------------------------
    def scene(self, study_seed: int, participant_key: str, planned: PlannedTrial) -> Scene:
        return trial_scene(study_seed, participant_key, planned.block_name, planned.trial, planned.complexity.value)

    @staticmethod
    def _attempt_args(study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> tuple:
        return study_seed, participant_key, planned.block_name, planned.trial, planned.complexity.value, success

    def attempt_for(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> Attempt:
        """The trial's autonomous attempt (deterministic; planned once, then cached)."""
        key = self._attempt_args(study_seed, participant_key, planned, success)
        with self._lock:
            if (attempt := self._attempts.get(key)) is not None:
                self._attempts.move_to_end(key)
                return attempt
        attempt = trial_attempt(*key)
        self._remember_attempt(key, attempt)
        return attempt

    def _remember_attempt(self, key: tuple, attempt: Attempt) -> None:
        with self._lock:
            self._attempts[key] = attempt
            while len(self._attempts) > ATTEMPT_CACHE_SIZE:
                self._attempts.popitem(last=False)

    def prepare_attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> None:
        """Plan a trial's attempt ahead (after its decision window opened, outside any database transaction).

        With ``planner_processes``, a helper process plans it: planning is milliseconds of pure-Python CPU, and in
        a thread of this process it would hold the interpreter lock against the event loop, stalling every
        request for up to a switch interval each time the loop let go of the lock. Whatever the helper has not
        delivered when the attempt is needed is planned here (the same attempt: it depends on seeds only).
        """
        key = self._attempt_args(study_seed, participant_key, planned, success)
        if self.settings.planner_processes == 0:
            self.attempt_for(study_seed, participant_key, planned, success)
            return
        with self._lock:
            if key in self._attempts or key in self._planning:
                return
            self._planning.add(key)
        try:
            future = self._planner_pool().submit(trial_attempt, *key)
        except Exception:  # noqa: BLE001 -- a broken pool (its process died): plan when needed, and start a new one
            self._planner = None
            with self._lock:
                self._planning.discard(key)
            logger.warning("attempt planner process unavailable; planning in the server", exc_info=True)
            return
        future.add_done_callback(lambda done: self._planned(key, done))

    def _planned(self, key: tuple, done: Future) -> None:
        with self._lock:
            self._planning.discard(key)
        if not done.cancelled() and done.exception() is None:
            self._remember_attempt(key, done.result())

    def _planner_pool(self) -> ProcessPoolExecutor:
        with self._lock:  # units may run in several threads (PostgreSQL): one pool, not one each
            if self._planner is None:  # on first use
                self._planner = helper_pool(self.settings.planner_processes)
            return self._planner

    def close(self) -> None:
        """Stop the planner and physics processes (attempts still being planned are dropped)."""
        if self._planner is not None:
            self._planner.shutdown(wait=False, cancel_futures=True)
            self._planner = None
        if self._physics is not None:
            self._physics.shutdown(wait=False, cancel_futures=True)
            self._physics = None

    def attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool, *,
                started_ago_s: float, speed: float) -> AttemptInfo:
        """Plan the autonomous attempt of a trial (``AttemptPlanner``) and start playing it back."""
        attempt = self.attempt_for(study_seed, participant_key, planned, success)
        self.play(participant_key, attempt, time.monotonic() - started_ago_s, speed)
        return AttemptInfo(attempt.duration, attempt.failure_mode)

    # -- teleoperation -----------------------------------------------------------------
    def teleop(self, key: TrialKey, scene: Scene, rules: TeleopRules = DEFAULT_RULES, speed: float = 1.0
               ) -> TeleopSession:
        """The teleoperation of a trial, started from the ready pose the first time it is asked for."""
        with self._lock:
            dropped = self._playbacks.pop(key.participant_key, None)
            session = self._teleops.get(key.participant_key)
            if session is None or session.key != key:
                session = self._teleops[key.participant_key] = TeleopSession(
                    key, scene, teleop_start_state(scene), rules, min(speed, MAX_TELEOP_SPEEDUP))
        if dropped is not None:
            self._tell_playback(key.participant_key, None)
        return session

    def advance(self, session: TeleopSession, now: float | None = None) -> None:
        """Move the arm from where it was last moved to ``now`` under the held input (the server's clock).

        The held motion stops ``DEADMAN_S`` after the last message; a gap longer than ``MAX_ADVANCE_PERIODS`` of
        the world loop (``MAX_ADVANCE_S`` without it: a stalled server) is not made up for, so the arm never jumps
        and a late server does not do more physics per tick.
        """
        now = time.monotonic() if now is None else now
        with self._lock:
            self._advance(session, now)

    def _advance_unguarded(self, session: TeleopSession, now: float) -> None:
        steps = self._plan(session, now)
        moves = tuple(step.move for step in steps if step.move is not None)
        start = time.perf_counter()
        results = hold_moves(session.state, session.scene, moves, session.rules)
        if moves:
            self._measured_arm_moves(time.perf_counter() - start, 1)
        self._apply(session, steps, results, now)

    def _advance(self, session: TeleopSession, now: float) -> None:
        """Move the arm up to ``now`` (from the world loop or a participant's message): a step that fails (a bug, or an input no check foresaw) stops that
        participant's arm, is logged and recorded, and leaves every other arm moving. A teleoperation that fails
        again with nothing held is ended (its trial's time limit then resolves it, as for a closed tab)."""
        try:
            self._advance_unguarded(session, now)
        except Exception as exc:  # noqa: BLE001 -- contained to this participant
            self.faults.record("world", exc, participant=session.participant_key)
            session.advanced_at = now  # the failed interval is not tried again
            if session.moving or session.stopped is not None:
                session.held, session.stopped = TeleopCommand(), None
                session.version += 1
                session.append_log({"server_ms": session.server_ms(now), "event": "fault_stop"})
            elif self._teleops.get(session.participant_key) is session:
                del self._teleops[session.participant_key]

    def _measured_arm_moves(self, seconds: float, arms: int) -> None:
        """Note what moving ``arms`` arms took (here or in the helper): it decides where the next ticks' go."""
        per_arm = seconds / arms
        known = self.arm_move_s
        self.arm_move_s = per_arm if known is None else known + ARM_MOVE_SMOOTHING * (per_arm - known)

    def _plan(self, session: TeleopSession, now: float) -> list[AdvanceStep]:
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
        steps += self._held_step(session, held, start, now, if_settling=not _is_motion(held))
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
    def _apply(session: TeleopSession, steps: list[AdvanceStep],
               results: list[tuple[WorldState, tuple[str, ...]] | None], now: float) -> None:
        """Record an advance planned by ``_plan`` with its moves' results (``hold_moves``), in order."""
        moved = iter(results)
        for step in steps:
            if step.move is None:  # the dead-man stop
                session.held, session.stopped = TeleopCommand(), session.held
                session.version += 1
                session.append_log({"server_ms": session.server_ms(step.end), "event": "deadman_stop"})
            elif (result := next(moved)) is not None:
                if step.lost:
                    session.lose_time(step.lost, step.end)
                session._record(step.end, *result)
        session.advanced_at = max(session.advanced_at, now)

    def _catch_up_deadman(self, session: TeleopSession, now: float) -> None:
        """Before a message that leaves the held input as it is: apply a dead-man stop that is due.

        Otherwise nothing is computed here: the held input moves the arm the same whether the interval is
        integrated now or at the next world tick, and a person's page sends many keep-alives per change.
        """
        if session.moving and now >= session.last_message + DEADMAN_S:
            self._advance(session, now)

    def set_input(self, session: TeleopSession, held: TeleopCommand, gripper: str | None, *, seq: int,
                  client_ms: float | None, now: float | None = None) -> tuple[str, ...]:
        """The participant's new input: the arm moves under the old one up to now, then holds the new one; a
        gripper action is applied at once. Returns the events of the gripper action."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if held != session.held or gripper is not None or session.stopped is not None:
                self._advance(session, now)  # the old input moved the arm up to now
            else:
                self._catch_up_deadman(session, now)
            session.last_message, session.input_seq, session.messages = now, seq, session.messages + 1
            session.stopped = None
            entry = {"server_ms": session.server_ms(now), "client_ms": client_ms, "seq": seq,
                     "input": _input_dict(held, gripper)}
            session.append_log(entry)
            if held != session.held:
                session.held = held
                session.version += 1
            if gripper is None:
                return ()
            state, events = hold_command(session.state, session.scene, replace(held, gripper=gripper),
                                         GRIPPER_ACTION_S * session.speedup, session.rules)
            session._record(now, state, events)
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
                session.append_log({"server_ms": session.server_ms(now), "event": "resumed"})

    def release(self, session: TeleopSession, now: float | None = None) -> None:
        """The socket that held the input closed: the arm stops at once."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._advance(session, now)
            session.stopped = None
            if session.moving:
                session.held = TeleopCommand()
                session.version += 1
                session.append_log({"server_ms": session.server_ms(now), "event": "disconnect_stop"})

    def allow(self, session: TeleopSession, now: float | None = None) -> bool:
        """Whether the participant may send this command: ``teleop_rate_limit_hz`` a second, a small burst."""
        return self._teleop_limit.take(session.participant_key, now) == 0

    def is_current(self, session: TeleopSession) -> bool:
        """Whether ``session`` is still its participant's teleoperation (not ended, nor replaced by a newer one)."""
        with self._lock:
            return self._teleops.get(session.participant_key) is session

    def end_teleop(self, key: TrialKey) -> None:
        with self._lock:
            if (session := self._teleops.get(key.participant_key)) is not None and session.key == key:
                del self._teleops[key.participant_key]

    def teleop_over(self, participant_key: str, practice: bool, block: int, trial: int) -> None:
        """The trial's teleoperation ended without a deposit (``AttemptPlanner``: its time limit passed)."""
        self.end_teleop(TrialKey(participant_key, practice, block, trial))

    def active_teleops(self) -> int:
        return len(self._teleops)

    # -- autonomous attempts being played back ------------------------------------------
    def play(self, participant_key: str, attempt, start: float, speed: float) -> None:
        """Show ``attempt`` from monotonic time ``start`` (the decision deadline) at ``speed``."""
        playback = Playback(attempt, start, speed)
        with self._lock:
            self._teleops.pop(participant_key, None)
            self._playbacks[participant_key] = playback
        self._tell_playback(participant_key, playback)

    def stop(self, participant_key: str) -> None:
        with self._lock:
            dropped = self._playbacks.pop(participant_key, None)
        if dropped is not None:
            self._tell_playback(participant_key, None)

    def _tell_playback(self, participant_key: str, playback: Playback | None) -> None:
        if (listener := self.playback_listener) is not None:
            try:
                listener(participant_key, playback)
            except Exception:  # the view may miss a playback; the participant's trial goes on
                logger.exception("playback listener failed")

    def teleoperated(self, participant_keys: Iterable[str]) -> set[str]:
        """Those of ``participant_keys`` whose live world is a teleoperation."""
        with self._lock:
            return {key for key in participant_keys if key in self._teleops}

    # -- the 30 Hz loop ----------------------------------------------------------------
    def subscribe(self, participant_key: str) -> asyncio.Queue:
        """Frames (world state dicts with link poses) of one participant's world, newest only."""
        queue: asyncio.Queue = asyncio.Queue(maxsize=1)
        with self._lock:
            self._subscribers.setdefault(participant_key, []).append(queue)
        return queue

    def unsubscribe(self, participant_key: str, queue: asyncio.Queue) -> None:
        with self._lock:
            queues = self._subscribers.get(participant_key, [])
            if queue in queues:
                queues.remove(queue)
            if not queues:
                self._subscribers.pop(participant_key, None)

    def add_tick_listener(self, listener: TickListener, wanted: WantedKeys = None) -> None:
        """Call ``listener(worlds)`` after every tick, on the ticking thread (keep it short).

        ``wanted()`` names the participants whose worlds the listener uses (called on the ticking thread):
        the loop then computes only the worlds someone looks at.
        """
        with self._lock:
            self._tick_listeners.append((listener, wanted))

    def remove_tick_listener(self, listener: TickListener) -> None:
        with self._lock:
            self._tick_listeners = [(f, w) for f, w in self._tick_listeners if f != listener]

    def world_of(self, participant_key: str, now: float | None = None) -> LiveWorld | None:
        """The participant's live world now: the teleoperation, else the attempt played back (None: neither)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return self._live_world(participant_key, now)

    def _live_world(self, participant_key: str, now: float) -> LiveWorld | None:
        if (teleop := self._teleops.get(participant_key)) is not None:
            return LiveWorld(teleop.scene.seed, teleop.state)
        if (playback := self._playbacks.get(participant_key)) is not None:
            return LiveWorld(playback.attempt.scene.seed, playback.state(now))
        return None

    async def run(self, app: FastAPI) -> None:
        """Tick at ``world_hz`` with a deadline loop (no drift). A tick that is more than a period late is not made
        up for (the arms move by the clock, not by ticks): a saturated event loop gets no burst of ticks."""
        period = self.period_s
        next_tick = time.monotonic()
        self.ticking = True
        try:
            while True:
                now = time.monotonic()
                self.note_start(max(0.0, now - next_tick))
                if self.late_s > period:
                    next_tick = now
                try:
                    self.start_advancing_elsewhere(now)
                    self.tick(now, wanted_only=True)
                except Exception as exc:  # noqa: BLE001 -- the next tick tries again; one bad tick stops no one
                    self.faults.record("world", exc)
                next_tick += period
                await asyncio.sleep(max(0.0, next_tick - time.monotonic()))
        finally:
            self.ticking = False
            if self._physics_batch is not None:
                self._physics_batch.cancel()

    def moving(self, now: float) -> tuple[int, int]:
        """(attempts being played back, arms under teleoperation) at ``now``."""
        with self._lock:
            playing = sum(now - p.start < p.attempt.duration / p.speed for p in self._playbacks.values())
            return playing, len(self._teleops)

    def take_latest_start(self) -> float:
        """How late the latest-starting tick since the last call started (s), and start over."""
        latest, self.latest_start_s = self.latest_start_s, 0.0
        return latest

    async def advance_elsewhere(self, now: float) -> None:
        """Advance the moving arms to ``now`` in the physics helper process (``start_advancing_elsewhere``), and
        wait for it."""
        if (batch := self.start_advancing_elsewhere(now)) is not None:
            await batch

    def start_advancing_elsewhere(self, now: float) -> asyncio.Task | None:
        """Start advancing the moving arms to ``now`` in the physics helper process, when moving them here would
        take long enough (``physics_helper_min_ms``: the arms times ``arm_move_s``) and the previous batch is done;
        None if not started.

        The world loop does not wait for it: it ticks on, showing those arms where they were until their batch is
        back (a tick later, at most a few), and advances the others here. An arm that a message advanced in the
        meantime (an input change, a gripper action, a release: those advance it here, from where it was) keeps
        that: the helper's result for it is dropped, and the next tick goes on from there.
        """
        if not self.settings.physics_helper or now < self._physics_retry_at:
            return None
        if self._physics_batch is not None and not self._physics_batch.done():
            return None
        with self._lock:
            # nothing to compute for the others (``tick`` only moves their clocks)
            moving = [session for session in self._teleops.values() if session.moving or settling(session.state)]
            if not self._worth_the_helper(len(moving)):
                return None
            work = []
            for session in moving:
                steps = self._plan(session, now)
                moves = tuple(step.move for step in steps if step.move is not None)
                if moves:
                    work.append((session, session.advanced_at, session.state, steps, moves))
            if not work or (pool := self._physics_pool()) is None:
                return None
            jobs = [self._physics_scenes.job(session.scene_id, session.scene, state, session.rules, moves)
                    for session, _, state, _, moves in work]
            self._in_flight = {id(session) for session, *_ in work}
        self._physics_batch = asyncio.create_task(self._advanced_elsewhere(pool, jobs, work, now), name="physics")
        return self._physics_batch

    async def _advanced_elsewhere(self, pool: ProcessPoolExecutor, jobs: list, work: list, now: float) -> None:
        try:
            results, seconds = await asyncio.get_running_loop().run_in_executor(pool, timed_advance_arms, jobs)
        except asyncio.CancelledError:  # the world loop stopped
            with self._lock:
                self._in_flight = set()
            raise
        except Exception:  # noqa: BLE001 -- a helper that died or lost a scene: ``tick`` moves the arms here
            logger.warning("physics helper process failed; moving the arms in the server", exc_info=True)
            with self._lock:
                self._in_flight = set()
                self._physics, self._physics_scenes = None, SceneShipments()
                self._physics_retry_at = time.monotonic() + PHYSICS_RETRY_S
            pool.shutdown(wait=False, cancel_futures=True)
            return
        with self._lock:
            self._in_flight = set()
            self.physics_batches += 1
            self._measured_arm_moves(seconds, len(jobs))
            for (session, start, state, steps, _), result in zip(work, results):
                if self._teleops.get(session.participant_key) is session and session.advanced_at == start \
                        and session.state is state:
                    self._apply(session, steps, result, now)

    def _worth_the_helper(self, arms: int) -> bool:
        """Whether moving ``arms`` arms here would take ``physics_helper_min_ms`` or more (unknown until an arm has
        moved here: then not, unless the threshold is 0)."""
        threshold_s = self.settings.physics_helper_min_ms / 1000
        if arms == 0:
            return False
        if threshold_s == 0:
            return True
        return self.arm_move_s is not None and arms * self.arm_move_s >= threshold_s

    def _physics_pool(self) -> ProcessPoolExecutor | None:
        """The physics helper once it has started (None until then: it takes a second to spawn and import)."""
        if self._physics is None:
            self._physics, self._physics_scenes = helper_pool(1), SceneShipments()
            self._physics_started = self._physics.submit(warm_up)
        return self._physics if self._physics_started.done() else None

    async def next_tick(self, timeout: float, ticks: int = 1) -> None:
        """Wait (on the event loop) until the loop has ticked ``ticks`` more times, or ``timeout`` s at most.

        Each waiter has a future of its own, woken by the tick it waits for (no task per wait, and a socket that
        pushes every n-th tick is not woken by the others)."""
        waiter = asyncio.get_running_loop().create_future()
        self._tick_waiters.setdefault(self.ticks + ticks, []).append(waiter)
        try:
            async with asyncio.timeout(timeout):
                await waiter
        except TimeoutError:
            pass

    def tick(self, now: float | None = None, *, wanted_only: bool = False) -> dict[str, LiveWorld]:
        """Advance the live worlds to ``now``, hand each subscriber its newest frame, tell the listeners.

        ``wanted_only``: only the worlds of subscribers and of what the listeners want (the 30 Hz loop: with
        no one watching, a world costs nothing).
        """
        now = time.monotonic() if now is None else now
        with self._lock:
            subscribers = {k: list(v) for k, v in self._subscribers.items()}
            listeners = [listener for listener, _ in self._tick_listeners]
            wanted = [w for _, w in self._tick_listeners]
        keys: set[str] | None = None
        if wanted_only and all(w is not None for w in wanted):
            keys = set(subscribers).union(*(w() for w in wanted if w is not None))
        with self._lock:
            for teleop in list(self._teleops.values()):  # the arms move on the server's clock, watched or not
                if id(teleop) not in self._in_flight:  # (those the physics helper is moving: when it is done)
                    self._advance(teleop, now)
            live = self._playbacks.keys() | self._teleops.keys()
            keys = live if keys is None else keys & live
            worlds = {}
            for key in keys:
                try:
                    if (world := self._live_world(key, now)) is not None:
                        worlds[key] = world
                except Exception as exc:  # noqa: BLE001 -- this participant's world is not shown this tick
                    self.faults.record("world", exc, participant=key)
        for key, queues in subscribers.items():
            if key in worlds:
                frame = world_frame(worlds[key].state)
                for queue in queues:
                    _offer(queue, frame)
        for listener in listeners:
            try:
                listener(worlds)
            except Exception as exc:  # noqa: BLE001 -- a listener's failure is its own (the views skip a frame)
                self.faults.record("world", exc)
        self.ticks += 1
        for waiter in self._tick_waiters.pop(self.ticks, ()):  # the teleoperation sockets push what this tick moved
            if not waiter.done():
                waiter.set_result(None)
        return worlds


@dataclass(frozen=True)
class Playback:
    attempt: Any
    start: float  # monotonic time the attempt began
    speed: float

    def state(self, now: float) -> WorldState:
        return self.attempt.state_at(max(0.0, now - self.start) * self.speed)


def _is_motion(command: TeleopCommand) -> bool:
    return command.ee_velocity is not None or command.joint_velocity is not None


def _offer(queue: asyncio.Queue, frame: dict[str, Any]) -> None:
    """Keep only the newest frame: a slow viewer skips frames instead of queueing them."""
    if queue.full():
        try:
            queue.get_nowait()
        except asyncio.QueueEmpty:
            pass
    queue.put_nowait(frame)


def _input_dict(held: TeleopCommand, gripper: str | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if held.ee_velocity is not None:
        out["ee_velocity"] = list(held.ee_velocity)
    if held.joint_velocity is not None:
        out["joint_velocity"] = list(held.joint_velocity)
    if gripper is not None:
        out["gripper"] = gripper
    return out


def world_frame(state: WorldState) -> dict[str, Any]:
    poses = {name: [list(map(float, p)), list(map(float, q))] for name, (p, q) in link_poses(state).items()}
    return world_state_dict(state) | {"poses": poses}


def world_state_dict(state: WorldState) -> dict[str, Any]:
    """A JSON form of the world state (what bots and the page read)."""
    item = state.item
    return {"t": state.t, "base": list(state.base), "joints": list(state.joints), "gripper": state.gripper,
            "gripper_target": state.gripper_target,
            "item": {"mode": item.mode.value, "position": list(item.position), "wxyz": list(item.wxyz)}}


