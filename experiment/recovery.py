"""Can this design recover this model? Simulate studies from a fitted model, refit, compare (issue 40).

Each replication runs the study's design with simulated participants who follow the model (as
``experiment.simulate``), fits a model of the same number of trust states to their trials (``fit.fit_iohmm`` for
two, ``trust_states_em`` for more; Laplace standard errors) and compares every parameter's estimate with the
truth:

- **bias** and **RMSE** over the replications in which the data exercised the parameter;
- **coverage**: the share of replications with a Laplace interval (status ``estimated``) whose 95 % interval,
  estimate ± 1.96 SE, holds the truth. The approximation is valid where coverage is near 95 %
  (``defaults.RECOVERY_COVERAGE_RANGE``);
- **verdict** (``verdict``): ``recovered`` (a Laplace interval in most studies, coverage in range), ``intervals
  off`` (intervals in most studies, coverage outside the range), ``at a bound`` (the estimate mostly sits at 0 or
  1: no interval; the RMSE says how close it comes) or ``not identified`` (mostly not exercised or in a flat
  direction of the likelihood). "Most" is ``defaults.RECOVERY_IDENTIFIED_SHARE``.

The true model's states are the fitted model's (high = relies more in high complexity), so labels agree.

With a rating emission (a model fitted with trust ratings), the simulated participants also rate their trust
after each shelf and every refit uses the ratings (``experiment.trust_ratings``; the intervals are then
conditional on the rating emission); each state's mean rating is reported with its bias and RMSE.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import norm

from experiment import defaults
from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.fit import fit_iohmm
from experiment.iohmm import PARAMETER_NAMES, IOHMMParams
from experiment.records import TrialRecord
from experiment.sequences import Sequence
from experiment.simulate import SimulatedParticipant, simulate_study
from experiment.trust_ratings import RatingEmission, Ratings, ratings_at_shelf_ends
from experiment.trust_states import order_states
from experiment.trust_states_document import TrustModel, by_name, two_state_names
from experiment.trust_states_em import EMSettings, PaddedData, fit_k_states
from experiment.trust_states_uncertainty import k_state_uncertainty

Z_95 = float(norm.ppf(0.975))  # the two-sided 95 % normal quantile


def sequence_of(records: list[TrialRecord]) -> Sequence:
    """A participant's non-practice trials, in order, as a model sequence."""
    scored = [r for r in records if not r.practice]
    return Sequence(*(np.array([getattr(r, name).code for r in scored], dtype=np.int8)
                      for name in ("complexity", "robot_action", "human_action", "experience")))


@dataclass(frozen=True)
class ParameterRecovery:
    name: str
    true: float
    n_exercised: int  # replications whose data exercised it
    n_estimated: int  # … of which it had a Laplace interval
    n_boundary: int
    n_unidentified: int
    bias: float  # mean(estimate − truth) over the exercised replications (NaN if none)
    rmse: float
    coverage: float  # share of the estimated replications whose 95 % interval holds the truth (NaN if none)
    mean_stderr: float  # mean Laplace SE over the estimated replications
    verdict: str  # "recovered" | "intervals off" | "at a bound" | "not identified" (``verdict``)

    @property
    def identified(self) -> bool:
        return self.verdict in ("recovered", "intervals off")

    def to_dict(self) -> dict[str, Any]:
        return {**{k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in self.__dict__.items()},
                "identified": self.identified}


@dataclass(frozen=True)
class RatingRecovery:
    """A state's mean trust rating: the truth and how the refits estimated it."""

    state: int
    true: float
    bias: float
    rmse: float


@dataclass(frozen=True)
class Recovery:
    participants: int
    replications: int
    seed: int
    parameters: tuple[ParameterRecovery, ...]
    ratings: tuple[RatingRecovery, ...] = ()  # with a rating emission: each state's mean rating

    def not_identified(self) -> list[str]:
        """Parameters this design gives no Laplace interval in most studies (at a bound, flat or unexercised)."""
        return [p.name for p in self.parameters if not p.identified]

    def lines(self) -> list[str]:
        """The result as a table of text lines, with what it means in words."""
        low, high = defaults.RECOVERY_COVERAGE_RANGE
        out = [f"{self.replications} simulated studies of {self.participants} participants, seed {self.seed}, each "
               f"refitted (Laplace 95 % intervals: trusted where their coverage is {low:.0%}–{high:.0%})",
               f"  {'parameter':<45} {'true':>6} {'bias':>7} {'RMSE':>6} {'coverage':>8} {'intervals':>9}  verdict"]
        for p in self.parameters:
            coverage = "–" if math.isnan(p.coverage) else f"{p.coverage:.0%}"
            out.append(f"  {p.name:<45} {p.true:6.3f} {p.bias:+7.3f} {p.rmse:6.3f} {coverage:>8} "
                       f"{p.n_estimated:>4}/{self.replications:<4}  {p.verdict}")
        identified = [p for p in self.parameters if p.identified]
        if identified:
            widest = max(identified, key=lambda p: p.rmse)
            out.append(f"  With {self.participants} participants every parameter with intervals is recovered to "
                       f"± {widest.rmse:.2f} (RMSE) or better; the widest is {widest.name}.")
        if self.not_identified():
            out.append("  No interval in most studies (at a bound, flat or not exercised): "
                       + ", ".join(self.not_identified()))
        if self.ratings:
            out.append("  Fitted with the simulated trust ratings (intervals conditional on the rating emission); "
                       "each state's mean rating:")
            out += [f"    state {r.state}: true {r.true:5.2f}, bias {r.bias:+.2f}, RMSE {r.rmse:.2f}"
                    for r in self.ratings]
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"participants": self.participants, "replications": self.replications, "seed": self.seed,
                "coverage_range": list(defaults.RECOVERY_COVERAGE_RANGE),
                "identified_share": defaults.RECOVERY_IDENTIFIED_SHARE,
                "parameters": [p.to_dict() for p in self.parameters], "not_identified": self.not_identified(),
                "ratings": [r.__dict__ for r in self.ratings]}


def summarise(name: str, true: float, estimates: np.ndarray, stderrs: np.ndarray, statuses: list[str],
              replications: int) -> ParameterRecovery:
    """One parameter's figures from its estimate, SE and status in each replication."""
    exercised = np.array([s != "not_exercised" for s in statuses])
    estimated = np.array([s == "estimated" for s in statuses])
    errors = estimates[exercised] - true
    covered = np.abs(estimates[estimated] - true) <= Z_95 * stderrs[estimated]
    n_boundary, n_unidentified = statuses.count("boundary"), statuses.count("unidentified")
    coverage = float(covered.mean()) if covered.size else math.nan
    return ParameterRecovery(
        name, true, int(exercised.sum()), int(estimated.sum()), n_boundary, n_unidentified,
        float(errors.mean()) if errors.size else math.nan,
        float(np.sqrt((errors ** 2).mean())) if errors.size else math.nan, coverage,
        float(stderrs[estimated].mean()) if estimated.any() else math.nan,
        verdict(int(estimated.sum()), n_boundary, coverage, replications))


def verdict(n_estimated: int, n_boundary: int, coverage: float, replications: int) -> str:
    """What the design does for one parameter (module docstring)."""
    most = defaults.RECOVERY_IDENTIFIED_SHARE * replications
    low, high = defaults.RECOVERY_COVERAGE_RANGE
    if n_estimated >= most:
        return "recovered" if low <= coverage <= high else "intervals off"
    return "at a bound" if n_boundary >= most else "not identified"


def recover(config: StudyConfig, truth: TrustModel, participants: int, replications: int, *, seed: int = 0,
            restarts: int = defaults.STATES_RESTARTS, progress: Callable[[int, int], None] | None = None,
            ratings: RatingEmission | None = None) -> Recovery:
    """Simulate ``replications`` studies of ``participants`` from ``truth`` under ``config``, refit each, compare.

    A model of K ≥ 3 states is refitted with K states (``trust_states_em``, Laplace intervals from
    ``trust_states_uncertainty``); with ``ratings`` (the truth's rating emission) every refit uses the simulated
    ratings, with the K-state EM at any K. Same arguments ⇒ the same result. ``progress(done, replications)``
    after each refit (it may raise to cancel).
    """
    if participants < 1 or replications < 2:
        raise ValueError("a recovery run needs at least 1 participant and 2 replications")
    if ratings is not None and not config.shelf_questionnaire:
        raise ValueError("this design asks no shelf questionnaire: its participants give no trust ratings")
    runtime = StudyRuntime(config)
    if isinstance(truth, IOHMMParams):
        names, true = list(PARAMETER_NAMES), truth.to_vector()
    else:
        truth = order_states(truth)  # the refit's labels
        flat = by_name(truth.initial, truth.transition, truth.p_rely)
        names, true = list(flat), np.array(list(flat.values()), dtype=float)
    estimates, stderrs, statuses, rating_means = [], [], [], []
    for r in range(replications):
        sim = simulate_study(config, truth, participants, seed=seed, runtime=runtime, id_prefix=f"recover{r + 1}",
                             ratings=ratings)
        sequences = [sequence_of(p.records) for p in sim.participants]
        rated = None if ratings is None else _ratings_of(sim.participants, ratings)
        estimate, stderr, status, means = _refit(truth, sequences, restarts, seed + r, rated)
        estimates.append(estimate)
        stderrs.append(stderr)
        statuses.append(status)
        rating_means.append(means)
        if progress is not None:
            progress(r + 1, replications)
    est, se = np.array(estimates), np.array(stderrs)
    parameters = tuple(
        summarise(name, float(true[i]), est[:, i], se[:, i], [s[i] for s in statuses], replications)
        for i, name in enumerate(names) if not math.isnan(true[i]))
    recovered_ratings: tuple[RatingRecovery, ...] = ()
    if ratings is not None:
        errors = np.array(rating_means) - ratings.mean_rating()
        recovered_ratings = tuple(RatingRecovery(j, float(ratings.mean_rating()[j]), float(errors[:, j].mean()),
                                                 float(np.sqrt((errors[:, j] ** 2).mean())))
                                  for j in range(errors.shape[1]))
    return Recovery(participants, replications, seed, parameters, recovered_ratings)


def _ratings_of(participants: list[SimulatedParticipant], emission: RatingEmission) -> Ratings:
    """The simulated ratings placed at the last scored trial of their shelf, as a fit reads them."""
    shelves = {p.participant_id: [(r.block, r.shelf) for r in p.records if not r.practice] for p in participants}
    rows = [{"participant_id": p.participant_id, "context": f"shelf:{r.block}:{r.shelf}", "item": defaults.RATING_ITEM,
             "value": str(r.value)} for p in participants for r in p.ratings]
    return ratings_at_shelf_ends([p.participant_id for p in participants], shelves, rows,
                                 minimum=emission.minimum, maximum=emission.maximum)


def _refit(truth: TrustModel, sequences: list[Sequence], restarts: int, seed: int,
           ratings: Ratings | None = None) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """Estimates, standard errors and statuses of a refit, in the order of the truth's parameters, and the
    refit's mean rating per state (empty without ratings)."""
    if isinstance(truth, IOHMMParams) and ratings is None:
        fit = fit_iohmm(sequences, restarts=restarts, seed=seed)
        return fit.params.to_vector(), fit.stderr, list(fit.status), np.empty(0)
    k = 2 if isinstance(truth, IOHMMParams) else truth.n_states
    data = PaddedData(sequences, ratings)
    k_fit = fit_k_states(data, k, seed=seed, settings=EMSettings(restarts=restarts))
    uncertainty = k_state_uncertainty(k_fit.params, data, k_fit.ratings)
    values = by_name(k_fit.params.initial, k_fit.params.transition, k_fit.params.p_rely)
    stderr = by_name(*uncertainty.stderr)
    status = {name: str(v) for name, v in by_name(*uncertainty.status).items()}
    if k == 2 and isinstance(truth, IOHMMParams):  # under the paper's names, in the truth's order
        values, stderr, status = two_state_names(values), two_state_names(stderr), two_state_names(status)
    means = np.empty(0) if k_fit.ratings is None else k_fit.ratings.mean_rating()
    return (np.array(list(values.values()), dtype=float), np.array(list(stderr.values()), dtype=float),
            list(status.values()), means)
