"""The trial engine shared by the simulator and the server.

``StudyRuntime`` compiles a ``StudyConfig`` once (models resolved, policies
solved) and then answers, for any participant and trial, the questions a
session asks: which complexity, which robot action, did the autonomous
attempt succeed, and what the trial's record is. Every random draw comes
from a stream derived from (study seed, participant key, block, trial,
purpose), so a participant's session is reproducible from the stored trials
alone and no RNG state needs to be persisted.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from math import comb

import numpy as np

from experiment.agnostic import trust_agnostic_policy
from experiment.belief_mdp import BeliefMDPSolution, solve_belief_mdp
from experiment.config import (
    AlwaysAskSpec,
    AlwaysAutoSpec,
    BlockConfig,
    RandomAssistSpec,
    StudyConfig,
    TrustAgnosticSpec,
    TrustAwareSpec,
    resolve_trust_model,
)
from experiment.duration import DurationEstimate, estimate_duration
from experiment.flow import Step, progress_at, step_fractions
from experiment.iohmm import BeliefUpdate, IOHMMParams
from experiment.policies import Policy, RandomAssist, TrustAgnostic, TrustAware, always_ask, always_auto
from experiment.provenance import TrialProvenance, study_provenance
from experiment.records import TrialRecord
from experiment.schedule import complexity_schedule, derive_rng, shelves
from experiment.task import Complexity, HumanAction, RobotAction, TaskParams, resolve_trial
from experiment.trust_belief import Belief, initial_belief, next_belief, p_highest
from experiment.trust_states import KStateParams
from experiment.trust_states_document import TrustModel
from experiment.trust_states_policy import KPolicySolution, solve_k_state_policy

#: Block orders whose steps a runtime keeps listed (a study has as many orders as its counterbalancing makes: a few).
STEP_ORDERS_KEPT = 256


@dataclass(frozen=True)
class PlannedTrial:
    """Where a trial sits in a participant's session, and its complexity."""

    block: int  # position in the participant's block order, from 1
    block_name: str
    trial: int  # within block, from 1
    trial_overall: int  # across blocks, from 1
    shelf: int  # within block, from 1
    shelf_end: bool  # the last trial of its shelf: a shelf survey follows
    complexity: Complexity


def schedule_p_high(block: BlockConfig) -> float:
    """The probability of high complexity a block's schedule implies."""
    return block.schedule.p_high


def build_policy(block: BlockConfig, config: StudyConfig) -> Policy:
    """The policy object of a block (the trust-aware one is solved here; solutions are cached)."""
    spec = block.policy
    if isinstance(spec, RandomAssistSpec):
        return RandomAssist(spec.p_ask_low, spec.p_ask_high)
    if isinstance(spec, AlwaysAutoSpec):
        return always_auto()
    if isinstance(spec, AlwaysAskSpec):
        return always_ask()
    if isinstance(spec, TrustAgnosticSpec):
        return TrustAgnostic(_agnostic(spec, config.task))
    assert isinstance(spec, TrustAwareSpec)
    model = resolve_trust_model(spec.model)
    p_high = spec.p_high if spec.p_high is not None else schedule_p_high(block)
    if isinstance(model, KStateParams):
        solution: BeliefMDPSolution | KPolicySolution = _solve_k(
            model.n_states, _model_bytes(model), config.task, p_high, simplex_resolution(model.n_states, spec.grid),
            spec.discount, spec.belief_update)
    else:
        solution = _solve(model.to_vector().tobytes(), config.task, p_high, spec.grid, spec.discount,
                          spec.belief_update)
    return TrustAware(solution, model, spec.belief_update)


def simplex_resolution(n_states: int, grid: int) -> int:
    """The finest step 1/n of the belief simplex of ``n_states`` states with at most ``grid`` points (C(n + K − 1,
    K − 1)); at K = 2 that is n = grid − 1, the two-state solver's grid. The config's ``grid`` is a budget of
    points, so that a study of more states solves in about the same time, not in C(grid + K − 2, K − 1) points."""
    n = 1
    while comb(n + 1 + n_states - 1, n_states - 1) <= grid:
        n += 1
    return n


def _model_bytes(model: TrustModel) -> bytes:
    """The model's numbers as a cache key (two models with equal bytes and K are the same model)."""
    if isinstance(model, IOHMMParams):
        return model.to_vector().tobytes()
    return b"".join(np.ascontiguousarray(a).tobytes() for a in (model.initial, model.transition, model.p_rely))


def _agnostic(spec: TrustAgnosticSpec, task: TaskParams):
    if spec.actions is not None:
        from experiment.agnostic import AgnosticPolicy  # explicit actions: nothing to compute
        return AgnosticPolicy.explicit(spec.actions, task)
    return trust_agnostic_policy({Complexity.LOW: spec.intervention_rate_low,
                                  Complexity.HIGH: spec.intervention_rate_high}, task)


@lru_cache(maxsize=32)
def _solve(model_bytes: bytes, task: TaskParams, p_high: float, grid: int, discount: float,
           belief_update: BeliefUpdate):
    params = IOHMMParams.from_vector(np.frombuffer(model_bytes, dtype=float))
    return solve_belief_mdp(params, task, p_high=p_high, grid=grid, discount=discount, belief_update=belief_update)


@lru_cache(maxsize=32)
def _solve_k(n_states: int, model_bytes: bytes, task: TaskParams, p_high: float, resolution: int, discount: float,
             belief_update: BeliefUpdate) -> KPolicySolution:
    k = n_states
    numbers = np.frombuffer(model_bytes, dtype=float)
    params = KStateParams(numbers[:k], numbers[k:k + 8 * k * k].reshape(2, 2, 2, k, k), numbers[k + 8 * k * k:])
    return solve_k_state_policy(params, task, p_high=p_high, resolution=resolution, discount=discount,
                                belief_update=belief_update)


class StudyRuntime:
    """A compiled study configuration."""

    def __init__(self, config: StudyConfig):
        self.config = config
        self.model = resolve_trust_model(config.model)
        self.policies = {block.name: build_policy(block, config) for block in config.blocks}
        #: What every trial row records: model and policy hashes and the seed (``experiment.provenance``).
        self.block_provenance, self.practice_provenance = study_provenance(config)
        self._step_fractions: dict[tuple[str, ...] | None, dict[Step, float]] = {}  # by block order

    @cached_property
    def duration(self) -> DurationEstimate:
        """How long the study takes (``experiment.duration``), computed once: every consent page shows it."""
        return estimate_duration(self.config)

    def progress(self, step: Step, block_order: list[str] | None) -> float:
        """``experiment.flow.progress``, each block order's steps listed once (every state the page reads has it)."""
        key = tuple(block_order) if block_order else None
        fractions = self._step_fractions.get(key)
        if fractions is None:
            if len(self._step_fractions) >= STEP_ORDERS_KEPT:
                self._step_fractions.clear()
            fractions = self._step_fractions[key] = step_fractions(self.config, block_order)
        return progress_at(fractions, step)

    def provenance(self, block_name: str, practice: bool = False) -> TrialProvenance:
        return self.practice_provenance if practice else self.block_provenance[block_name]

    def plan(self, participant_key: str, block_order: list[str]) -> list[PlannedTrial]:
        """Every non-practice trial of a participant, in order."""
        planned, overall = [], 0
        for position, name in enumerate(block_order, start=1):
            block = self.config.block(name)
            rng = derive_rng(self.config.seed, participant_key, name, "complexity")
            complexities = complexity_schedule(block.schedule, rng)
            shelf_of = shelves(len(complexities), self.config.shelf_size)
            for i, complexity in enumerate(complexities):
                overall += 1
                last = i + 1 == len(complexities) or shelf_of[i + 1] != shelf_of[i]
                planned.append(PlannedTrial(position, name, i + 1, overall, shelf_of[i], last, complexity))
        return planned

    def initial_beliefs(self) -> dict[str, Belief]:
        """The beliefs before the first trial: under the study's model (key ``""``), and under the own model of
        every trust-aware block whose model or update differs from it. A belief is P(trust high) under a two-state
        model and the vector over the states under a K-state one (``experiment.trust_belief``)."""
        beliefs = {"": initial_belief(self.model)}
        for name, policy in self.policies.items():
            if self._own_belief(name):
                assert isinstance(policy, TrustAware)
                beliefs[name] = initial_belief(policy.belief_model)
        return beliefs

    def policy_belief(self, beliefs: dict[str, Belief], block_name: str) -> Belief:
        """The belief the block's policy acts on."""
        return beliefs.get(block_name, beliefs[""])

    def updated_beliefs(self, beliefs: dict[str, Belief], record: TrialRecord) -> dict[str, Belief]:
        """Every kept belief after a trial (trust carries over between blocks)."""
        # A two-state study belief is the record's own number; a K-state one is the vector the record has no room for.
        out: dict[str, Belief] = {"": record.belief_after if isinstance(self.model, IOHMMParams) else next_belief(
            self.model, beliefs[""], record.complexity, record.robot_action, record.human_action, record.experience,
            self.config.belief_update)}
        for name in beliefs.keys() - {""}:
            policy = self.policies[name]
            assert isinstance(policy, TrustAware)
            out[name] = next_belief(policy.belief_model, beliefs[name], record.complexity, record.robot_action,
                                    record.human_action, record.experience, policy.belief_update)
        return out

    def belief_of_trial(self, recorded: float, kept: Belief) -> Belief:
        """The study belief before a trial the server resolves: the trial row's number under a two-state model (as
        it always was), the participant's kept vector under a K-state one (the row holds only ``p_highest``; the
        kept belief changes only when a trial completes, so it is still the one the trial started with)."""
        return recorded if isinstance(self.model, IOHMMParams) else kept

    def _own_belief(self, block_name: str) -> bool:
        policy = self.policies[block_name]
        return isinstance(policy, TrustAware) and not (
            policy.belief_update == self.config.belief_update
            and type(policy.belief_model) is type(self.model)
            and _model_bytes(policy.belief_model) == _model_bytes(self.model))

    def robot_action(self, participant_key: str, trial: PlannedTrial, policy_belief: Belief) -> RobotAction:
        rng = derive_rng(self.config.seed, participant_key, trial.block_name, trial.trial, "policy")
        return self.policies[trial.block_name].act(trial.complexity, policy_belief, rng)

    def autonomous_success(self, participant_key: str, trial: PlannedTrial) -> bool:
        """The trial's outcome draw; the server never reveals it before the attempt happens."""
        rng = derive_rng(self.config.seed, participant_key, trial.block_name, trial.trial, "outcome")
        return bool(rng.random() < self.config.task.p_success(trial.complexity))

    def record(self, participant_id: str, participant_key: str, trial: PlannedTrial, robot_action: RobotAction,
               human_action: HumanAction, *, belief_before: Belief, policy_belief: Belief, score_before: float,
               practice: bool = False) -> TrialRecord:
        """Resolve a trial and build its record; the belief after uses the study's model. The record's beliefs are
        numbers: ``p_highest`` of a K-state belief (P(trust high) itself under a two-state model)."""
        success = self.autonomous_success(participant_key, trial)
        result = resolve_trial(trial.complexity, robot_action, human_action, success, self.config.task)
        belief_after = next_belief(self.model, belief_before, trial.complexity, robot_action, human_action,
                                   result.experience, self.config.belief_update)
        provenance = self.provenance(trial.block_name, practice)
        return TrialRecord(
            participant_id=participant_id, block=trial.block, trial=trial.trial, complexity=trial.complexity,
            robot_action=robot_action, human_action=human_action, outcome=result.outcome,
            experience=result.experience, practice=practice, block_name=trial.block_name,
            policy=self.policies[trial.block_name].kind, trial_overall=trial.trial_overall, shelf=trial.shelf,
            reward=result.reward, score=score_before + result.reward, belief_before=p_highest(belief_before),
            belief_after=p_highest(belief_after), policy_belief=p_highest(policy_belief),
            model_hash=provenance.model_hash, policy_hash=provenance.policy_hash, seed=provenance.seed,
        )
