"""The world of one trial of one participant, derived from seeds alone.

A trial's scene and its autonomous attempt are deterministic in (study seed,
participant, block, trial): any process can rebuild them, so the server may
plan an attempt in a helper process and get the same attempt it would plan
itself.
"""

from __future__ import annotations

from functools import lru_cache

from experiment.schedule import derive_rng
from experiment.world.attempt import Attempt, plan_attempt
from experiment.world.scene import Scene, build_scene, scene_stamp


def scene_seed(study_seed: int, participant_key: str, block_name: str, trial: int) -> int:
    return int(derive_rng(study_seed, participant_key, block_name, trial, "scene").integers(2**62))


def trial_scene(study_seed: int, participant_key: str, block_name: str, trial: int, complexity: str) -> Scene:
    return build_scene(complexity, scene_seed(study_seed, participant_key, block_name, trial))


def trial_scene_stamp(study_seed: int, participant_key: str, block_name: str, trial: int, complexity: str) -> str:
    """``trial_scene(...).stamp`` without building the scene."""
    return scene_stamp(complexity, scene_seed(study_seed, participant_key, block_name, trial))


def trial_attempt(study_seed: int, participant_key: str, block_name: str, trial: int, complexity: str,
                  success: bool) -> Attempt:
    """The trial's autonomous attempt (a success, or a failure of the trial's drawn kind)."""
    rng = derive_rng(study_seed, participant_key, block_name, trial, "attempt")
    return plan_attempt(trial_scene(study_seed, participant_key, block_name, trial, complexity), success, rng)


@lru_cache(maxsize=4096)
def trial_target_parts(study_seed: int, participant_key: str, block_name: str, trial: int, complexity: str):
    """What names the trial's item to collect (``guidance.TargetParts``; cached: the state names it on every poll)."""
    from experiment.world.guidance import target_parts  # guidance imports the scene modules this one does

    return target_parts(trial_scene(study_seed, participant_key, block_name, trial, complexity))


@lru_cache(maxsize=4096)
def trial_target(study_seed: int, participant_key: str, block_name: str, trial: int, complexity: str) -> str:
    """The trial's item to collect in words (cached: the participant's state names it on every poll)."""
    from experiment.world.guidance import describe_target  # guidance imports the scene modules this one does

    return describe_target(trial_scene(study_seed, participant_key, block_name, trial, complexity))
