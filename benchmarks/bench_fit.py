"""Benchmark of the IOHMM fit (SPEC §10: 33 × 71 trials, 20 restarts < 1 s; 1,000 × 200 < 30 s).

Run: ``python benchmarks/bench_fit.py [--quick]``. Data come from
``sample_random_assist_sequences(paper_params(), ...)`` with a fixed seed;
generating them is not timed. Prints wall time, loglik (and the loglik of the
true parameters), iterations and convergence for each size.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from experiment.fit import fit_iohmm, log_likelihood
from experiment.iohmm import paper_params
from experiment.sequences import sample_random_assist_sequences

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


def main() -> None:
    quick = "--quick" in sys.argv
    ok = [run(n, t, target, 1 if (quick or n > 100) else 5) for n, t, target in CASES]
    sys.exit(0 if all(ok) else 1)


if __name__ == "__main__":
    main()
