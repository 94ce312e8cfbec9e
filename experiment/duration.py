"""How long a study takes a participant, estimated from its configuration.

The consent and instructions pages announce it, so it must follow the configuration (trial counts, the
decision window, the robot's pace, the share of trials a person steers, the questionnaires) rather than a
sentence written once. The estimate is a range: a quick participant who trusts the robot (reads fast,
rarely intervenes, steers fast) to a slow one who distrusts it (reads slowly, intervenes as the paper's
low-trust participants did, steers slowly). Its constants are in ``experiment.defaults``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

from experiment import defaults
from experiment.agnostic import AgnosticPolicy, trust_agnostic_policy
from experiment.config import (
    AlwaysAskSpec,
    AlwaysAutoSpec,
    BlockConfig,
    RandomAssistSpec,
    StudyConfig,
    TrustAgnosticSpec,
)
from experiment.schedule import n_shelves
from experiment.task import Complexity, RobotAction

QUICK, SLOW = 0, 1


@dataclass(frozen=True)
class DurationEstimate:
    """Whole minutes from a quick to a slow participant."""

    low_minutes: int
    high_minutes: int

    @property
    def text(self) -> str:
        """In words, e.g. "about 10–25 minutes"."""
        return f"about {self.low_minutes}–{self.high_minutes} minutes"


def estimate_duration(config: StudyConfig) -> DurationEstimate:
    """The study's duration for a quick and a slow participant, in whole minutes (in fives past 10 minutes)."""
    low, high = (_round(study_seconds(config, side) / 60) for side in (QUICK, SLOW))
    return DurationEstimate(max(1, low), max(low + 1, high))


def _round(minutes: float) -> int:
    step = 5 if minutes > 10 else 1
    return int(math.floor(minutes / step + 0.5) * step)


def study_seconds(config: StudyConfig, side: int) -> float:
    """Seconds the whole study takes the quick (``side`` 0) or slow (1) participant."""
    return (defaults.FIXED_PAGES_S[side] + _reading_s(config, side) + _practice_s(config, side)
            + sum(_block_s(config, block, side) for block in config.blocks) + _questionnaires_s(config, side))


def _reading_s(config: StudyConfig, side: int) -> float:
    texts = config.texts.in_language(config.default_language, config.default_language)
    words = len(str(texts.consent).split()) + len(str(texts.instructions).split()) + defaults.INSTRUCTIONS_PAGE_WORDS
    return 60 * words / defaults.READING_WORDS_PER_MINUTE[side]


def _teleop_s(config: StudyConfig, side: int) -> float:
    return min(defaults.TELEOP_PERSON_S[side], config.timing.teleop_time_limit_s)


def _relied_s(config: StudyConfig, complexity: Complexity) -> float:
    """A trial the robot attempts: the whole decision window, then the attempt at the study's pace."""
    return config.timing.decision_window_s + attempt_s(complexity) / config.timing.animation_speed


def _intervened_s(config: StudyConfig, side: int) -> float:
    """A trial the participant takes over: half the decision window, then the teleoperation."""
    return config.timing.decision_window_s / 2 + _teleop_s(config, side)


def _practice_s(config: StudyConfig, side: int) -> float:
    practice = config.practice
    if not practice.enabled:
        return 0.0
    total, steered = 0.0, 0
    for trial in practice.trials:
        total += defaults.TRIAL_OVERHEAD_S[side] + config.timing.next_item_pause_s
        if trial.robot_action == RobotAction.AUTO and trial.human_action_hint != "intervene":
            total += _relied_s(config, trial.complexity)
            continue
        if trial.robot_action == RobotAction.AUTO:
            total += config.timing.decision_window_s / 2
        tutorial = practice.tutorial
        total += (min(defaults.TUTORIAL_TELEOP_S[side], tutorial.time_limit_s * tutorial.max_tries)
                  if steered == 0 and tutorial.enabled else _teleop_s(config, side))
        steered += 1
    return total


def _block_s(config: StudyConfig, block: BlockConfig, side: int) -> float:
    p_high = block.schedule.p_high
    total = 0.0
    for complexity, share in ((Complexity.LOW, 1 - p_high), (Complexity.HIGH, p_high)):
        ask = ask_share(block, config, complexity, side)
        intervene = 1 - defaults.PAPER_P_RELY[(complexity.value, "high" if side == QUICK else "low")]
        auto_s = intervene * _intervened_s(config, side) + (1 - intervene) * _relied_s(config, complexity)
        trial_s = (defaults.TRIAL_OVERHEAD_S[side] + config.timing.next_item_pause_s + ask * _teleop_s(config, side)
                   + (1 - ask) * auto_s)
        total += share * block.schedule.n_trials * trial_s
    if config.shelf_questionnaire:
        pages = n_shelves(block.schedule.n_trials, config.shelf_size)
        total += pages * _page_s(config, config.shelf_questionnaire, side)
    return total + sum(_page_s(config, q, side) for q in block.questionnaires_after)


def ask_share(block: BlockConfig, config: StudyConfig, complexity: Complexity, side: int) -> float:
    """The share of the block's trials of ``complexity`` in which the robot asks for help.

    The trust-aware policy asks in high complexity only while it believes trust is low, which depends on the
    participant: none for the quick participant, all for the slow one.
    """
    policy = block.policy
    if isinstance(policy, AlwaysAskSpec):
        return 1.0
    if isinstance(policy, AlwaysAutoSpec):
        return 0.0
    if isinstance(policy, RandomAssistSpec):
        return policy.p_ask_low if complexity == Complexity.LOW else policy.p_ask_high
    if isinstance(policy, TrustAgnosticSpec):
        return float(_agnostic(policy, config).action[complexity] == RobotAction.ASK)
    return float(complexity == Complexity.HIGH and side == SLOW)  # trust-aware: never asks in low complexity


def _agnostic(policy: TrustAgnosticSpec, config: StudyConfig) -> AgnosticPolicy:
    if policy.actions is not None:
        return AgnosticPolicy.explicit(policy.actions, config.task)
    rates = {Complexity.LOW: policy.intervention_rate_low, Complexity.HIGH: policy.intervention_rate_high}
    return trust_agnostic_policy(rates, config.task)


def _questionnaires_s(config: StudyConfig, side: int) -> float:
    """The questionnaires outside the blocks: before the first, and at the end of the study."""
    return sum(_page_s(config, q, side) for q in (*config.questionnaires_before, *config.questionnaires_end))


def _page_s(config: StudyConfig, questionnaire_id: str, side: int) -> float:
    items = len(config.questionnaire(questionnaire_id).items)
    return defaults.QUESTIONNAIRE_PAGE_S[side] + items * defaults.QUESTION_ITEM_S[side]


@cache
def attempt_s(complexity: Complexity) -> float:
    """The robot's successful autonomous attempt, s at animation speed 1 (the planner's; the same in every scene
    of a complexity, as its phases have fixed durations)."""
    from experiment.world.attempt import plan_attempt  # the world is only needed here (and is slower to import)
    from experiment.world.scene import build_scene
    return plan_attempt(build_scene(complexity.value, 0), success=True).duration
