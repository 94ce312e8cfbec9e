"""The trust-agnostic baseline policy (paper §5.1): complexity only, from observed intervention rates.

Complexity is i.i.d., so the optimal complexity-only policy compares one-step
expected rewards per complexity:

    E[R | auto, C] = (1 - q_C) (p_suc,C R_success + (1 - p_suc,C) R_failure) + q_C R_intervene,
    E[R | ask, C]  = R_ask,

with q_C = P(o = intervene | C, auto), estimated as #interventions / #auto
trials in C (``intervention_rates``). Ties go to ask, as in the trust-aware
policy (``belief_mdp``): when the expected rewards are equal, the sure reward
is preferred.

With the paper's rates 0.006 (low) and 0.1848 (high) and the default task,
E[R | auto] = 0.994 * 2.79 = 2.773 in low and 0.8152 * 1.25 = 1.019 in high
complexity; both exceed R_ask = 1, so the policy never asks. The paper prints
2.79 for low complexity: that is the formula without interventions
(0.97 * 3 - 0.03 * 4); the formula as written gives 2.77 (SPEC §11). The
decision is the same either way.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from experiment.sequences import Sequence
from experiment.task import Complexity, HumanAction, RobotAction, TaskParams, expected_reward_given_action


@dataclass(frozen=True)
class InterventionRates:
    """P(o = intervene | C, auto) per complexity, with the counts behind it (None: no auto trials)."""

    rates: dict[Complexity, float | None]
    interventions: dict[Complexity, int]
    auto_trials: dict[Complexity, int]

    def to_dict(self) -> dict[str, Any]:
        return {c.value: {"rate": self.rates[c], "interventions": self.interventions[c],
                          "auto_trials": self.auto_trials[c]} for c in Complexity}

    def missing_reason(self) -> str | None:
        """Why the rates cannot make a baseline (a complexity without autonomous attempts), or None."""
        missing = [c.value for c in Complexity if self.rates[c] is None]
        return (f"no autonomous attempts in {' or '.join(missing)} complexity, so no intervention rate"
                if missing else None)


def intervention_rates(sequences: Iterable[Sequence]) -> InterventionRates:
    """Count interventions among autonomous attempts, per complexity (paper §5.1)."""
    interventions = {c: 0 for c in Complexity}
    auto_trials = {c: 0 for c in Complexity}
    for sequence in sequences:
        auto = sequence.robot_action == RobotAction.AUTO.code
        intervened = auto & (sequence.human_action == HumanAction.INTERVENE.code)
        for c in Complexity:
            in_c = sequence.complexity == c.code
            auto_trials[c] += int((auto & in_c).sum())
            interventions[c] += int((intervened & in_c).sum())
    rates = {c: interventions[c] / auto_trials[c] if auto_trials[c] else None for c in Complexity}
    return InterventionRates(rates, interventions, auto_trials)


@dataclass(frozen=True)
class AgnosticPolicy:
    """The complexity-only policy: expected rewards per complexity and the chosen action (ties -> ask).

    A policy given by explicit actions (``explicit``) has no rates and no
    expected reward of acting (None).
    """

    intervention_rate: Mapping[Complexity, float | None]
    expected_reward_auto: Mapping[Complexity, float | None]
    expected_reward_ask: dict[Complexity, float]
    action: dict[Complexity, RobotAction]

    @classmethod
    def explicit(cls, actions: Mapping[Complexity, RobotAction], task: TaskParams = TaskParams()) -> AgnosticPolicy:
        """A complexity-only policy with the actions given, not computed (e.g. a study's configured baseline)."""
        missing = [c.value for c in Complexity if c not in actions]
        if missing:
            raise ValueError(f"explicit trust-agnostic actions must name every complexity; "
                             f"missing {', '.join(missing)}")
        ask = expected_reward_given_action(Complexity.LOW, RobotAction.ASK, HumanAction.INTERVENE, task)
        return cls({c: None for c in Complexity}, {c: None for c in Complexity}, {c: ask for c in Complexity},
                   {c: RobotAction(actions[c]) for c in Complexity})

    def act(self, complexity: Complexity) -> RobotAction:
        return self.action[Complexity(complexity)]

    def to_dict(self) -> dict[str, Any]:
        """JSON of ``trustlab agnostic --json``."""

        def by_c(values: Mapping[Complexity, Any]) -> dict[str, Any]:
            return {c.value: values[c] for c in Complexity}

        return {"intervention_rate": by_c(self.intervention_rate),
                "expected_reward": {"auto": by_c(self.expected_reward_auto), "ask": by_c(self.expected_reward_ask)},
                "action": {c.value: self.action[c].value for c in Complexity}}


def trust_agnostic_policy(rates: Mapping[Complexity, float | None], task: TaskParams = TaskParams()) -> AgnosticPolicy:
    """The optimal complexity-only policy for intervention rates q_C = P(o = intervene | C, auto)."""
    q = {}
    for c in Complexity:
        rate = rates.get(c)
        if rate is None:
            raise ValueError(f"no intervention rate for {c} complexity (no autonomous trials there?); give one")
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"the intervention rate for {c} complexity must be in [0, 1], got {rate}")
        q[c] = float(rate)
    auto = {c: (1.0 - q[c]) * expected_reward_given_action(c, RobotAction.AUTO, HumanAction.RELY, task)
            + q[c] * expected_reward_given_action(c, RobotAction.AUTO, HumanAction.INTERVENE, task) for c in Complexity}
    ask = {c: expected_reward_given_action(c, RobotAction.ASK, HumanAction.INTERVENE, task) for c in Complexity}
    action = {c: RobotAction.AUTO if auto[c] > ask[c] else RobotAction.ASK for c in Complexity}
    return AgnosticPolicy(q, auto, ask, action)


def baseline_from_rates(rates: InterventionRates, task: TaskParams = TaskParams()) -> dict[str, Any]:
    """The baseline as a fitted model stores it: the rates with their counts, then the expected rewards
    and actions, or (when a complexity had no autonomous attempt) ``error`` saying so."""
    reason = rates.missing_reason()
    if reason is not None:
        return {"rates": rates.to_dict(), "expected_reward": None, "action": None, "error": reason}
    policy = trust_agnostic_policy(rates.rates, task).to_dict()
    return {"rates": rates.to_dict(), "expected_reward": policy["expected_reward"], "action": policy["action"],
            "error": None}
