"""Scenes and the robot's autonomous attempts, planned ahead in helper processes and kept for when they are shown."""

from __future__ import annotations

import logging
from collections import OrderedDict
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from threading import RLock

from experiment.engine import PlannedTrial
from experiment.world import Attempt, Scene
from experiment.world.attempt import FailureMode
from experiment.world.trial import trial_attempt, trial_scene
from server.settings import Settings
from server.world.processes import helper_pool

logger = logging.getLogger(__name__)

#: Planned attempts kept (about two per active session): planning one takes milliseconds of CPU, which a
#: request would otherwise spend holding the database.
ATTEMPT_CACHE_SIZE = 1024

AttemptArgs = tuple[int, str, str, int, str, bool]  # what ``trial_attempt`` is called with


@dataclass(frozen=True)
class AttemptInfo:
    """What the trial's record needs of an attempt being shown."""

    duration_s: float  # at animation speed 1
    failure_mode: FailureMode | None  # None on success


def trial_scene_of(study_seed: int, participant_key: str, planned: PlannedTrial) -> Scene:
    """The trial's scene (deterministic in the seeds)."""
    return trial_scene(study_seed, participant_key, planned.block_name, planned.trial, planned.complexity.value)


class Attempts:
    """The autonomous attempts of this process's trials: planned once (ahead, in a helper, when asked), then cached."""

    def __init__(self, settings: Settings, lock: RLock) -> None:
        self.settings, self._lock = settings, lock
        self._cache: OrderedDict[AttemptArgs, Attempt] = OrderedDict()
        self._planning: set[AttemptArgs] = set()  # attempts the planner processes are working on
        self._pool: ProcessPoolExecutor | None = None

    @staticmethod
    def _args(study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> AttemptArgs:
        return study_seed, participant_key, planned.block_name, planned.trial, planned.complexity.value, success

    def get(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> Attempt:
        """The trial's autonomous attempt (deterministic; planned once, then cached)."""
        key = self._args(study_seed, participant_key, planned, success)
        with self._lock:
            if (attempt := self._cache.get(key)) is not None:
                self._cache.move_to_end(key)
                return attempt
        attempt = trial_attempt(*key)
        self._remember(key, attempt)
        return attempt

    def prepare(self, study_seed: int, participant_key: str, planned: PlannedTrial, success: bool) -> None:
        """Plan a trial's attempt ahead (after its decision window opened, outside any database transaction).

        With ``planner_processes``, a helper process plans it: planning is milliseconds of pure-Python CPU, which in
        a thread of this process would hold the interpreter lock against the event loop. Whatever the helper has not
        delivered when the attempt is needed is planned here (the same attempt: it depends on seeds only).
        """
        key = self._args(study_seed, participant_key, planned, success)
        if self.settings.planner_processes == 0:
            self.get(study_seed, participant_key, planned, success)
            return
        with self._lock:
            if key in self._cache or key in self._planning:
                return
            self._planning.add(key)
        try:
            future = self._planner_pool().submit(trial_attempt, *key)
        except Exception:  # a broken pool (its process died): plan when needed, and start a new one
            self._pool = None
            with self._lock:
                self._planning.discard(key)
            logger.warning("attempt planner process unavailable; planning in the server", exc_info=True)
            return
        future.add_done_callback(lambda done: self._planned(key, done))

    def close(self) -> None:
        """Stop the planner processes (attempts still being planned are dropped)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def _remember(self, key: AttemptArgs, attempt: Attempt) -> None:
        with self._lock:
            self._cache[key] = attempt
            while len(self._cache) > ATTEMPT_CACHE_SIZE:
                self._cache.popitem(last=False)

    def _planned(self, key: AttemptArgs, done: Future) -> None:
        with self._lock:
            self._planning.discard(key)
        if not done.cancelled() and done.exception() is None:
            self._remember(key, done.result())

    def _planner_pool(self) -> ProcessPoolExecutor:
        with self._lock:  # units may run in several threads (PostgreSQL): one pool, not one each
            if self._pool is None:  # on first use
                self._pool = helper_pool(self.settings.planner_processes)
            return self._pool
