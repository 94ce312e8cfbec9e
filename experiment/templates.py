"""Built-in study designs: the paper's two studies and a short demo (SPEC §3).

Shelf size is not stated in the paper; 8 trials per shelf gives 9 surveys in
study 1 (71 trials) and 5 per block in study 2 (40 trials). The paper's two
studies ask the shelf questions in the paper's words ("the automation",
``SHELF_TRUST_RELIANCE``) and study 2 the Schaefer scale before the blocks and
after each block, about that block's robot, as the paper did; the demo's shelf
questions name the robot as its pages do (the default,
``SHELF_TRUST_RELIANCE_NAMED``). How long each takes
a participant is estimated from the design (``experiment.duration``) and shown
to participants; the titles and descriptions here are for researchers, who see
them on the admin page (participants see ``texts.title``).
"""

from __future__ import annotations

from collections.abc import Callable

from experiment import defaults
from experiment.config import (
    BlockConfig,
    CompensationConfig,
    RandomAssistSpec,
    StudyConfig,
    TimingConfig,
    TrustAgnosticSpec,
    TrustAwareSpec,
)
from experiment.instruments import SCHAEFER_14, SHELF_TRUST_RELIANCE
from experiment.schedule import CountsSchedule

#: The paper's shelf questions, in its words (§4.4–4.5, appendix), for the paper's studies.
PAPER_SHELF_QUESTIONS = {"questionnaires": [SHELF_TRUST_RELIANCE, SCHAEFER_14],
                         "shelf_questionnaire": SHELF_TRUST_RELIANCE.id}


def model_estimation() -> StudyConfig:
    """Paper study 1 (§4): one block of 71 trials (41 low, 30 high), random assistance-seeking."""
    return StudyConfig(
        title="Model estimation (paper study 1)",
        description=(f"One block of {defaults.STUDY1_TRIALS_LOW + defaults.STUDY1_TRIALS_HIGH} trials; the robot asks "
                     f"for help at random (p = {defaults.STUDY1_P_ASK_LOW:.2f} low, {defaults.STUDY1_P_ASK_HIGH:.2f} "
                     "high)."),
        blocks=[BlockConfig(
            name="estimation",
            policy=RandomAssistSpec(p_ask_low=defaults.STUDY1_P_ASK_LOW, p_ask_high=defaults.STUDY1_P_ASK_HIGH),
            schedule=CountsSchedule(n_low=defaults.STUDY1_TRIALS_LOW, n_high=defaults.STUDY1_TRIALS_HIGH),
        )],
        counterbalance="none",
        compensation=CompensationConfig(base=defaults.STUDY1_COMPENSATION_MAX_USD),
        **PAPER_SHELF_QUESTIONS,
    )


def _evaluation_blocks(n_low: int, n_high: int) -> list[BlockConfig]:
    schedule = CountsSchedule(n_low=n_low, n_high=n_high)
    return [
        BlockConfig(name="trust_aware", policy=TrustAwareSpec(model="paper"), schedule=schedule,
                    questionnaires_after=[SCHAEFER_14.id]),
        BlockConfig(name="trust_agnostic", policy=TrustAgnosticSpec(), schedule=schedule,
                    questionnaires_after=[SCHAEFER_14.id]),
    ]


def policy_evaluation() -> StudyConfig:
    """Paper study 2 (§5.2): Schaefer before; two counterbalanced blocks of 40 trials (20 low, 20 high)."""
    return StudyConfig(
        title="Policy evaluation (paper study 2)",
        description="Trust-aware vs. trust-agnostic robot, block order counterbalanced, Schaefer TPS-HRI before and "
                    "after each.",
        blocks=_evaluation_blocks(defaults.STUDY2_TRIALS_LOW_PER_BLOCK, defaults.STUDY2_TRIALS_HIGH_PER_BLOCK),
        questionnaires_before=[SCHAEFER_14.id],
        counterbalance="all",
        **PAPER_SHELF_QUESTIONS,
    )


def demo() -> StudyConfig:
    """Practice, two blocks of 6 trials (3 low, 3 high), a shelf survey every 3 trials (about 10–20 minutes for a
    person: ``experiment.duration``)."""
    return StudyConfig(
        title="trustlab demo",
        description="A short version of the policy-evaluation study to try the platform.",
        blocks=_evaluation_blocks(3, 3),
        shelf_size=3,
        counterbalance="all",
        timing=TimingConfig(teleop_time_limit_s=60.0),
    )


def demo_fast() -> StudyConfig:
    """The demo with machine pacing (50 ms decision window, robot 100× faster): for bots and tests only."""
    return demo().model_copy(update={
        "title": "trustlab demo (fast, for bots)",
        "timing": TimingConfig(decision_window_s=0.05, animation_speed=100.0, teleop_time_limit_s=30.0),
    })


TEMPLATES: dict[str, Callable[[], StudyConfig]] = {
    "model-estimation": model_estimation,
    "policy-evaluation": policy_evaluation,
    "demo": demo,
    "demo-fast": demo_fast,
}


def template(name: str) -> StudyConfig:
    try:
        return TEMPLATES[name]()
    except KeyError:
        raise KeyError(f"unknown design {name!r}; built-in designs: {', '.join(TEMPLATES)}") from None
