"""Robot policies (paper §3–§5) behind one small protocol.

A policy maps the trial's complexity and the current belief (P(trust high)
under a two-state model, the vector over the states under a K-state one:
``experiment.trust_belief``) to a robot action; randomness comes in as an ``np.random.Generator``. Policies
that need a belief say which model computes it (``belief_model``), so the
engine that runs them (simulation or server) keeps that belief per
participant.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol, runtime_checkable

import numpy as np

from experiment import defaults
from experiment.agnostic import AgnosticPolicy
from experiment.belief_mdp import BeliefMDPSolution
from experiment.iohmm import BeliefUpdate
from experiment.task import Complexity, RobotAction
from experiment.trust_belief import Belief, scalar_belief
from experiment.trust_states_document import TrustModel
from experiment.trust_states_policy import KPolicySolution


class PolicyKind(StrEnum):
    """What chose a trial's robot action (``Trial.policy``): its block's policy, or the practice list."""

    PRACTICE = "practice"  # the practice trials' scripted actions (config practice.trials)
    TRUST_AWARE = "trust_aware"
    TRUST_AGNOSTIC = "trust_agnostic"
    RANDOM_ASSIST = "random_assist"
    ALWAYS_AUTO = "always_auto"
    ALWAYS_ASK = "always_ask"


@runtime_checkable
class Policy(Protocol):
    @property
    def kind(self) -> PolicyKind: ...

    def act(self, complexity: Complexity, belief: Belief, rng: np.random.Generator) -> RobotAction: ...


@dataclass(frozen=True)
class RandomAssist:
    """Ask with probability p_ask[C] (study 1, §4)."""

    p_ask_low: float = defaults.STUDY1_P_ASK_LOW
    p_ask_high: float = defaults.STUDY1_P_ASK_HIGH
    kind: PolicyKind = PolicyKind.RANDOM_ASSIST

    def act(self, complexity: Complexity, belief: Belief, rng: np.random.Generator) -> RobotAction:
        p_ask = self.p_ask_high if complexity == Complexity.HIGH else self.p_ask_low
        return RobotAction.ASK if rng.random() < p_ask else RobotAction.AUTO


@dataclass(frozen=True)
class Constant:
    """``always_auto`` / ``always_ask`` baselines (also used in practice)."""

    action: RobotAction
    kind: PolicyKind = PolicyKind.ALWAYS_AUTO

    def act(self, complexity: Complexity, belief: Belief, rng: np.random.Generator) -> RobotAction:
        return self.action


def always_auto() -> Constant:
    return Constant(RobotAction.AUTO, PolicyKind.ALWAYS_AUTO)


def always_ask() -> Constant:
    return Constant(RobotAction.ASK, PolicyKind.ALWAYS_ASK)


@dataclass(frozen=True)
class TrustAgnostic:
    """The optimal complexity-only policy (§5.1): one action per complexity."""

    baseline: AgnosticPolicy
    kind: PolicyKind = PolicyKind.TRUST_AGNOSTIC

    def act(self, complexity: Complexity, belief: Belief, rng: np.random.Generator) -> RobotAction:
        return self.baseline.action[complexity]


@dataclass(frozen=True)
class TrustAware:
    """Acts by the belief-MDP solution on the belief kept with ``belief_model`` (§5.1): the paper's two-state
    solution (``belief_mdp``) or, for a model of K ≥ 3 states, the one on the belief simplex
    (``trust_states_policy``)."""

    solution: BeliefMDPSolution | KPolicySolution
    belief_model: TrustModel = field(repr=False)
    belief_update: BeliefUpdate = "bayes"
    kind: PolicyKind = PolicyKind.TRUST_AWARE

    def act(self, complexity: Complexity, belief: Belief, rng: np.random.Generator) -> RobotAction:
        if isinstance(self.solution, KPolicySolution):
            return self.solution.action(np.asarray(belief, dtype=float), complexity)
        return self.solution.action(scalar_belief(belief), complexity)
