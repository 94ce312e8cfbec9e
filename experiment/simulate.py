"""Simulated participants, in process (SPEC §6): humans drawn from an IOHMM run through a study design.

Each simulated human (``experiment.participants.reliance.SimulatedHuman``) has a hidden trust state that starts
from the model's initial distribution, chooses rely/intervene with the model's emission probabilities and moves
with its transition probabilities after each trial. Given a rating emission (a model fitted with trust ratings,
``experiment.trust_ratings``), it also rates its trust after each shelf, from its state at the shelf's last trial,
drawn from a random stream of its own (the same seed gives the same trials with or without ratings). The robot
side is the real trial engine (``experiment.engine``), so the records are exactly those the platform stores.
Practice is not simulated (it is excluded from the score and the model data anyway).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from experiment import defaults
from experiment.analysis import TTestResult, ttest2
from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.iohmm import IOHMMParams
from experiment.participants.reliance import simulated_human
from experiment.records import TrialRecord
from experiment.schedule import assign_block_order, block_orders, derive_rng
from experiment.trust_ratings import RatingEmission
from experiment.trust_states_document import TrustModel


@dataclass(frozen=True)
class SimulatedParticipant:
    participant_id: str
    block_order: tuple[str, ...]
    records: list[TrialRecord]
    block_rewards: dict[str, float]  # cumulative reward per block name
    ratings: list[ShelfRating] = field(default_factory=list)  # with a rating emission: one per shelf


@dataclass(frozen=True)
class ShelfRating:
    """The trust rating a simulated participant gave after a shelf (the shelf questionnaire's trust item)."""

    block: int  # position in the participant's order, from 1
    block_name: str
    shelf: int
    value: int  # on the emission's scale
    questionnaire: str  # the study's shelf questionnaire

    def survey_row(self, participant_id: str) -> dict[str, Any]:
        """The row's known cells of ``surveys.csv`` (the others are empty)."""
        return {"participant_id": participant_id, "context": f"shelf:{self.block}:{self.shelf}",
                "block": self.block, "block_name": self.block_name, "shelf": self.shelf,
                "questionnaire": self.questionnaire, "item": defaults.RATING_ITEM, "value": self.value,
                "scored_value": self.value, "excluded": 0, "item_kind": "rating"}


@dataclass(frozen=True)
class StudySimulation:
    participants: list[SimulatedParticipant]

    def rewards(self, block_name: str) -> np.ndarray:
        """(n_participants,) cumulative reward in one block."""
        return np.array([p.block_rewards[block_name] for p in self.participants])

    def records(self) -> list[TrialRecord]:
        return [r for p in self.participants for r in p.records]

    def survey_rows(self) -> list[dict[str, Any]]:
        """The trust ratings as ``surveys.csv`` rows (known cells only)."""
        return [r.survey_row(p.participant_id) for p in self.participants for r in p.ratings]


def order_names(config: StudyConfig) -> list[tuple[str, ...]]:
    """The block orders participants are assigned to, as block names."""
    names = [b.name for b in config.blocks]
    if config.counterbalance == "none" or len(names) == 1:
        return [tuple(names)]
    return [tuple(names[i] for i in order) for order in block_orders(len(names), config.counterbalance)]


def simulate_participant(runtime: StudyRuntime, human_model: TrustModel, participant_id: str,
                         block_order: tuple[str, ...], human_rng: np.random.Generator,
                         ratings: RatingEmission | None = None,
                         rating_rng: np.random.Generator | None = None) -> SimulatedParticipant:
    human = simulated_human(human_model, human_rng)
    beliefs, score, records = runtime.initial_beliefs(), 0.0, []
    block_rewards = dict.fromkeys(block_order, 0.0)
    given: list[ShelfRating] = []
    questionnaire = runtime.config.shelf_questionnaire  # a study without one asks no ratings
    rating_pmf = None if ratings is None else ratings.pmf()
    if rating_pmf is not None and rating_pmf.shape[1] != human_model_states(human_model):
        raise ValueError(f"a rating emission of {rating_pmf.shape[1]} states for a model of "
                         f"{human_model_states(human_model)}")
    for trial in runtime.plan(participant_id, list(block_order)):
        policy_belief = runtime.policy_belief(beliefs, trial.block_name)
        robot_action = runtime.robot_action(participant_id, trial, policy_belief)
        record = runtime.record(participant_id, participant_id, trial, robot_action,
                                human.respond(trial.complexity, robot_action), belief_before=beliefs[""],
                                policy_belief=policy_belief, score_before=score)
        if questionnaire and ratings is not None and rating_pmf is not None and trial.shelf_end:
            rng = rating_rng if rating_rng is not None else human_rng
            level = int(rng.choice(ratings.levels + 1, p=rating_pmf[:, human.state_index]))
            given.append(ShelfRating(record.block, record.block_name, record.shelf, ratings.minimum + level,
                                     questionnaire))
        human.experience(record)
        beliefs, score = runtime.updated_beliefs(beliefs, record), record.score
        block_rewards[trial.block_name] += record.reward
        records.append(record)
    return SimulatedParticipant(participant_id, block_order, records, block_rewards, given)


def human_model_states(model: TrustModel) -> int:
    return 2 if isinstance(model, IOHMMParams) else model.n_states


def simulate_study(config: StudyConfig, human_model: TrustModel, n_participants: int, *, seed: int = 0,
                   runtime: StudyRuntime | None = None, id_prefix: str = "sim",
                   ratings: RatingEmission | None = None) -> StudySimulation:
    """Run ``n_participants`` simulated humans through ``config`` with counterbalanced block orders (rating their
    trust after each shelf when given a rating emission)."""
    runtime = runtime or StudyRuntime(config)
    orders = order_names(config)
    counts = dict.fromkeys(orders, 0)
    assign_rng = derive_rng(seed, id_prefix, "assignment")
    participants = []
    for i in range(n_participants):
        order = assign_block_order(orders, counts, assign_rng).order
        counts[order] += 1
        pid = f"{id_prefix}-{i + 1:04d}"
        participants.append(simulate_participant(runtime, human_model, pid, order, derive_rng(seed, pid, "human"),
                                                 ratings, derive_rng(seed, pid, "ratings")))
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
    differences: np.ndarray  # (replications,) mean reward of block_a minus that of block_b
    rewards: dict[str, np.ndarray]  # block name -> (replications, n_participants) cumulative rewards


def power_analysis(config: StudyConfig, human_model: TrustModel, n_participants: int, replications: int, *,
                   block_a: str, block_b: str, seed: int = 0, alpha: float = 0.05,
                   progress: Callable[[int, int], None] | None = None) -> PowerResult:
    """Run ``replications`` simulated studies; power = share where block_a beats block_b at p < alpha."""
    runtime = StudyRuntime(config)
    p_values, differences, effects, hits = [], [], [], 0
    rewards: dict[str, list[np.ndarray]] = {block_a: [], block_b: []}
    for r in range(replications):
        sim = simulate_study(config, human_model, n_participants, seed=seed, runtime=runtime, id_prefix=f"rep{r + 1}")
        a, b = sim.rewards(block_a), sim.rewards(block_b)
        rewards[block_a].append(a)
        rewards[block_b].append(b)
        p = _p_value(a, b)
        pooled = np.sqrt((a.var(ddof=1) + b.var(ddof=1)) / 2) if n_participants > 1 else np.nan
        p_values.append(p)
        differences.append(a.mean() - b.mean())
        effects.append((a.mean() - b.mean()) / pooled if pooled > 0 else np.nan)
        hits += bool(p < alpha and a.mean() > b.mean())
        if progress:
            progress(r + 1, replications)
    return PowerResult(n_participants, replications, alpha, hits / replications, float(np.mean(differences)),
                       float(np.nanmean(effects)) if not np.isnan(effects).all() else float("nan"), np.array(p_values),
                       np.array(differences), {name: np.array(values) for name, values in rewards.items()})


def _p_value(a: np.ndarray, b: np.ndarray) -> float:
    """ttest2's p, or NaN when it is undefined (no variation in either group); NaN never counts as a hit."""
    try:
        return ttest2(a, b).p
    except ValueError:
        return float("nan")


#: The power a study is conventionally planned for.
TARGET_POWER = 0.8


@dataclass(frozen=True)
class PowerSweep:
    results: list[PowerResult]  # one per number of participants, ascending
    target_power: float

    def participants_needed(self) -> int | None:
        """The smallest number of participants tried whose power reaches the target (None: none did)."""
        return next((r.n_participants for r in self.results if r.power >= self.target_power), None)


def power_sweep(config: StudyConfig, human_model: TrustModel, sizes: list[int], replications: int, *,
                block_a: str, block_b: str, seed: int = 0, alpha: float = 0.05, target_power: float = TARGET_POWER,
                progress: Callable[[int, int, int], None] | None = None) -> PowerSweep:
    """``power_analysis`` at each number of participants in ``sizes``; ``progress(n, done, replications)``."""
    if not sizes or min(sizes) < 2:
        raise ValueError("a power sweep needs participant numbers of at least 2 (a t-test needs variation)")
    results = []
    for n in sorted(set(sizes)):
        report = (lambda done, total, n=n: progress(n, done, total)) if progress else None
        results.append(power_analysis(config, human_model, n, replications, block_a=block_a, block_b=block_b,
                                      seed=seed, alpha=alpha, progress=report))
    return PowerSweep(results, target_power)


def reward_summary(values: np.ndarray) -> dict[str, float]:
    """The distribution of per-participant cumulative rewards (values: (n,))."""
    return {"mean": float(values.mean()), "median": float(np.median(values)),
            "sd": float(values.std(ddof=1)) if len(values) > 1 else float("nan"),
            "p5": float(np.percentile(values, 5)), "p95": float(np.percentile(values, 95)), "n": int(len(values))}


def sweep_document(sweep: PowerSweep, blocks: list[str]) -> dict[str, Any]:
    """A power sweep as JSON: per N the power, effect size, differences and each block's reward distribution."""
    rows = [{"participants": r.n_participants, "power": r.power, "effect_size": r.effect_size,
             "mean_difference": r.mean_difference,
             "difference_95": [float(np.percentile(r.differences, 2.5)), float(np.percentile(r.differences, 97.5))],
             "rewards": {b: reward_summary(r.rewards[b].ravel()) for b in blocks}} for r in sweep.results]
    return {"alpha": sweep.results[0].alpha, "compared": blocks, "sweep": rows, "target_power": sweep.target_power,
            "participants_needed": sweep.participants_needed()}


def paper_comparison(config: StudyConfig, result: PowerResult) -> dict[str, Any] | None:
    """The model's predicted trust-aware vs trust-agnostic difference next to what the paper measured (§5.2).

    Medians per block, as the paper reports them, and per trial, so that designs
    with other block lengths compare with the paper's 40-trial blocks. None
    unless the design compares a trust-aware with a trust-agnostic block.
    """
    kinds = {b.policy.kind: b for b in config.blocks}
    if set(kinds) != {"trust_aware", "trust_agnostic"}:
        return None
    aware, agnostic = kinds["trust_aware"], kinds["trust_agnostic"]
    predicted = {"trust_aware": float(np.median(result.rewards[aware.name])),
                 "trust_agnostic": float(np.median(result.rewards[agnostic.name]))}
    measured = {"trust_aware": defaults.PAPER_MEDIAN_SCORE_AWARE,
                "trust_agnostic": defaults.PAPER_MEDIAN_SCORE_AGNOSTIC}
    paper_trials = defaults.STUDY2_TRIALS_LOW_PER_BLOCK + defaults.STUDY2_TRIALS_HIGH_PER_BLOCK
    design_trials = aware.schedule.n_trials
    predicted_gain = (predicted["trust_aware"] - predicted["trust_agnostic"]) / design_trials
    measured_gain = (measured["trust_aware"] - measured["trust_agnostic"]) / paper_trials
    verdict = ("a much smaller difference than" if predicted_gain < measured_gain / 2 else
               "a difference of about the size" if predicted_gain <= 2 * measured_gain else "a larger difference than")
    message = (f"Model prediction: median cumulative reward {predicted['trust_aware']:.1f} (trust-aware) vs "
               f"{predicted['trust_agnostic']:.1f} (trust-agnostic) over {design_trials} trials per block, "
               f"{predicted_gain:+.3f} points per trial (mean difference {result.mean_difference:+.2f}, "
               f"d = {result.effect_size:.3f}, at N = {result.n_participants}); the paper measured medians "
               f"{measured['trust_aware']} vs {measured['trust_agnostic']} with people over {paper_trials} trials "
               f"({measured_gain:+.3f} per trial, p = {defaults.PAPER_SCORE_TTEST_P}). "
               f"The model predicts {verdict} the paper measured.")
    return {"predicted_median": predicted, "measured_median": measured, "design_trials_per_block": design_trials,
            "paper_trials_per_block": paper_trials, "predicted_gain_per_trial": predicted_gain,
            "measured_gain_per_trial": measured_gain, "message": message}
