"""Simulated participants, in process (SPEC §6): humans drawn from an IOHMM run through a study design.

Each simulated human has a hidden trust state that starts from the model's
initial distribution, chooses rely/intervene with the model's emission
probabilities and moves with its transition probabilities after each trial.
The robot side is the real trial engine (``experiment.engine``), so the
records are exactly those the platform stores. Practice is not simulated
(it is excluded from the score and the model data anyway).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from experiment.analysis import TTestResult, ttest2
from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.iohmm import IOHMMParams
from experiment.records import TrialRecord
from experiment.schedule import assign_block_order, block_orders, derive_rng
from experiment.task import Complexity, Experience, HumanAction, RobotAction, Trust


@dataclass(frozen=True)
class SimulatedParticipant:
    participant_id: str
    block_order: tuple[str, ...]
    records: list[TrialRecord]
    block_rewards: dict[str, float]  # cumulative reward per block name


@dataclass(frozen=True)
class StudySimulation:
    participants: list[SimulatedParticipant]

    def rewards(self, block_name: str) -> np.ndarray:
        """(n_participants,) cumulative reward in one block."""
        return np.array([p.block_rewards[block_name] for p in self.participants])

    def records(self) -> list[TrialRecord]:
        return [r for p in self.participants for r in p.records]


class SimulatedHuman:
    """A participant whose behaviour follows an IOHMM."""

    def __init__(self, model: IOHMMParams, rng: np.random.Generator):
        self.model, self.rng = model, rng
        self.trust = Trust.HIGH if rng.random() < model.initial_high else Trust.LOW

    def respond(self, complexity: Complexity, robot_action: RobotAction) -> HumanAction:
        p_intervene = self.model.p_intervene(complexity, robot_action)[self.trust.code]
        return HumanAction.INTERVENE if self.rng.random() < p_intervene else HumanAction.RELY

    def experience(self, record: TrialRecord) -> None:
        self.update(record.complexity, record.robot_action, record.experience)

    def update(self, complexity: Complexity, robot_action: RobotAction, experience: Experience) -> None:
        """Move the hidden trust after a trial with the model's transition probabilities."""
        p_high = self.model.p_high_after(complexity, robot_action, experience)[self.trust.code]
        self.trust = Trust.HIGH if self.rng.random() < p_high else Trust.LOW


def order_names(config: StudyConfig) -> list[tuple[str, ...]]:
    """The block orders participants are assigned to, as block names."""
    names = [b.name for b in config.blocks]
    if config.counterbalance == "none" or len(names) == 1:
        return [tuple(names)]
    return [tuple(names[i] for i in order) for order in block_orders(len(names), config.counterbalance)]


def simulate_participant(runtime: StudyRuntime, human_model: IOHMMParams, participant_id: str,
                         block_order: tuple[str, ...], human_rng: np.random.Generator) -> SimulatedParticipant:
    human = SimulatedHuman(human_model, human_rng)
    beliefs, score, records = runtime.initial_beliefs(), 0.0, []
    block_rewards = dict.fromkeys(block_order, 0.0)
    for trial in runtime.plan(participant_id, list(block_order)):
        policy_belief = runtime.policy_belief(beliefs, trial.block_name)
        robot_action = runtime.robot_action(participant_id, trial, policy_belief)
        record = runtime.record(participant_id, participant_id, trial, robot_action,
                                human.respond(trial.complexity, robot_action), belief_before=beliefs[""],
                                policy_belief=policy_belief, score_before=score)
        human.experience(record)
        beliefs, score = runtime.updated_beliefs(beliefs, record), record.score
        block_rewards[trial.block_name] += record.reward
        records.append(record)
    return SimulatedParticipant(participant_id, block_order, records, block_rewards)


def simulate_study(config: StudyConfig, human_model: IOHMMParams, n_participants: int, *, seed: int = 0,
                   runtime: StudyRuntime | None = None, id_prefix: str = "sim") -> StudySimulation:
    """Run ``n_participants`` simulated humans through ``config`` with counterbalanced block orders."""
    runtime = runtime or StudyRuntime(config)
    orders = order_names(config)
    counts = dict.fromkeys(orders, 0)
    assign_rng = derive_rng(seed, id_prefix, "assignment")
    participants = []
    for i in range(n_participants):
        order = assign_block_order(orders, counts, assign_rng).order
        counts[order] += 1
        pid = f"{id_prefix}-{i + 1:04d}"
        participants.append(simulate_participant(runtime, human_model, pid, order, derive_rng(seed, pid, "human")))
    return StudySimulation(participants)


@dataclass(frozen=True)
class PolicyComparison:
    block_a: str
    block_b: str
    test: TTestResult


def compare_blocks(sim: StudySimulation, block_a: str, block_b: str) -> PolicyComparison:
    """``ttest2`` of the cumulative rewards of two blocks (the paper's test, §5.2)."""
    return PolicyComparison(block_a, block_b, ttest2(sim.rewards(block_a), sim.rewards(block_b)))


@dataclass(frozen=True)
class PowerResult:
    n_participants: int
    replications: int
    alpha: float
    power: float  # fraction of replications with p < alpha and the difference in the expected direction
    mean_difference: float
    effect_size: float  # mean Cohen's d over replications
    p_values: np.ndarray


def power_analysis(config: StudyConfig, human_model: IOHMMParams, n_participants: int, replications: int, *,
                   block_a: str, block_b: str, seed: int = 0, alpha: float = 0.05,
                   progress: Callable[[int, int], None] | None = None) -> PowerResult:
    """Run ``replications`` simulated studies; power = share where block_a beats block_b at p < alpha."""
    runtime = StudyRuntime(config)
    p_values, differences, effects, hits = [], [], [], 0
    for r in range(replications):
        sim = simulate_study(config, human_model, n_participants, seed=seed, runtime=runtime, id_prefix=f"rep{r + 1}")
        a, b = sim.rewards(block_a), sim.rewards(block_b)
        p = _p_value(a, b)
        pooled = np.sqrt((a.var(ddof=1) + b.var(ddof=1)) / 2) if n_participants > 1 else np.nan
        p_values.append(p)
        differences.append(a.mean() - b.mean())
        effects.append((a.mean() - b.mean()) / pooled if pooled > 0 else np.nan)
        hits += bool(p < alpha and a.mean() > b.mean())
        if progress:
            progress(r + 1, replications)
    return PowerResult(n_participants, replications, alpha, hits / replications, float(np.mean(differences)),
                       float(np.nanmean(effects)) if not np.isnan(effects).all() else float("nan"), np.array(p_values))


def _p_value(a: np.ndarray, b: np.ndarray) -> float:
    """ttest2's p, or NaN when it is undefined (no variation in either group); NaN never counts as a hit."""
    try:
        return ttest2(a, b).p
    except ValueError:
        return float("nan")
