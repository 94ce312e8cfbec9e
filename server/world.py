"""The live robot worlds of active sessions (server memory, rebuilt on demand).

Every trial's scene and autonomous attempt are deterministic in (study seed,
participant, block, trial), so nothing here needs to survive a restart: the
database holds the trial's stage and deadlines, and the world of any trial
can be rebuilt from them. Teleoperation advances the world per command
(the server owns the arm); a 30 Hz loop computes the pose of every active
world for the viewers.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from threading import Lock
from typing import Any

from fastapi import FastAPI

from experiment.engine import PlannedTrial
from experiment.world import Attempt, Scene, WorldState, link_poses, teleop_start_state, teleop_step
from experiment.world.constants import MAX_TELEOP_DT
from experiment.world.trial import trial_attempt, trial_scene
from server.planner import planner_pool
from server.ratelimit import RateLimiter
from server.services.trials import AttemptInfo
from server.settings import Settings

logger = logging.getLogger(__name__)

#: A command after a pause moves the arm for at most this long (s, before the speed-up).
MAX_COMMAND_GAP_S = 2 / 30
#: Teleoperation is sped up by the study's animation speed, but at most this much: a command then
#: moves the arm for at most MAX_COMMAND_GAP_S * 8 ≈ 0.53 s, which a closed-loop operator can still steer.
MAX_TELEOP_SPEEDUP = 8.0
RATE_BURST = 10  # commands allowed in a burst above the steady rate
#: Planned attempts kept (about two per active session): planning one takes milliseconds of CPU, which a
#: request would otherwise spend holding the database.
ATTEMPT_CACHE_SIZE = 1024


@dataclass(frozen=True)
class TrialKey:
    participant_key: str
    practice: bool
    block: int
    trial: int


@dataclass
class TeleopSession:
    """One teleoperation in progress (in memory; a restart starts the arm from its ready pose again)."""

    key: TrialKey
    scene: Scene
    state: WorldState
    started: float = field(default_factory=time.monotonic)
    last_command: float | None = None
    commands: int = 0
    done: bool = False
    log: list[list[Any]] = field(default_factory=list)  # commands not yet written to the event log

    @property
    def participant_key(self) -> str:
        return self.key.participant_key

    def take_log(self) -> list[list[Any]]:
        """The commands logged since the last call (to be written to the event log)."""
        batch, self.log = self.log, []
        return batch


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

    def __init__(self, settings: Settings):
        self.settings = settings
        self._teleops: dict[str, TeleopSession] = {}  # by participant key
        self._playbacks: dict[str, Playback] = {}
        self._subscribers: dict[str, list[asyncio.Queue]] = {}
        self._tick_listeners: list[tuple[TickListener, WantedKeys]] = []
        self._attempts: OrderedDict[tuple, Any] = OrderedDict()
        self._teleop_limit = RateLimiter(settings.teleop_rate_limit_hz, RATE_BURST)
        self._planning: set[tuple] = set()  # attempts the planner processes are working on
        self._planner: ProcessPoolExecutor | None = None
        self._lock = Lock()
        self.ticks = 0

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
                self._planner = planner_pool(self.settings.planner_processes)
            return self._planner

    def close(self) -> None:
        """Stop the planner processes (attempts still being planned are dropped)."""
        if self._planner is not None:
            self._planner.shutdown(wait=False, cancel_futures=True)
            self._planner = None

    def attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool, *,
                started_ago_s: float, speed: float) -> AttemptInfo:
        """Plan the autonomous attempt of a trial (``AttemptPlanner``) and start playing it back."""
        attempt = self.attempt_for(study_seed, participant_key, planned, success)
        self.play(participant_key, attempt, time.monotonic() - started_ago_s, speed)
        return AttemptInfo(attempt.duration, attempt.failure_mode)

    # -- teleoperation -----------------------------------------------------------------
    def teleop(self, key: TrialKey, scene: Scene) -> TeleopSession:
        """The teleoperation of a trial, started from the ready pose the first time it is asked for."""
        with self._lock:
            self._playbacks.pop(key.participant_key, None)
            session = self._teleops.get(key.participant_key)
            if session is None or session.key != key:
                session = self._teleops[key.participant_key] = TeleopSession(key, scene, teleop_start_state(scene))
            return session

    def command(self, session: TeleopSession, command: Any, speed: float, now: float | None = None
                ) -> tuple[WorldState, tuple[str, ...]]:
        """Apply one command for the time since the previous one (capped), scaled by the animation speed."""
        now = time.monotonic() if now is None else now
        gap = MAX_COMMAND_GAP_S / 2 if session.last_command is None else min(now - session.last_command, MAX_COMMAND_GAP_S)
        session.last_command, session.commands = now, session.commands + 1
        remaining, events = max(gap, 1e-4) * min(speed, MAX_TELEOP_SPEEDUP), []
        state = session.state
        while remaining > 1e-9:
            dt = min(remaining, MAX_TELEOP_DT / 2)
            state, step_events = teleop_step(state, session.scene, command, dt)
            events.extend(step_events)
            remaining -= dt
            if isinstance(command, dict) and "gripper" in command:  # a gripper action happens once, not per sub-step
                command = {k: v for k, v in command.items() if k != "gripper"}
        session.state = state
        return state, tuple(events)

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
        with self._lock:
            self._teleops.pop(participant_key, None)
            self._playbacks[participant_key] = Playback(attempt, start, speed)

    def stop(self, participant_key: str) -> None:
        with self._lock:
            self._playbacks.pop(participant_key, None)

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
        """Tick at ``world_hz`` with a deadline loop (no drift)."""
        period = 1.0 / self.settings.world_hz
        next_tick = time.monotonic()
        while True:
            next_tick += period
            self.tick(wanted_only=True)
            await asyncio.sleep(max(0.0, next_tick - time.monotonic()))

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
            live = self._playbacks.keys() | self._teleops.keys()
            keys = live if keys is None else keys & live
            worlds = {key: world for key in keys if (world := self._live_world(key, now)) is not None}
        for key, queues in subscribers.items():
            if key in worlds:
                frame = world_frame(worlds[key].state)
                for queue in queues:
                    _offer(queue, frame)
        for listener in listeners:
            listener(worlds)
        self.ticks += 1
        return worlds


@dataclass(frozen=True)
class Playback:
    attempt: Any
    start: float  # monotonic time the attempt began
    speed: float

    def state(self, now: float) -> WorldState:
        return self.attempt.state_at(max(0.0, now - self.start) * self.speed)


def _offer(queue: asyncio.Queue, frame: dict[str, Any]) -> None:
    """Keep only the newest frame: a slow viewer skips frames instead of queueing them."""
    if queue.full():
        try:
            queue.get_nowait()
        except asyncio.QueueEmpty:
            pass
    queue.put_nowait(frame)


def world_frame(state: WorldState) -> dict[str, Any]:
    poses = {name: [list(map(float, p)), list(map(float, q))] for name, (p, q) in link_poses(state).items()}
    return world_state_dict(state) | {"poses": poses}


def world_state_dict(state: WorldState) -> dict[str, Any]:
    """A JSON form of the world state (what bots and the page read)."""
    item = state.item
    return {"t": state.t, "base": list(state.base), "joints": list(state.joints), "gripper": state.gripper,
            "gripper_target": state.gripper_target,
            "item": {"mode": item.mode.value, "position": list(item.position), "wxyz": list(item.wxyz)}}


