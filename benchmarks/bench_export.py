"""Streaming export of ``trials.csv`` (SPEC §10: 1,000 participants × 80 trials in < 10 s, flat memory).

Run: ``python benchmarks/bench_export.py [--participants N] [--keep DIR]``. Builds a
temporary SQLite database (migrated with ``server.db.migrate.upgrade``) holding a
policy-evaluation study (2 blocks × 40 trials) with N completed participants,
bulk-inserted with realistic rows (the participant's plan, consistent
actions/outcomes/experiences/rewards, running scores, beliefs, timings), plus a
second study with N/4 participants. Then it streams ``trials.csv`` of the big
study through ``server.export.iter_csv`` and prints rows, bytes,
seconds, the growth of the process's peak RSS while streaming, the time of
the whole zip (``iter_zip``), and the
``tracemalloc`` peak of streaming each study: memory is flat when the peak for
N participants is no larger than for N/4 (4× fewer rows).
"""

from __future__ import annotations

import argparse
import gc
import hashlib
import resource
import sys
import tempfile
import time
import tracemalloc
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import cast

import numpy as np
from sqlalchemy import Table, insert, select

from experiment.engine import StudyRuntime
from experiment.flow import DEBRIEF
from experiment.task import Complexity, HumanAction, Outcome, RobotAction, resolve_trial
from experiment.templates import policy_evaluation
from server import export
from server.db.engine import make_engine, make_sessionmaker
from server.db.migrate import upgrade
from server.models import Participant, StudyVersion, Trial
from server.services.studies import create_study, current_version

from results_log import append_result

TARGET_SECONDS = 10.0
START = datetime(2026, 3, 1, 9, 0, tzinfo=UTC)


def populate(factory, slug: str, participants: int, seed: int) -> int:
    """Create study ``slug`` and bulk-insert ``participants`` completed participants; returns trial rows."""
    config = policy_evaluation()
    runtime = StudyRuntime(config)
    with factory.begin() as session:
        study = create_study(session, config, slug, status="open")
        version = current_version(session, study)
        study_id, version_id = study.id, version.id
        session.execute(select(StudyVersion).where(StudyVersion.id == version_id)).scalar_one().frozen_at = START
    rng = np.random.default_rng(seed)
    orders = [[b.name for b in config.blocks], [b.name for b in reversed(config.blocks)]]
    total, batch = 0, 100
    for first in range(0, participants, batch):
        people, trials = [], []
        for index in range(first, min(first + batch, participants)):
            public_id = f"P{study_id:03d}{index:09d}"
            order = orders[index % 2]
            joined = START + timedelta(minutes=index)
            people.append({
                "public_id": public_id, "token_hash": hashlib.sha256(public_id.encode()).hexdigest(),
                "study_id": study_id, "study_version_id": version_id, "external_id": f"prolific-{index:06d}",
                "recruitment": {"PROLIFIC_PID": f"prolific-{index:06d}", "STUDY_ID": "bench"},
                "status": "completed", "step": DEBRIEF, "block_order": order,
                "assignment": {"method": "balanced"}, "beliefs": {}, "completion_code": "C0DE",
                "excluded": index % 50 == 0, "exclusion_reason": "attention check" if index % 50 == 0 else None,
                "created_at": joined, "consented_at": joined + timedelta(seconds=30),
                "started_at": joined + timedelta(minutes=2), "finished_at": joined + timedelta(minutes=25),
                "last_seen_at": joined + timedelta(minutes=25)})
            score, belief = 0.0, 0.6
            rows = _trials(runtime, rng, public_id, order, joined)
            for row in rows:
                row.update(study_version_id=version_id)
                score += row["reward"]
                row["score"] = score
                row["belief_before"] = belief
                belief = float(np.clip(belief + rng.normal(0, 0.05), 0.01, 0.99))
                row["belief_after"] = belief
                row["policy_belief"] = row["belief_before"] if row["policy"] == "trust_aware" else None
            trials.append((public_id, rows, score))
        with factory.begin() as session:  # Core executemany: the bulk path, no ORM objects
            connection = session.connection()
            connection.execute(insert(cast(Table, Participant.__table__)), [
                dict(p, score=s, compensation=round(5 + max(s, 0) * 0.05, 2))
                for p, (_, _, s) in zip(people, trials, strict=True)])
            ids = dict(connection.execute(select(Participant.public_id, Participant.id)
                                          .where(Participant.public_id.in_([p["public_id"] for p in people]))).all())
            flat = [dict(row, participant_id=ids[pid]) for pid, rows, _ in trials for row in rows]
            connection.execute(insert(cast(Table, Trial.__table__)), flat)
            total += len(flat)
    return total


def _trials(runtime: StudyRuntime, rng: np.random.Generator, key: str, order: list[str],
            joined: datetime) -> list[dict]:
    rows = []
    at = joined + timedelta(minutes=2)
    for planned in runtime.plan(key, order):
        policy = runtime.policies[planned.block_name].kind
        ask = rng.random() < (0.1 if planned.complexity == Complexity.LOW else 0.4)
        robot = RobotAction.ASK if ask else RobotAction.AUTO
        human = HumanAction.INTERVENE if ask or rng.random() < 0.3 else HumanAction.RELY
        success = rng.random() < runtime.config.task.p_success(planned.complexity)
        result = resolve_trial(planned.complexity, robot, human, success, runtime.config.task)
        teleop = human == HumanAction.INTERVENE
        decided = None if ask else at + timedelta(seconds=3)
        rows.append({
            "practice": False, "block": planned.block, "block_name": planned.block_name, "policy": policy,
            "trial": planned.trial,
            "trial_overall": planned.trial_overall, "shelf": planned.shelf, "complexity": planned.complexity.value,
            "robot_action": robot.value, "stage": "done", "human_action": human.value, "outcome": result.outcome.value,
            "experience": result.experience.value, "reward": result.reward,
            "decision_time_ms": float(rng.uniform(300, 2900)) if teleop and not ask else None,
            "teleop_time_ms": float(rng.uniform(4000, 20000)) if teleop else None,
            "teleop_success": bool(rng.random() < 0.95) if teleop else None,
            "failure_mode": (("collision" if rng.random() < 0.5 else "drop")
                             if result.outcome == Outcome.FAILURE else None),
            "started_at": at, "decided_at": decided, "completed_at": at + timedelta(seconds=12)})
        at += timedelta(seconds=15)
    return rows


def stream(factory, slug: str) -> tuple[int, int, float]:
    with factory() as session:
        target = export.export_target(session, slug)
    counter = export.RowCounter()
    size = 0
    start = time.perf_counter()
    for chunk in export.iter_csv(factory, target, "trials.csv", counter=counter):
        size += len(chunk)
    return counter.rows, size, time.perf_counter() - start


def rss_kib() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() // 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=1000)
    parser.add_argument("--keep", type=Path, help="keep the database in this directory")
    args = parser.parse_args()
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
        sys.exit(run(args, args.keep))
    with tempfile.TemporaryDirectory(prefix="trustlab-bench-export-") as directory:
        code = run(args, Path(directory))
    sys.exit(code)


def run(args: argparse.Namespace, directory: Path) -> int:
    url = f"sqlite:///{directory / 'bench.db'}"
    upgrade(url)
    engine = make_engine(url)
    factory = make_sessionmaker(engine)
    start = time.perf_counter()
    small = max(1, args.participants // 4)
    n_big = populate(factory, "bench", args.participants, seed=1)
    n_small = populate(factory, "bench-small", small, seed=2)
    print(f"setup: {args.participants} + {small} participants, {n_big} + {n_small} trial rows inserted "
          f"in {time.perf_counter() - start:.1f} s ({directory / 'bench.db'})")

    gc.collect()
    peak_before, rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, rss_kib()
    rows, size, seconds = stream(factory, "bench")
    peak_after, rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, rss_kib()
    print(f"trials.csv: {rows} rows, {size / 1e6:.1f} MB in {seconds:.2f} s ({rows / seconds:,.0f} rows/s)")
    print(f"RSS: {rss_before / 1024:.1f} MiB before, {rss_after / 1024:.1f} MiB after; "
          f"peak RSS growth while streaming {(peak_after - peak_before) / 1024:.1f} MiB")

    with factory() as session:
        target = export.export_target(session, "bench")
    start, size = time.perf_counter(), 0
    for chunk in export.iter_zip(factory, target):
        size += len(chunk)
    print(f"export.zip (all files + manifest): {size / 1e6:.1f} MB in {time.perf_counter() - start:.2f} s")

    peaks = {}
    for slug, n in (("bench-small", small), ("bench", args.participants)):
        gc.collect()
        tracemalloc.start()
        stream(factory, slug)
        peaks[slug] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        print(f"tracemalloc peak while streaming {slug} ({n} participants): {peaks[slug] / 2**20:.2f} MiB")
    ratio = peaks["bench"] / peaks["bench-small"]
    print(f"peak ratio (4x rows / 1x rows): {ratio:.2f} (flat memory: about 1)")
    ok = rows == n_big and seconds < TARGET_SECONDS and ratio < 1.5
    print(f"{'PASS' if ok else 'FAIL'}: {rows} rows in {seconds:.2f} s (target < {TARGET_SECONDS:.0f} s), "
          f"memory {'flat' if ratio < 1.5 else 'grows'}")
    append_result("bench_export.py", {"participants": args.participants, "trials_per_participant": 80},
                  {"rows": rows, "seconds": seconds, "target_s": TARGET_SECONDS, "zip_bytes": size,
                   "tracemalloc_peak_mib": {slug: peak / 2**20 for slug, peak in peaks.items()},
                   "peak_ratio": ratio, "passed": ok})
    engine.dispose()
    return 0 if ok else 1


if __name__ == "__main__":
    main()
