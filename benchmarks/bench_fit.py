"""Benchmark of the IOHMM fit (SPEC §10: 33 × 71 trials, 20 restarts < 1 s; 1,000 × 200 < 30 s).

Run: ``python benchmarks/bench_fit.py [--quick]``. Data come from
``sample_random_assist_sequences(paper_params(), ...)`` with a fixed seed;
generating them is not timed. Prints wall time, loglik (and the loglik of the
true parameters), iterations and convergence for each size.

``--select [SEEDS]`` instead times the choice of the number of trust states (issue 40: K = 2…4, 5-fold
cross-validation by participant on 300 × 71 trials, target < 2 min) on data of the paper's two-state model and of
``trust_states.illustrative_three_state_model``, then counts how often each number is chosen over SEEDS
(default 10) smaller studies (150 × 60) of each.

``--ratings [STUDIES]`` fits simulated studies (30 and 100 participants × 71 trials, a trust rating every 8
trials) of the paper's model and of the three-state one, each with an informative rating emission, with and
without the ratings (the true number of states, 5 folds), and prints how often the ratings improved the held-out
reliance (the 2-SE verdict) and the RMSE of the estimated transition and reliance probabilities against the
truth, with and without (default 5 studies each).

``--recover [REPLICATIONS]`` runs the parameter recovery of the paper's model in the model-estimation design
(33 and 100 participants, default 100 replications each) and prints its coverage table.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from experiment.fit import fit_iohmm, log_likelihood
from experiment.iohmm import paper_params
from experiment.model_selection import fit_with_ratings, select_states
from experiment.recovery import recover
from experiment.sequences import Sequence, sample_random_assist_sequences
from experiment.templates import template
from experiment.trust_ratings import RatingEmission, sample_ratings
from experiment.trust_states import (
    KStateParams,
    from_iohmm,
    illustrative_three_state_model,
    sample_sequences_k,
)

from results_log import append_result

CASES = [(33, 71, 1.0), (1000, 200, 30.0)]


def run(n_sequences: int, n_trials: int, target: float, repeats: int) -> bool:
    sequences, _ = sample_random_assist_sequences(paper_params(), n_sequences, n_trials, np.random.default_rng(2024))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fit_iohmm(sequences, restarts=20, seed=0)
        times.append(time.perf_counter() - start)
    best = min(times)
    flagged = {s: result.status.count(s) for s in ("estimated", "boundary", "unidentified", "not_exercised")}
    print(f"{n_sequences:>5} x {n_trials:<4} 20 restarts: {best:7.3f} s (best of {repeats}; target < {target:g} s) "
          f"{'OK' if best < target else 'MISSED'}\n"
          f"    loglik {result.loglik:.4f} (true params {log_likelihood(paper_params(), sequences):.4f}), "
          f"iterations {result.iterations}, converged {result.converged}, statuses {flagged}")
    append_result("bench_fit.py", {"sequences": n_sequences, "trials": n_trials, "restarts": 20, "repeats": repeats},
                  {"best_s": best, "target_s": target, "loglik": result.loglik, "iterations": result.iterations,
                   "converged": result.converged, "statuses": flagged})
    return best < target


SELECTION_TARGET_S = 120.0


def study(truth: int, n_sequences: int, n_trials: int, seed: int) -> list[Sequence]:
    rng = np.random.default_rng(seed)
    if truth == 2:
        return sample_random_assist_sequences(paper_params(), n_sequences, n_trials, rng)[0]
    return sample_sequences_k(illustrative_three_state_model(), n_sequences, n_trials, rng)[0]


def select(seeds: int) -> bool:
    ok = True
    for truth in (2, 3):
        sequences = study(truth, 300, 71, 2024)
        start = time.perf_counter()
        selection = select_states(sequences, [2, 3, 4], folds=5, seed=0)
        seconds = time.perf_counter() - start
        ok &= seconds < SELECTION_TARGET_S
        print(f"{truth}-state data, 300 x 71, K = 2…4, 5 folds: {seconds:6.1f} s (target < {SELECTION_TARGET_S:g} s) "
              f"{'OK' if seconds < SELECTION_TARGET_S else 'MISSED'}; chosen {selection.chosen}")
        for c in selection.candidates:
            print(f"    K = {c.n_states}: loglik {c.loglik:10.2f}  BIC {c.bic:9.1f}  ICL {c.icl:9.1f}  "
                  f"held-out/trial {c.held_out:.5f} ± {c.held_out_se:.5f}  converged {c.fit.converged}")
        append_result("bench_fit.py", {"mode": "select", "truth_states": truth, "sequences": 300, "trials": 71,
                                       "candidates": [2, 3, 4], "folds": 5},
                      {"seconds": seconds, "target_s": SELECTION_TARGET_S, "chosen": selection.chosen,
                       "held_out": {c.n_states: c.held_out for c in selection.candidates}})
    for truth in (2, 3):
        chosen = [select_states(study(truth, 150, 60, 5000 + s), [2, 3, 4], folds=5, seed=s).chosen
                  for s in range(seeds)]
        counts = {k: chosen.count(k) for k in (2, 3, 4)}
        print(f"{truth}-state data, 150 x 60, {seeds} studies: chosen {counts}")
        append_result("bench_fit.py", {"mode": "select-rate", "truth_states": truth, "sequences": 150, "trials": 60,
                                       "studies": seeds}, {"chosen": counts})
    return ok


#: Informative rating emissions: states that rate 2.5 and 7.5 (two states) or 2, 5 and 8 (three) of 10 on average,
#: with a concentration of 10 (a rating's SD ≈ 1.9 points).
RATED_TRUTHS = {2: RatingEmission(np.array([2.5, 7.5]), np.array([7.5, 2.5])),
                3: RatingEmission(np.array([2.0, 5.0, 8.0]), np.array([8.0, 5.0, 2.0]))}


def _rmse(fitted: KStateParams, truth: KStateParams) -> float:
    """RMSE over the transition rows and reliance probabilities both models have (NaN rows: not exercised)."""
    a = np.concatenate([fitted.transition.ravel(), fitted.p_rely.ravel()])
    b = np.concatenate([truth.transition.ravel(), truth.p_rely.ravel()])
    keep = ~np.isnan(a)
    return float(np.sqrt(np.mean((a[keep] - b[keep]) ** 2)))


def ratings(studies: int) -> None:
    for truth_k, emission in RATED_TRUTHS.items():
        truth = from_iohmm(paper_params()) if truth_k == 2 else illustrative_three_state_model()
        for participants in (30, 100):
            verdicts, gaps, with_rmse, without_rmse, seconds = [], [], [], [], 0.0
            for s in range(studies):
                rng = np.random.default_rng(7000 + s)
                if truth_k == 2:
                    sequences, states = sample_random_assist_sequences(paper_params(), participants, 71, rng)
                else:
                    sequences, states = sample_sequences_k(truth, participants, 71, rng)
                rated = sample_ratings(emission, states, 8, rng)
                start = time.perf_counter()
                fitted = fit_with_ratings(sequences, rated, [truth_k], restarts=20, seed=s, folds=5, fitted_on={})
                seconds += time.perf_counter() - start
                c = fitted.comparison
                gap, se = c.difference
                gaps.append(gap)
                verdicts.append("better" if gap > 2 * se else "worse" if gap < -2 * se else "no difference")
                with_rmse.append(_rmse(c.with_ratings.fit.params, truth))
                without_rmse.append(_rmse(c.without_ratings.fit.params, truth))
            counts = {v: verdicts.count(v) for v in ("better", "no difference", "worse")}
            print(f"{truth_k}-state truth, {participants} x 71, {studies} studies ({seconds / studies:.0f} s each): "
                  f"ratings {counts}; held-out gain {np.mean(gaps):+.4f} per trial; RMSE of the estimates with "
                  f"ratings {np.mean(with_rmse):.3f}, without {np.mean(without_rmse):.3f}")
            append_result("bench_fit.py", {"mode": "ratings", "truth_states": truth_k, "participants": participants,
                                           "trials": 71, "rating_every": 8, "studies": studies, "folds": 5},
                          {"verdicts": counts, "mean_gain_per_trial": float(np.mean(gaps)),
                           "rmse_with": float(np.mean(with_rmse)), "rmse_without": float(np.mean(without_rmse)),
                           "seconds_per_study": seconds / studies})


def recovery(replications: int) -> None:
    for participants in (33, 100):
        start = time.perf_counter()
        result = recover(template("model-estimation"), paper_params(), participants, replications, seed=0)
        print(f"Parameter recovery, paper model, model-estimation design ({time.perf_counter() - start:.0f} s):")
        print("\n".join(result.lines()))
        append_result("bench_fit.py", {"mode": "recover", "participants": participants, "replications": replications,
                                       "design": "model-estimation"},
                      {"coverage": {p.name: p.coverage for p in result.parameters},
                       "rmse": {p.name: p.rmse for p in result.parameters},
                       "verdict": {p.name: p.verdict for p in result.parameters}})


def main() -> None:
    if "--ratings" in sys.argv:
        at = sys.argv.index("--ratings") + 1
        ratings(int(sys.argv[at]) if at < len(sys.argv) else 5)
        return
    if "--recover" in sys.argv:
        at = sys.argv.index("--recover") + 1
        recovery(int(sys.argv[at]) if at < len(sys.argv) else 100)
        return
    if "--select" in sys.argv:
        at = sys.argv.index("--select") + 1
        sys.exit(0 if select(int(sys.argv[at]) if at < len(sys.argv) else 10) else 1)
    quick = "--quick" in sys.argv
    ok = [run(n, t, target, 1 if (quick or n > 100) else 5) for n, t, target in CASES]
    sys.exit(0 if all(ok) else 1)


if __name__ == "__main__":
    main()
