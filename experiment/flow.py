"""The participant's path through a study, as a pure step machine.

consent → instructions → practice trials → questionnaires before → for each
block in the participant's order: trials, with the shelf survey after each
shelf's last trial, then that block's questionnaires → debrief.

A ``Step`` is a small JSON-able dict stored with the participant; the server
moves a participant only with ``next_step`` and only when the current step's
work is recorded, so ``GET`` of the state can always say what to show.
"""

from __future__ import annotations

from typing import Any

from experiment.config import StudyConfig
from experiment.schedule import shelves

Step = dict[str, Any]

CONSENT: Step = {"phase": "consent"}
INSTRUCTIONS: Step = {"phase": "instructions"}
DEBRIEF: Step = {"phase": "debrief"}
#: Terminal steps other than the debrief.
DECLINED: Step = {"phase": "declined"}
FINISHED_PHASES = ("debrief", "declined")


def first_step() -> Step:
    return dict(CONSENT)


def next_step(config: StudyConfig, step: Step, block_order: list[str] | None = None) -> Step:
    """The step after ``step`` (``block_order`` is needed once trials begin)."""
    phase = step["phase"]
    if phase == "consent":
        return dict(INSTRUCTIONS)
    if phase == "instructions":
        return _after_instructions(config)
    if phase == "practice":
        if step["index"] + 1 < len(config.practice.trials):
            return {"phase": "practice", "index": step["index"] + 1}
        return _before_questionnaire(config, 0)
    if phase == "questionnaire" and step["context"] == "before":
        return _before_questionnaire(config, config.questionnaires_before.index(step["questionnaire"]) + 1)
    if block_order is None:
        raise ValueError("the block order is needed after the first trial")
    if phase == "trial":
        return _after_trial(config, step, block_order)
    if phase == "shelf_survey":
        return _after_shelf(config, step, block_order)
    if phase == "questionnaire":
        block = config.block(block_order[step["block"] - 1])
        return _after_block(config, step["block"], block.questionnaires_after.index(step["questionnaire"]) + 1, block_order)
    raise ValueError(f"no step follows {phase!r}")


def _after_instructions(config: StudyConfig) -> Step:
    if config.practice.enabled and config.practice.trials:
        return {"phase": "practice", "index": 0}
    return _before_questionnaire(config, 0)


def _before_questionnaire(config: StudyConfig, index: int) -> Step:
    if index < len(config.questionnaires_before):
        return {"phase": "questionnaire", "context": "before", "questionnaire": config.questionnaires_before[index]}
    return {"phase": "trial", "block": 1, "trial": 1}


def _after_trial(config: StudyConfig, step: Step, block_order: list[str]) -> Step:
    block = config.block(block_order[step["block"] - 1])
    n_trials = block.schedule.n_trials
    shelf_of = shelves(n_trials, config.shelf_size)
    index = step["trial"] - 1
    shelf_ends = index + 1 == n_trials or shelf_of[index + 1] != shelf_of[index]
    if shelf_ends and config.shelf_questionnaire:
        return {"phase": "shelf_survey", "block": step["block"], "shelf": shelf_of[index], "trial": step["trial"]}
    return _after_shelf(config, step, block_order)


def _after_shelf(config: StudyConfig, step: Step, block_order: list[str]) -> Step:
    block = config.block(block_order[step["block"] - 1])
    if step["trial"] < block.schedule.n_trials:
        return {"phase": "trial", "block": step["block"], "trial": step["trial"] + 1}
    return _after_block(config, step["block"], 0, block_order)


def _after_block(config: StudyConfig, block_position: int, index: int, block_order: list[str]) -> Step:
    block = config.block(block_order[block_position - 1])
    if index < len(block.questionnaires_after):
        return {"phase": "questionnaire", "context": f"after:{block_position}", "block": block_position,
                "questionnaire": block.questionnaires_after[index]}
    if block_position < len(block_order):
        return {"phase": "trial", "block": block_position + 1, "trial": 1}
    return dict(DEBRIEF)


def all_steps(config: StudyConfig, block_order: list[str]) -> list[Step]:
    """Every step of a participant who consents, in order (for progress displays and tests)."""
    steps = [first_step()]
    while steps[-1]["phase"] != "debrief":
        steps.append(next_step(config, steps[-1], block_order))
    return steps


def progress(config: StudyConfig, step: Step, block_order: list[str] | None) -> float:
    """Fraction of the study's steps done, for the participant's progress bar."""
    order = block_order or [b.name for b in config.blocks]
    steps = all_steps(config, order)
    try:
        return steps.index(step) / (len(steps) - 1)
    except ValueError:
        return 1.0 if step["phase"] in FINISHED_PHASES else 0.0
