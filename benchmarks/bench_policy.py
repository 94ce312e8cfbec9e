"""Belief-MDP solve time and the policy thresholds (SPEC §10: 1,001-point grid in < 0.5 s).

Run: ``python benchmarks/bench_policy.py [--repeats N]``. Prints the solve
time (the transition matrix is built and value iteration run on every call),
the number of value-iteration sweeps, and the high-complexity threshold for
each belief update and each study's p_high with the paper's parameters.
"""

from __future__ import annotations

import argparse
import statistics
import time

from experiment import defaults
from experiment.belief_mdp import myopic_threshold, solve_belief_mdp
from experiment.iohmm import paper_params
from experiment.task import Complexity

from results_log import append_result

TARGET_SECONDS = 0.5
P_HIGH = {"study 1 (30/71)": defaults.STUDY1_TRIALS_HIGH / (defaults.STUDY1_TRIALS_LOW + defaults.STUDY1_TRIALS_HIGH),
          "study 2 (0.5)": 0.5}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--grid", type=int, default=1001)
    args = parser.parse_args()
    params = paper_params()

    print(f"belief-MDP solve, grid {args.grid}, discount {defaults.DISCOUNT}, {args.repeats} repeats per case")
    print(f"{'belief update':<14}{'p_high':<18}{'median s':>9}{'max s':>8}{'sweeps':>8}{'threshold low':>15}"
          f"{'threshold high':>16}")
    worst, figures = 0.0, {}
    for method in ("bayes", "paper"):
        for label, p_high in P_HIGH.items():
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                solution = solve_belief_mdp(params, p_high=p_high, grid=args.grid, belief_update=method)
                times.append(time.perf_counter() - start)
            worst = max(worst, max(times))
            low = solution.thresholds[Complexity.LOW]
            low_text = f"never ({solution.constant_action[Complexity.LOW]})" if low is None else f"{low:.4f}"
            print(f"{method:<14}{label:<18}{statistics.median(times):>9.3f}{max(times):>8.3f}{solution.iterations:>8}"
                  f"{low_text:>15}{solution.thresholds[Complexity.HIGH]:>16.4f}")
            figures[f"{method}, {label}"] = {"median_s": statistics.median(times), "max_s": max(times),
                                             "sweeps": solution.iterations, "threshold_low": low,
                                             "threshold_high": solution.thresholds[Complexity.HIGH]}
    print(f"myopic threshold (high): {myopic_threshold(params, complexity=Complexity.HIGH):.4f}; "
          f"paper prints {defaults.PAPER_TRUST_AWARE_THRESHOLD_HIGH}")
    verdict = "PASS" if worst < TARGET_SECONDS else "FAIL"
    print(f"slowest solve {worst:.3f} s vs target {TARGET_SECONDS} s: {verdict}")
    append_result("bench_policy.py", {"grid": args.grid, "repeats": args.repeats, "discount": defaults.DISCOUNT},
                  {"slowest_s": worst, "target_s": TARGET_SECONDS, "cases": figures})


if __name__ == "__main__":
    main()
