"""The helper process that moves the teleoperated arms when many move at once (``PhysicsHelper``).

Integrating a held arm is pure-Python arithmetic (~60 µs a sub-step, two sub-steps a tick at a 2x robot); with
100 participants teleoperating it took half of the interpreter lock of the server's one process, and every
request, acknowledgement and 3D frame waited behind it. Here it runs on another core: each tick the server sends
one batch (the arms' states, the inputs they hold, for how long) and applies what comes back, on the event loop.
A job carries its scene only the first time (``scene_id``); the helper keeps scenes by id.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from threading import RLock

from experiment.world import Scene, WorldState
from experiment.world.teleop import HeldMove, TeleopRules, WorldEvent, hold_moves, settling
from server.settings import Settings
from server.world.processes import helper_pool
from server.world.teleop import AdvanceStep, Teleops, TeleopSession

logger = logging.getLogger(__name__)

#: After the physics helper failed, how long the arms move in the server before a new helper is started.
PHYSICS_RETRY_S = 10.0

#: Scenes a helper keeps, the latest sent (one per teleoperation; a scene is ~3 KB). The server forgets the same
#: ones in the same order (``SceneShipments``), so it sends a scene again exactly when the helper has dropped it.
SCENES_KEPT = 2048

_scenes: OrderedDict[int, Scene] = OrderedDict()


@dataclass(frozen=True, slots=True)
class ArmJob:
    """One arm's advance: from ``state`` through ``moves`` in the scene ``scene_id`` (sent along as ``scene`` the
    first time)."""

    scene_id: int
    scene: Scene | None
    state: WorldState
    rules: TeleopRules
    moves: tuple[HeldMove, ...]


class UnknownScene(LookupError):
    """The helper does not have a job's scene (it was restarted, or dropped it): send scenes again."""


def timed_advance_arms(jobs: Sequence[ArmJob]) -> tuple[list[list[tuple[WorldState, tuple[WorldEvent, ...]] | None]],
                                                        float]:
    """``advance_arms``, and the seconds it took (what the same moves would cost the server)."""
    start = time.perf_counter()
    results = advance_arms(jobs)
    return results, time.perf_counter() - start


def advance_arms(jobs: Sequence[ArmJob]) -> list[list[tuple[WorldState, tuple[WorldEvent, ...]] | None]]:
    """Each job's ``hold_moves`` (run in the helper process)."""
    for job in jobs:
        if job.scene is not None:
            _scenes[job.scene_id] = job.scene
            while len(_scenes) > SCENES_KEPT:
                _scenes.popitem(last=False)
    out = []
    for job in jobs:
        scene = _scenes.get(job.scene_id)
        if scene is None:
            raise UnknownScene(job.scene_id)
        out.append(hold_moves(job.state, scene, job.moves, job.rules))
    return out


class SceneShipments:
    """The scenes the helper has (the server's side of ``_scenes``: same size, same order)."""

    def __init__(self) -> None:
        self._sent: OrderedDict[int, None] = OrderedDict()

    def job(self, scene_id: int, scene: Scene, state: WorldState, rules: TeleopRules,
            moves: tuple[HeldMove, ...]) -> ArmJob:
        if scene_id in self._sent:
            return ArmJob(scene_id, None, state, rules, moves)
        self._sent[scene_id] = None
        while len(self._sent) > SCENES_KEPT:
            self._sent.popitem(last=False)
        return ArmJob(scene_id, scene, state, rules, moves)


def warm_up() -> None:
    """Nothing: submitted once so that the helper has started and imported the world before the first batch."""


ArmWork = tuple[TeleopSession, float, WorldState, list[AdvanceStep], tuple[HeldMove, ...]]  # (arm, from, state, ...)


class PhysicsHelper:
    """Moves the teleoperated arms in a helper process when moving them here would take long enough.

    The world loop does not wait for a batch: it ticks on, showing those arms where they were until their batch is
    back (a tick later, at most a few), and advances the others here. An arm that a message advanced in the meantime
    (an input change, a gripper action, a release: those advance it here, from where it was) keeps that: the
    helper's result for it is dropped, and the next tick goes on from there.
    """

    def __init__(self, settings: Settings, arms: Teleops, lock: RLock) -> None:
        self.settings, self.arms, self._lock = settings, arms, lock
        self._pool: ProcessPoolExecutor | None = None
        self._scenes = SceneShipments()  # the scenes (``TeleopSession.scene_id``) the helper has
        self._started: Future | None = None
        self._retry_at = 0.0  # after a helper failed, the arms move in the server until then
        self._batch: asyncio.Task | None = None  # the batch the helper is computing
        self.in_flight: set[int] = set()  # the sessions (ids) in it: the world loop does not move them meanwhile
        self.batches = 0  # ticks whose arms the helper moved

    def start(self, now: float) -> asyncio.Task | None:
        """Start advancing the moving arms to ``now`` in the helper, when moving them here would take long enough
        (``physics_helper_min_ms``: the arms times ``Teleops.arm_move_s``) and the previous batch is done; None if
        not started."""
        if not self.settings.physics_helper or now < self._retry_at:
            return None
        if self._batch is not None and not self._batch.done():
            return None
        with self._lock:
            # nothing to compute for the others (the world loop only moves their clocks)
            moving = [session for session in self.arms if session.moving or settling(session.state)]
            if not self._worth_it(len(moving)):
                return None
            work: list[ArmWork] = []
            for session in moving:
                steps = self.arms.plan(session, now)
                moves = tuple(step.move for step in steps if step.move is not None)
                if moves:
                    work.append((session, session.advanced_at, session.state, steps, moves))
            if not work or (pool := self.pool()) is None:
                return None
            jobs = [self._scenes.job(session.scene_id, session.scene, state, session.rules, moves)
                    for session, _, state, _, moves in work]
            self.in_flight = {id(session) for session, *_ in work}
        self._batch = asyncio.create_task(self._advanced(pool, jobs, work, now), name="physics")
        return self._batch

    async def advance(self, now: float) -> None:
        """Advance the moving arms to ``now`` in the helper (``start``), and wait for it."""
        if (batch := self.start(now)) is not None:
            await batch

    def cancel(self) -> None:
        if self._batch is not None:
            self._batch.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def pool(self) -> ProcessPoolExecutor | None:
        """The helper once it has started (None until then: it takes a second to spawn and import)."""
        if self._pool is None or self._started is None:
            self._pool, self._scenes = helper_pool(1), SceneShipments()
            self._started = self._pool.submit(warm_up)
        return self._pool if self._started.done() else None

    async def _advanced(self, pool: ProcessPoolExecutor, jobs: list[ArmJob], work: list[ArmWork], now: float) -> None:
        try:
            results, seconds = await asyncio.get_running_loop().run_in_executor(pool, timed_advance_arms, jobs)
        except asyncio.CancelledError:  # the world loop stopped
            with self._lock:
                self.in_flight = set()
            raise
        except Exception:  # a helper that died or lost a scene: the world loop moves the arms here
            logger.warning("physics helper process failed; moving the arms in the server", exc_info=True)
            with self._lock:
                self.in_flight = set()
                self._pool, self._scenes = None, SceneShipments()
                self._retry_at = time.monotonic() + PHYSICS_RETRY_S
            pool.shutdown(wait=False, cancel_futures=True)
            return
        with self._lock:
            self.in_flight = set()
            self.batches += 1
            self.arms.measured_arm_moves(seconds, len(jobs))
            for (session, start, state, steps, _), result in zip(work, results, strict=True):
                if self.arms.is_current(session) and session.advanced_at == start and session.state is state:
                    self.arms.apply(session, steps, result, now)

    def _worth_it(self, arms: int) -> bool:
        """Whether moving ``arms`` arms here would take ``physics_helper_min_ms`` or more (unknown until an arm has
        moved here: then not, unless the threshold is 0)."""
        threshold_s = self.settings.physics_helper_min_ms / 1000
        if arms == 0:
            return False
        if threshold_s == 0:
            return True
        return self.arms.arm_move_s is not None and arms * self.arms.arm_move_s >= threshold_s
