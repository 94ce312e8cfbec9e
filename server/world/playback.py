"""Autonomous attempts being shown, and the frames a live world sends to its watchers."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from threading import RLock
from typing import Any

from experiment.world import Attempt, WorldState, link_poses

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Playback:
    attempt: Attempt
    start: float  # monotonic time the attempt began
    speed: float

    def state(self, now: float) -> WorldState:
        return self.attempt.state_at(max(0.0, now - self.start) * self.speed)

    def playing(self, now: float) -> bool:
        return now - self.start < self.attempt.duration / self.speed


@dataclass(frozen=True)
class LiveWorld:
    """A participant's world at one moment, with the seed of the trial scene it belongs to."""

    scene_seed: object  # the scene's seed (Scene.seed)
    state: WorldState


#: Told of every playback started (a ``Playback``) or dropped (None), by participant key, outside the lock.
PlaybackListener = Callable[[str, Playback | None], None]


class Playbacks:
    """The attempts being shown in this process, by participant (``lock``: the world's, see ``Teleops``)."""

    def __init__(self, lock: RLock) -> None:
        self._lock = lock
        self._by_participant: dict[str, Playback] = {}
        #: the 3D view process plays the same attempts (``server.viewer.remote``)
        self.listener: PlaybackListener | None = None

    def start(self, participant_key: str, playback: Playback) -> None:
        with self._lock:
            self._by_participant[participant_key] = playback

    def get(self, participant_key: str) -> Playback | None:
        return self._by_participant.get(participant_key)

    def drop(self, participant_key: str) -> Playback | None:
        with self._lock:
            return self._by_participant.pop(participant_key, None)

    def keys(self) -> set[str]:
        return set(self._by_participant)

    def playing(self, now: float) -> int:
        with self._lock:
            return sum(p.playing(now) for p in self._by_participant.values())

    def tell(self, participant_key: str, playback: Playback | None) -> None:
        """Tell the listener (call outside the lock)."""
        if (listener := self.listener) is not None:
            try:
                listener(participant_key, playback)
            except Exception:  # the view may miss a playback; the participant's trial goes on
                logger.exception("playback listener failed")


def world_frame(state: WorldState) -> dict[str, Any]:
    """The world state with the pose of every link (what a viewer subscribed to a world gets each tick)."""
    poses = {name: [list(map(float, p)), list(map(float, q))] for name, (p, q) in link_poses(state).items()}
    return world_state_dict(state) | {"poses": poses}


def world_state_dict(state: WorldState) -> dict[str, Any]:
    """A JSON form of the world state (what bots and the page read)."""
    item = state.item
    return {"t": state.t, "base": list(state.base), "joints": list(state.joints), "gripper": state.gripper,
            "gripper_target": state.gripper_target,
            "item": {"mode": item.mode.value, "position": list(item.position), "wxyz": list(item.wxyz)}}
