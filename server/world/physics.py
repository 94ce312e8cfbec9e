"""The helper process that moves the teleoperated arms when many move at once (``WorldHub.run``).

Integrating a held arm is pure-Python arithmetic (~60 µs a sub-step, two sub-steps a tick at a 2x robot); with
100 participants teleoperating it took half of the interpreter lock of the server's one process, and every
request, acknowledgement and 3D frame waited behind it. Here it runs on another core: each tick the server sends
one batch (the arms' states, the inputs they hold, for how long) and applies what comes back, on the event loop.
A job carries its scene only the first time (``scene_id``); the helper keeps scenes by id.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

from experiment.world import Scene, WorldState
from experiment.world.teleop import HeldMove, TeleopRules, hold_moves

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


def timed_advance_arms(jobs: Sequence[ArmJob]) -> tuple[list[list[tuple[WorldState, tuple[str, ...]] | None]], float]:
    """``advance_arms``, and the seconds it took (what the same moves would cost the server: ``WorldHub``)."""
    start = time.perf_counter()
    results = advance_arms(jobs)
    return results, time.perf_counter() - start


def advance_arms(jobs: Sequence[ArmJob]) -> list[list[tuple[WorldState, tuple[str, ...]] | None]]:
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
