"""How many trust states the data support (issue 40): cross-validation by participant, BIC and ICL.

Every candidate K is fitted on all participants (its log-likelihood, BIC and ICL) and, once per fold, on the
participants outside the fold (its held-out log-likelihood per trial on the fold's participants). Folds are of
whole participants, drawn from the seed, so a person's trials are never split between fitting and scoring.

A fold's fit starts from the all-participant estimate (restart 0) and a share of the random restarts
(``defaults.SELECTION_FOLD_RESTART_SHARE``): it still maximises the likelihood of the fold's own participants,
only the search is shorter.

The choice is a standard-error rule (``defaults.SELECTION_SE_RULE`` errors) on scores paired by participant: the
fewest states whose held-out score falls short of the best candidate's by at most that many standard errors of
the difference. An extra state has to earn its place by more than the fold-to-fold noise; information criteria
pick too many states when the model is misspecified (Pohle et al. 2017), so BIC and ICL are reported beside
the choice, not used for it.

With trust ratings (``experiment.trust_ratings``) the fits use the ratings as a second observation, but the
held-out score stays the log-likelihood of the held-out participants' reliance alone: the quantity the robot's
policy depends on, and the same with and without ratings, so ``compare_ratings`` can say whether the ratings
improve the model of reliance. (BIC and ICL with ratings include the ratings' likelihood and parameters.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from experiment import defaults
from experiment.fit import fit_iohmm
from experiment.iohmm import nest
from experiment.sequences import Sequence
from experiment.trust_ratings import Ratings
from experiment.trust_states_document import by_name, k_state_document, two_state_names
from experiment.trust_states_em import EMSettings, KStateFit, Layout, PaddedData, e_step, fit_k_states
from experiment.trust_states_uncertainty import k_state_uncertainty

#: what BIC's log(n) counts: the trials (each trial is one observation of reliance or one robot request)
BIC_SAMPLE_SIZE = "trials"

Progress = Callable[[str, int, int], None]  # (what is being fitted, fits done, fits in all); may raise to cancel


@dataclass(frozen=True)
class Candidate:
    """One number of trust states: its fit on everyone and its cross-validated score."""

    n_states: int
    fit: KStateFit = field(repr=False)
    fold_scores: tuple[float, ...]  # held-out log-likelihood per trial, one per fold
    participant_scores: tuple[float, ...]  # held-out log-likelihood of each participant (under their fold's fit)

    @property
    def loglik(self) -> float:
        return self.fit.loglik

    @property
    def bic(self) -> float:
        """−2 L + p log n, with n the number of trials (``BIC_SAMPLE_SIZE``)."""
        return -2.0 * self.fit.loglik + self.fit.n_free * math.log(self.fit.n_trials)

    @property
    def icl(self) -> float:
        """BIC + 2 × the entropy of the posterior over state paths: penalises states the data cannot tell apart."""
        return self.bic + 2.0 * self.fit.path_entropy

    @property
    def held_out(self) -> float:
        """Mean over folds of the held-out log-likelihood per trial (higher is better)."""
        return float(np.mean(self.fold_scores))

    @property
    def held_out_se(self) -> float:
        """Standard error of ``held_out`` across folds."""
        return float(np.std(self.fold_scores, ddof=1) / math.sqrt(len(self.fold_scores)))

    def to_dict(self) -> dict[str, Any]:
        return {"n_states": self.n_states, "loglik": self.loglik, "n_free": self.fit.n_free, "bic": self.bic,
                "icl": self.icl, "path_entropy": self.fit.path_entropy, "held_out_per_trial": self.held_out,
                "held_out_se": self.held_out_se, "fold_scores": list(self.fold_scores),
                "participant_scores": list(self.participant_scores),
                "converged": self.fit.converged, "iterations": self.fit.iterations}


@dataclass(frozen=True)
class Selection:
    candidates: tuple[Candidate, ...]
    chosen: int  # the chosen number of states
    reason: str
    folds: int
    seed: int
    fold_of: tuple[int, ...]  # the fold of each participant, in the order given
    n_participants: int
    n_trials: int
    se_rule: float
    restarts: int  # of each fit on everyone (a fold's: ``SELECTION_FOLD_RESTART_SHARE`` fewer)
    n_ratings: int | None = None  # trust ratings the fits used (None: fitted without ratings)

    def candidate(self, n_states: int) -> Candidate:
        return next(c for c in self.candidates if c.n_states == n_states)

    def to_dict(self) -> dict[str, Any]:
        """What the model document's provenance records of the choice."""
        return {"method": "cross-validation by participant, standard-error rule paired by participant",
                "chosen": self.chosen,
                "reason": self.reason, "folds": self.folds, "seed": self.seed, "se_rule": self.se_rule,
                "restarts": self.restarts,
                "n_participants": self.n_participants, "n_trials": self.n_trials,
                "bic_sample_size": BIC_SAMPLE_SIZE, "fold_of": list(self.fold_of),
                "with_ratings": self.n_ratings is not None, "n_ratings": self.n_ratings,
                "held_out_of": "the held-out participants' reliance (ratings not scored)",
                "candidates": [c.to_dict() for c in self.candidates]}


def assign_folds(n_participants: int, folds: int, seed: int) -> np.ndarray:
    """(n_participants,) fold of each participant: a seeded permutation dealt round-robin (sizes differ by ≤ 1)."""
    if folds < 2:
        raise ValueError(f"cross-validation needs at least 2 folds, got {folds}")
    if n_participants < folds:
        raise ValueError(f"{folds}-fold cross-validation needs at least {folds} participants, got {n_participants}")
    order = np.random.default_rng(seed).permutation(n_participants)
    fold_of = np.empty(n_participants, dtype=int)
    fold_of[order] = np.arange(n_participants) % folds
    return fold_of


def held_out_loglik(fit: KStateFit, data: PaddedData) -> np.ndarray:
    """(N,) log-likelihood of each held-out participant under a fit.

    An input the fitted participants never showed has no estimate: it is scored with a uniform transition row
    (no information about where trust goes). A P(rely) estimated at 0 or 1 is scored as
    ``defaults.SELECTION_PROBABILITY_FLOOR`` from the bound: one held-out person doing what the fitted ones never
    did costs that candidate a large finite amount, not the whole comparison.
    """
    layout = Layout(fit.n_states)
    theta = layout.pack(fit.params)
    floor = defaults.SELECTION_PROBABILITY_FLOOR
    theta[layout.p_rely] = np.clip(theta[layout.p_rely], floor, 1.0 - floor)
    return e_step(layout, theta[None], data).sequence_loglik[0]


def paired_gap(best: Candidate, other: Candidate, trials: int) -> tuple[float, float]:
    """How much better ``best`` scores than ``other`` per held-out trial, and the standard error of that.

    Paired by participant: every candidate scores every participant (under the fit of the folds without them),
    so what differs between people cancels and the standard error rests on all participants, not on a few folds.
    """
    gaps = np.subtract(best.participant_scores, other.participant_scores)
    return float(gaps.sum() / trials), float(gaps.std(ddof=1) * math.sqrt(len(gaps)) / trials)


def choose(candidates: Seq[Candidate], se_rule: float, trials: int) -> tuple[int, str]:
    """The standard-error rule on paired scores: the fewest states whose held-out score is below the best's
    by no more than ``se_rule`` standard errors of the difference. ``trials``: the held-out trials in all."""
    best = max(candidates, key=lambda c: c.held_out)
    gap = {c.n_states: paired_gap(best, c, trials) for c in candidates if c is not best}
    within = [c for c in candidates if c is best or gap[c.n_states][0] <= se_rule * gap[c.n_states][1]]
    chosen = min(within, key=lambda c: c.n_states)
    errors = f"{se_rule:g} standard error{'s' if se_rule != 1 else ''}"
    if chosen is best:
        reason = f"{chosen.n_states} states: the best held-out log-likelihood per trial ({chosen.held_out:.4f})"
        fewer = [c for c in candidates if c.n_states < chosen.n_states]
        if fewer:
            shown = ", ".join(f"{c.n_states} states by {gap[c.n_states][0]:.4f} ± {gap[c.n_states][1]:.4f}"
                              for c in fewer)
            reason += f"; it beats fewer states by more than {errors} of the difference ({shown})"
    else:
        difference, se = gap[chosen.n_states]
        reason = (f"{chosen.n_states} states: the fewest whose held-out log-likelihood per trial "
                  f"({chosen.held_out:.4f}) is within {errors} of the best, {best.n_states} states "
                  f"({best.held_out:.4f}; difference {difference:.4f} ± {se:.4f})")
    return chosen.n_states, reason


def select_states(sequences: list[Sequence], states: Seq[int], *, folds: int = defaults.SELECTION_FOLDS,
                  seed: int = 0, settings: EMSettings | None = None, se_rule: float = defaults.SELECTION_SE_RULE,
                  progress: Progress | None = None, ratings: Ratings | None = None) -> Selection:
    """Fit every K in ``states`` on everyone and in ``folds``-fold cross-validation; choose K (module docstring).

    ``sequences`` are one per participant (``ratings``, if given, theirs in the same order). Same arguments ⇒
    the same result.
    """
    ks, settings = sorted(set(states)), settings or EMSettings()
    if not ks:
        raise ValueError("no candidate numbers of states")
    if len(sequences) != len([s for s in sequences if len(s)]):
        raise ValueError("every participant needs at least one trial")
    data = PaddedData(sequences, ratings)
    reliance = data if ratings is None else PaddedData(sequences)  # what the held-out participants are scored on
    fold_of = assign_folds(len(sequences), folds, seed)
    total, done = len(ks) * (folds + 1), 0

    fold_settings = replace(settings, restarts=max(1, settings.restarts // defaults.SELECTION_FOLD_RESTART_SHARE),
                            keep=max(1, settings.keep // defaults.SELECTION_FOLD_RESTART_SHARE))

    def fitted(label: str, part: PaddedData, k: int, init: KStateFit | None = None) -> KStateFit:
        nonlocal done
        if progress is not None:
            progress(label, done, total)
        # the same report after every EM iteration too, so that a caller can cancel within a fit
        result = fit_k_states(part, k, seed=seed, settings=settings if init is None else fold_settings,
                              init=None if init is None else init.params,
                              init_ratings=None if init is None else init.ratings,
                              progress=None if progress is None else lambda _i, _n: progress(label, done, total))
        done += 1
        return result

    candidates = []
    for k in ks:
        full = fitted(f"K = {k}, all participants", data, k)
        scores, by_participant = [], np.empty(len(sequences))
        for f in range(folds):
            train, test = np.flatnonzero(fold_of != f), np.flatnonzero(fold_of == f)
            fold_fit = fitted(f"K = {k}, fold {f + 1} of {folds}", data.subset(train), k, full)
            held_out = reliance.subset(test)
            by_participant[test] = held_out_loglik(fold_fit, held_out)
            scores.append(float(by_participant[test].sum()) / held_out.n_trials)
        candidates.append(Candidate(k, full, tuple(scores), tuple(by_participant.tolist())))
    if progress is not None:
        progress("done", total, total)
    if len(candidates) == 1:
        chosen, reason = ks[0], f"{ks[0]} states: the only candidate"
    else:
        chosen, reason = choose(candidates, se_rule, data.n_trials)
    return Selection(tuple(candidates), chosen, reason, folds, seed, tuple(int(f) for f in fold_of),
                     data.n_sequences, data.n_trials, se_rule, settings.restarts,
                     None if ratings is None else data.n_ratings)


@dataclass(frozen=True)
class RatingsComparison:
    """The same number of states fitted with and without the trust ratings, scored on held-out reliance."""

    n_states: int
    with_ratings: Candidate = field(repr=False)
    without_ratings: Candidate = field(repr=False)
    n_trials: int
    n_ratings: int
    se_rule: float

    @property
    def difference(self) -> tuple[float, float]:
        """Held-out reliance log-likelihood per trial, with minus without ratings, and its paired standard error."""
        gap, se = paired_gap(self.with_ratings, self.without_ratings, self.n_trials)
        return gap, se

    @property
    def verdict(self) -> str:
        gap, se = self.difference
        shown = f"{gap:+.4f} ± {se:.4f} per held-out trial"
        errors = f"{self.se_rule:g} standard errors"
        if gap > self.se_rule * se:
            return f"the ratings improve the model of reliance ({shown}, beyond {errors})"
        if gap < -self.se_rule * se:
            return f"the ratings make the model of reliance worse ({shown}, beyond {errors})"
        return f"the ratings make no difference to the model of reliance beyond {errors} ({shown})"

    def to_dict(self) -> dict[str, Any]:
        gap, se = self.difference
        return {"n_states": self.n_states, "n_ratings": self.n_ratings, "scored": "held-out reliance only",
                "held_out_with_ratings": self.with_ratings.held_out,
                "held_out_without_ratings": self.without_ratings.held_out,
                "difference_per_trial": gap, "difference_se": se, "verdict": self.verdict,
                "participant_scores_with": list(self.with_ratings.participant_scores),
                "participant_scores_without": list(self.without_ratings.participant_scores)}


def compare_ratings(with_ratings: Selection, without_ratings: Selection, n_states: int) -> RatingsComparison:
    """``n_states`` from a selection with ratings and one without, on the same participants, folds and seed."""
    if with_ratings.n_ratings is None or without_ratings.n_ratings is not None:
        raise ValueError("compare a selection with ratings to one without")
    if (with_ratings.fold_of, with_ratings.seed) != (without_ratings.fold_of, without_ratings.seed):
        raise ValueError("the two selections must use the same folds")
    return RatingsComparison(n_states, with_ratings.candidate(n_states), without_ratings.candidate(n_states),
                             with_ratings.n_trials, with_ratings.n_ratings, with_ratings.se_rule)


@dataclass(frozen=True)
class RatedFit:
    """A fit with trust ratings: its model JSON, the selection among the numbers of states (with ratings) and the
    chosen number's comparison with the fit without ratings."""

    document: dict[str, Any]
    selection: Selection
    comparison: RatingsComparison


def fit_with_ratings(sequences: list[Sequence], ratings: Ratings, states: Seq[int], *, restarts: int, seed: int,
                     folds: int, fitted_on: dict[str, Any], progress: Progress | None = None) -> RatedFit:
    """Choose among ``states`` with the ratings (one number: cross-validated all the same, for the comparison),
    compare the chosen number with and without ratings on held-out reliance, and write the model with ratings.
    ``progress(label, done, total)`` over both selections; it may raise to cancel."""
    if not ratings.count:
        raise ValueError("no trust rating of a shelf with scored trials: nothing to fit the ratings to")
    settings = EMSettings(restarts=restarts)
    ks = sorted(set(states))
    total = (len(ks) + 1) * (folds + 1)

    def part(offset: int, what: str) -> Progress | None:
        if progress is None:
            return None
        report = progress
        return lambda label, done, _total: report(f"{what} {label}", offset + done, total)

    rated = select_states(sequences, ks, folds=folds, seed=seed, settings=settings, ratings=ratings,
                          progress=part(0, "with ratings:"))
    plain = select_states(sequences, [rated.chosen], folds=folds, seed=seed, settings=settings,
                          progress=part(len(ks) * (folds + 1), "without ratings:"))
    comparison = compare_ratings(rated, plain, rated.chosen)
    document = model_document(sequences, rated.chosen, restarts=restarts, seed=seed, selection=rated,
                              ratings=ratings, comparison=comparison, fitted_on=fitted_on)
    if len(rated.candidates) == 1:  # one number asked for: nothing was chosen (the comparison keeps the scores)
        del document["selection"]
    return RatedFit(document, rated, comparison)


def model_document(sequences: list[Sequence], n_states: int, *, restarts: int, seed: int,
                   fitted_on: dict[str, Any], selection: Selection | None = None,
                   progress: Callable[[int, int], None] | None = None, ratings: Ratings | None = None,
                   comparison: RatingsComparison | None = None) -> dict[str, Any]:
    """The model JSON of an ``n_states`` fit with Laplace standard errors and statuses, and the selection that
    chose it (if any) in ``"selection"``.

    Two states without ratings: today's fit (``fit.fit_iohmm``: EM and the polish), so that K = 2 is exactly the
    paper's model. Otherwise the K-state EM (the selection's fit on everyone when it ran with the same restarts,
    seed and ratings); with ratings, the rating emission in ``"ratings"`` and the comparison with the fit
    without them in ``"ratings_comparison"``.
    """
    extra = {} if selection is None else {"selection": selection.to_dict()}
    if comparison is not None:
        extra["ratings_comparison"] = comparison.to_dict()
    if n_states == 2 and ratings is None:
        result = fit_iohmm(sequences, restarts=restarts, seed=seed, progress=progress)
        return {**result.to_document(fitted_on=fitted_on), **extra}
    data = PaddedData(sequences, ratings)
    settings = EMSettings(restarts=restarts)
    reused = (selection is not None and (selection.seed, selection.restarts) == (seed, restarts)
              and (selection.n_ratings is None) == (ratings is None)
              and n_states in {c.n_states for c in selection.candidates})
    fit = (selection.candidate(n_states).fit if reused and selection is not None
           else fit_k_states(data, n_states, seed=seed, settings=settings, progress=progress))
    uncertainty = k_state_uncertainty(fit.params, data, fit.ratings)
    if fit.ratings is not None:
        extra["ratings"] = {**fit.ratings.to_document(), "n_ratings": fit.n_ratings}
    stderr = {name: None if math.isnan(value) else float(value) for name, value in by_name(*uncertainty.stderr).items()}
    status = {name: str(value) for name, value in by_name(*uncertainty.status).items()}
    if n_states == 2:
        stderr, status = two_state_names(stderr), two_state_names(status)
    return k_state_document(fit.params, loglik=fit.loglik, stderr=nest(stderr), status=nest(status),
                            fit={"restarts": len(fit.restart_logliks), "seed": seed, "iterations": fit.iterations,
                                 "converged": fit.converged, "n_sequences": fit.n_sequences,
                                 "n_trials": fit.n_trials, "n_free": fit.n_free,
                                 "stderr_method": uncertainty.method},
                            fitted_on=fitted_on, **extra)
