"""What a study configuration amounts to, in words a researcher checks before launch.

Trials per block and in total (practice apart), the expected duration (``experiment.duration``), the block orders
counterbalancing assigns, each block's policy in words (the trust-aware policy by its solved thresholds), the
questionnaires and when they are asked, and what a participant is paid. Pure: the designer's summary panel and
``GET /api/admin/studies/{slug}/summary`` show it.
"""

from __future__ import annotations

from dataclasses import dataclass

from experiment.agnostic import AgnosticPolicy
from experiment.belief_mdp import BeliefMDPSolution
from experiment.config import (
    AlwaysAskSpec,
    AlwaysAutoSpec,
    BlockConfig,
    CompensationConfig,
    RandomAssistSpec,
    StudyConfig,
    TrustAgnosticSpec,
)
from experiment.duration import estimate_duration
from experiment.engine import build_policy
from experiment.policies import TrustAgnostic, TrustAware
from experiment.schedule import CountsSchedule, n_shelves
from experiment.simulate import order_names
from experiment.task import Complexity, RobotAction
from experiment.trust_states_policy import KPolicySolution, ask_share


@dataclass(frozen=True)
class BlockSummary:
    name: str
    trials: int
    n_low: float  # expected for a Bernoulli schedule
    n_high: float
    schedule: str
    shelves: int
    policy: str
    questionnaires_after: list[str]


@dataclass(frozen=True)
class QuestionnaireUse:
    id: str
    title: str
    items: int
    when: str


@dataclass(frozen=True)
class StudySummary:
    blocks: list[BlockSummary]
    scored_trials: int
    practice_trials: int
    duration_low_minutes: int
    duration_high_minutes: int
    duration: str
    counterbalance: str
    orders: list[list[str]]
    questionnaires: list[QuestionnaireUse]
    payment: str


def summarize(config: StudyConfig) -> StudySummary:
    """The summary of a valid configuration (trust-aware policies are solved; solutions are cached)."""
    blocks = [_block(config, block) for block in config.blocks]
    estimate = estimate_duration(config)
    practice = len(config.practice.trials) if config.practice.enabled else 0
    return StudySummary(
        blocks=blocks, scored_trials=sum(b.trials for b in blocks), practice_trials=practice,
        duration_low_minutes=estimate.low_minutes, duration_high_minutes=estimate.high_minutes,
        duration=estimate.text, counterbalance=_counterbalance_words(config),
        orders=[list(order) for order in order_names(config)], questionnaires=_questionnaires(config),
        payment=payment_words(config.compensation))


def _block(config: StudyConfig, block: BlockConfig) -> BlockSummary:
    schedule = block.schedule
    n = schedule.n_trials
    if isinstance(schedule, CountsSchedule):
        n_low, n_high = float(schedule.n_low), float(schedule.n_high)
        words = f"{schedule.n_low} low + {schedule.n_high} high complexity, shuffled"
    else:
        n_high = n * schedule.p_high
        n_low = n - n_high
        words = f"each trial high complexity with probability {_num(schedule.p_high)} (about {_num(n_high)} of {n})"
    return BlockSummary(name=block.name, trials=n, n_low=n_low, n_high=n_high, schedule=words,
                        shelves=n_shelves(n, config.shelf_size), policy=policy_words(block, config),
                        questionnaires_after=list(block.questionnaires_after))


def policy_words(block: BlockConfig, config: StudyConfig) -> str:
    """The block's policy in words, with its numbers (the trust-aware policy as solved)."""
    spec = block.policy
    if isinstance(spec, AlwaysAutoSpec):
        return "always acts alone: never asks for help"
    if isinstance(spec, AlwaysAskSpec):
        return "always asks for help"
    if isinstance(spec, RandomAssistSpec):
        return (f"random: asks with probability {_num(spec.p_ask_low)} in low and {_num(spec.p_ask_high)} in high "
                f"complexity")
    policy = build_policy(block, config)  # the policy the study runs, so the words cannot drift from it
    if isinstance(spec, TrustAgnosticSpec):
        assert isinstance(policy, TrustAgnostic)
        return _agnostic_words(spec, policy.baseline)
    assert isinstance(policy, TrustAware)
    solution = policy.solution
    if isinstance(solution, KPolicySolution):
        shares = ask_share(solution)
        return (f"trust-aware ({solution.n_states} trust states): asks in high complexity where the belief of low "
                f"trust is high ({shares[Complexity.HIGH]:.0%} of beliefs), in low complexity in "
                f"{shares[Complexity.LOW]:.0%} of beliefs")
    return "trust-aware: " + "; ".join(_aware_words(solution, c) for c in (Complexity.HIGH, Complexity.LOW))


def _aware_words(solution: BeliefMDPSolution, complexity: Complexity) -> str:
    where = f"in {complexity.value} complexity"
    constant = solution.constant_action[complexity]
    if constant is not None:
        return f"always asks {where}" if constant == RobotAction.ASK else f"never asks {where}"
    threshold = solution.thresholds[complexity]
    if threshold is not None:
        return f"asks {where} when the belief of high trust ≤ {threshold:.2f}"
    switches = ", ".join(f"{b:.2f}" for b in solution.switches[complexity])
    return f"asks {where} depending on the belief of high trust (switches at {switches})"


def _agnostic_words(spec: TrustAgnosticSpec, policy: AgnosticPolicy) -> str:
    actions = {c: policy.action[c] for c in Complexity}
    if set(actions.values()) == {RobotAction.AUTO}:
        decision = "never asks"
    elif set(actions.values()) == {RobotAction.ASK}:
        decision = "always asks"
    else:
        decision = " and ".join(f"{'asks' if a == RobotAction.ASK else 'acts alone'} in {c.value}"
                                for c, a in actions.items())
    if spec.actions is not None:
        return f"trust-agnostic (actions given): {decision}"
    observed = f"intervention rates {_num(spec.intervention_rate_low)} low, {_num(spec.intervention_rate_high)} high"
    auto = ", ".join(f"{policy.expected_reward_auto[c]:.2f} {c.value}" for c in Complexity)
    ask = policy.expected_reward_ask[Complexity.LOW]
    return f"trust-agnostic ({observed}): {decision} (expected reward acting alone {auto}; asking {_num(ask)})"


def _counterbalance_words(config: StudyConfig) -> str:
    if len(config.blocks) == 1:
        return "one block: no block order to balance"
    return {"none": "none: every participant meets the blocks as listed",
            "all": "every order of the blocks, assigned to keep the orders balanced",
            "latin": "the rows of a Latin square, assigned to keep the orders balanced"}[config.counterbalance]


def _questionnaires(config: StudyConfig) -> list[QuestionnaireUse]:
    when: dict[str, list[str]] = {}
    for q in config.questionnaires_before:
        when.setdefault(q, []).append("before the first block")
    if config.shelf_questionnaire:
        when.setdefault(config.shelf_questionnaire, []).append(
            f"after each shelf of {config.shelf_size} trial{'s' if config.shelf_size != 1 else ''}")
    for block in config.blocks:
        for q in block.questionnaires_after:
            when.setdefault(q, []).append(f"after block {block.name}")
    for q in config.questionnaires_end:
        when.setdefault(q, []).append("at the end of the study, after every block")
    return [QuestionnaireUse(id=q, title=config.questionnaire(q).title, items=len(config.questionnaire(q).items),
                             when="; ".join(times)) for q, times in when.items()]


def payment_words(pay: CompensationConfig) -> str:
    """What the participant is paid, in words."""
    bonus = pay.has_bonus
    if not pay.defined:
        return "nothing (the recruitment site pays)"
    parts = [f"{_money(pay.base, pay.currency)} for taking part"] if pay.base > 0 else []
    if bonus:
        parts.append(f"{_money(pay.bonus_per_point, pay.currency)} per point of the final score, up to "
                     f"{_money(pay.bonus_cap, pay.currency)}")
    most = f" (at most {_money(pay.base + pay.bonus_cap, pay.currency)})" if bonus and pay.base > 0 else ""
    return " + ".join(parts) + most


def _money(amount: float, currency: str) -> str:
    return f"{amount:.2f} {currency}"


def _num(value: float | None) -> str:
    """A probability or count without trailing zeros (0.1, 0.33, 12)."""
    return "—" if value is None else f"{value:.4g}"
