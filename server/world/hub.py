"""``WorldHub``: the live worlds of this process and the loop that moves them.

A participant has at most one live world: starting a teleoperation replaces the participant's playback and any
older teleoperation, and starting a playback replaces the participant's teleoperation. A loop at ``world_hz``
advances every teleoperated arm (``server.world.teleop``), in the physics helper when many move
(``server.world.physics``), and hands the worlds someone watches to the sockets and the 3D views.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterable
from threading import RLock
from typing import Any

from experiment.engine import PlannedTrial
from experiment.flow import TrialRef
from experiment.world import Attempt, Scene
from experiment.world.teleop import DEFAULT_RULES, TeleopRules
from server.faults import FaultLog
from server.settings import Settings
from server.world.attempts import AttemptInfo, Attempts, trial_scene_of
from server.world.physics import PhysicsHelper
from server.world.playback import LiveWorld, Playback, Playbacks, world_frame
from server.world.teleop import Teleops, TeleopSession, TrialKey

#: A world tick that starts this share of a period after its time counts as late (the event loop held it up; 10 ms
#: at 30 Hz): the figure the server's load report gives (``server.loadmeter``). A share, not a time: at the
#: ``world_hz`` a deployment sets (up to 240), late means the same part of a tick. The 3D view pacer sheds frames
#: only from a later start (``server.viewer.manager.LATE_STEP_PERIODS``).
LATE_TICK_PERIODS = 0.3

TickListener = Callable[[dict[str, LiveWorld]], None]
#: The participant keys a tick listener needs worlds for (None: every live world).
WantedKeys = Callable[[], Iterable[str]] | None


class WorldHub:
    """Scenes, attempts and teleoperations of the sessions this process serves, and the world loop.

    It implements ``server.services.trials.AttemptPlanner`` (``attempt``, ``teleop_over``, ``prepare_attempt``).
    """

    def __init__(self, settings: Settings, faults: FaultLog | None = None):
        self.settings = settings
        self.faults = faults or FaultLog()  # contained failures of one session's step (``server.faults``)
        self._lock = RLock()  # one for all the parts: a participant's teleoperation and playback replace each other
        self.arms = Teleops(settings, self.faults, self._lock)
        self.playbacks = Playbacks(self._lock)
        self.attempts = Attempts(settings, self._lock)
        self.physics = PhysicsHelper(settings, self.arms, self._lock)
        self._subscribers: dict[str, list[asyncio.Queue]] = {}
        self._tick_listeners: list[tuple[TickListener, WantedKeys]] = []
        self._tick_waiters: dict[int, list[asyncio.Future]] = {}  # by the tick (``ticks``) they wait for
        self.ticks = 0
        self.late_s = 0.0  # how late the loop's latest tick started: the event loop is that congested
        self.late_ticks = 0  # ticks that started LATE_TICK_PERIODS late or more (``server.loadmeter`` reads them)
        self.latest_start_s = 0.0  # the latest start of a tick since ``take_latest_start`` (the loop's worst hold-up)

    @property
    def ticking(self) -> bool:
        """Whether the world loop runs (``run``): it advances every teleoperated arm."""
        return self.arms.ticking

    @ticking.setter
    def ticking(self, value: bool) -> None:
        self.arms.ticking = value

    @property
    def period_s(self) -> float:
        """The world loop's period (s): lateness is judged as a share of it."""
        return 1.0 / self.settings.world_hz

    def close(self) -> None:
        """Stop the planner and physics processes (attempts still being planned are dropped)."""
        self.attempts.close()
        self.physics.close()

    # -- a participant's live world ----------------------------------------------------------------------------------
    def scene(self, study_seed: int, participant_key: str, planned: PlannedTrial) -> Scene:
        return trial_scene_of(study_seed, participant_key, planned)

    def teleop(self, key: TrialKey, scene: Scene, rules: TeleopRules = DEFAULT_RULES, speed: float = 1.0
               ) -> TeleopSession:
        """The teleoperation of a trial (it replaces the participant's playback), started from the ready pose the
        first time it is asked for."""
        with self._lock:
            dropped = self.playbacks.drop(key.participant_key)
            session = self.arms.start(key, scene, rules, speed)
        if dropped is not None:
            self.playbacks.tell(key.participant_key, None)
        return session

    def play(self, participant_key: str, attempt: Attempt, start: float, speed: float) -> None:
        """Show ``attempt`` from monotonic time ``start`` (the decision deadline) at ``speed`` (it replaces the
        participant's teleoperation)."""
        playback = Playback(attempt, start, speed)
        with self._lock:
            self.arms.drop(participant_key)
            self.playbacks.start(participant_key, playback)
        self.playbacks.tell(participant_key, playback)

    def stop(self, participant_key: str) -> None:
        """The participant's playback ends."""
        if self.playbacks.drop(participant_key) is not None:
            self.playbacks.tell(participant_key, None)

    def world_of(self, participant_key: str, now: float | None = None) -> LiveWorld | None:
        """The participant's live world now: the teleoperation, else the attempt played back (None: neither)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return self._live_world(participant_key, now)

    def _live_world(self, participant_key: str, now: float) -> LiveWorld | None:
        if (teleop := self.arms.get(participant_key)) is not None:
            return LiveWorld(teleop.scene.seed, teleop.state)
        if (playback := self.playbacks.get(participant_key)) is not None:
            return LiveWorld(playback.attempt.scene.seed, playback.state(now))
        return None

    def moving(self, now: float) -> tuple[int, int]:
        """(attempts being played back, arms under teleoperation) at ``now``."""
        with self._lock:
            return self.playbacks.playing(now), len(self.arms)

    # -- ``AttemptPlanner`` (the trials' service) ---------------------------------------------------------------------
    def attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool, *,
                started_ago_s: float, speed: float) -> AttemptInfo:
        """Plan the autonomous attempt of a trial and start playing it back."""
        attempt = self.attempts.get(study_seed, participant_key, planned, success)
        self.play(participant_key, attempt, time.monotonic() - started_ago_s, speed)
        return AttemptInfo(attempt.duration, attempt.failure_mode)

    def prepare_attempt(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> None:
        self.attempts.prepare(study_seed, participant_key, planned, success)

    def teleop_over(self, participant_key: str, ref: TrialRef) -> None:
        """The trial's teleoperation ended without a deposit (its time limit passed)."""
        self.arms.end(TrialKey(participant_key, ref))

    # -- watchers ----------------------------------------------------------------------------------------------------
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

    # -- the loop ----------------------------------------------------------------------------------------------------
    async def run(self) -> None:
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
                    self.physics.start(now)
                    self.tick(now, wanted_only=True)
                except Exception as exc:  # noqa: BLE001 -- the next tick tries again; one bad tick stops no one
                    self.faults.record("world", exc)
                next_tick += period
                await asyncio.sleep(max(0.0, next_tick - time.monotonic()))
        finally:
            self.ticking = False
            self.physics.cancel()

    def note_start(self, late_s: float) -> None:
        """Count a tick of the loop that started ``late_s`` after its time (the load report's figures)."""
        self.late_s = late_s
        self.late_ticks += late_s >= LATE_TICK_PERIODS * self.period_s
        self.latest_start_s = max(self.latest_start_s, late_s)

    def take_latest_start(self) -> float:
        """How late the latest-starting tick since the last call started (s), and start over."""
        latest, self.latest_start_s = self.latest_start_s, 0.0
        return latest

    def tick(self, now: float | None = None, *, wanted_only: bool = False) -> dict[str, LiveWorld]:
        """Advance the live worlds to ``now``, hand each subscriber its newest frame, tell the listeners.

        ``wanted_only``: only the worlds of subscribers and of what the listeners want (the world loop: with
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
            for teleop in self.arms:  # the arms move on the server's clock, watched or not
                if id(teleop) not in self.physics.in_flight:  # (those the physics helper is moving: when it is done)
                    self.arms.advance(teleop, now)
            live = self.playbacks.keys() | self.arms.keys()
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


def _offer(queue: asyncio.Queue, frame: dict[str, Any]) -> None:
    """Keep only the newest frame: a slow viewer skips frames instead of queueing them."""
    if queue.full():
        try:
            queue.get_nowait()
        except asyncio.QueueEmpty:
            pass
    queue.put_nowait(frame)
