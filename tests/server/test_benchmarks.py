"""The load benchmarks stay runnable at HEAD: ``bench_scenes`` end to end, and one ``bench_load`` case (a real
``trustlab serve``, a bot process, every bot's 3D view open) on a study small enough for a few seconds.

What they measure is not checked here (the machine running the tests is not a quiet one), only that they run
against the current server, that their 3D clients receive the moving robot, and that every decision window was
opened by a 3D report of the scene (the bots' protocol for ``POST trials/shown``).
"""

from __future__ import annotations

import math
import re
import sqlite3
import subprocess
import sys

import pytest

from benchmarks import bench_load, bench_scenes, cpuquota
from server.harness.viewer_client import motion_stats
from tests.server.factories import tiny_study

#: Far below the 30 Hz the view is sent at, far above a view that does not follow the robot.
SOME_UPDATES_PER_S = 5.0


def test_bench_scenes_runs_and_its_viewers_see_every_robot_frame():
    result = bench_scenes.run_case(2, 1.5, warmup_s=0.5)
    assert result["errors"] == []  # includes: both decision windows opened by the 3D report, none by the wait
    assert result["n"] == 2 and result["min"] >= SOME_UPDATES_PER_S and math.isfinite(result["max_gap_ms"])
    assert result["kib"] > 0 and result["server_cpu"] > 0


def smoke_study() -> dict:
    """One practice trial and one block of two, the robot always trying by itself (each a 3D scene report and an
    attempt the view shows), at a speed-up that keeps the attempts a second or so long."""
    return tiny_study("bench_load smoke", hint="rely", n_high=1, animation_speed=8.0).model_dump(mode="json")


def test_bench_load_runs_a_case_with_every_bots_3d_view_open(tmp_path, capsys):
    watch = tmp_path / "loop-watch.txt"
    r = bench_load.run_case(f"sqlite:///{tmp_path / 'load.db'}", 2, "fast", bot_processes=1, ramp_s=0.0,
                            config=smoke_study(), watch=watch, load_poll_s=1.0)
    assert r["errors"] == [] and r["completed"] == 2
    assert r["rows"] == r["expected_rows"] == r["distinct_rows"] == 4
    assert r["windows_opened_by"] == {"3d": 6}  # 3 trials each, every window opened by the 3D report
    views = r["views"]
    assert views["viewers"] == 2 and views["errors"] == [] and views["reconnects"] == 0
    assert views["rate_min"] >= SOME_UPDATES_PER_S and math.isfinite(views["max_gap_ms"])
    assert views["whole_attempts_rate_min"] >= SOME_UPDATES_PER_S
    assert 0 < views["max_stamp_gap_ms"] < math.inf  # the server's stamps came with the frames
    bench_load.report("sqlite", r)
    printed = capsys.readouterr().out
    assert "windows opened by: 3d 6" in printed and "3D view, 2 viewers" in printed
    assert re.search(r"every target \((met|not met)\): ", printed)
    # how fast the machine ran the server's kind of work, idle, before and after the run (a slow spell shows)
    probe = r["probe_us"]
    assert all(0 < probe[when] < 10_000 for when in ("before", "during", "during_max", "after"))
    assert re.search(r"machine speed probe \(CPU µs per view frame; \d+ in a quiet hour here\): before [\d.]+, "
                     r"during [\d.]+ \(max [\d.]+\), after [\d.]+", printed)
    assert re.search(r"longest gap in attempts \d+ ms \(between the server's stamps \d+ ms\)", printed)
    by_route = r["routes"]
    assert sum(route["count"] for route in by_route.values()) == r["requests"]
    assert by_route["POST join"]["count"] == 2 and by_route["POST trials/start"]["count"] >= 6
    assert 0 < by_route["POST trials/start"]["p50"] <= by_route["POST trials/start"]["p99"]
    assert "requests per participant:" in printed and "POST trials/shown" in printed
    assert re.search(r"p50 / p99 latency by route \(ms\): .*POST trials/start \d+ / \d+", printed)
    load = r["server_load"]  # the server's own report, read once a second during the run
    assert load["reports"] >= 2 and load["unanswered"] == 0 and load["world_hz"] == 30.0
    assert 0 < load["ticks_per_s_min"] <= load["ticks_per_s_median"] and sum(load["statuses"].values()) >= 2
    assert "the server's own report" in printed and "world loop ticks/s" in printed
    assert 1 <= len(load["skipped_shares"]) <= load["reports"]
    assert re.search(r"3D views skipped, % of ticks, report by report \(.*\): \d+( \d+)+\n", printed)
    # --watch-loop: the server's loop watch wrote its summary (the start-up collection is always there), with the
    # requests' time in the server: at least every bot request was timed
    bench_load.print_loop_watch(watch)
    printed = capsys.readouterr().out
    assert "loop watch: gc generation 2:" in printed and "loop watch: event-loop callbacks over 40 ms:" in printed
    served = re.search(r"loop watch: requests in the server: (\d+), p50 [\d.]+ ms", printed)
    assert served is not None and int(served.group(1)) >= r["requests"], watch.read_text()[:600]
    assert re.search(r"loop watch: requests in the server by route, p50 / p99 ms: .*POST trials/start \d+ / \d+",
                     printed)
    iterations = re.search(r"loop watch: loop iterations: (\d+), busy (\d+) % of \d+ s; work per iteration p50 \d+ "
                           r"ms, p99 \d+ ms, longest \d+ ms; share of the run in iterations of at least 10 ms [\d.]+ %",
                           printed)
    assert iterations is not None and int(iterations.group(1)) > r["requests"] and 0 < int(iterations.group(2)) <= 100


def test_a_views_gaps_are_measured_by_arrival_and_by_the_servers_stamps():
    """A frame that reached the client late (its process was busy) makes a gap by arrival, not between the stamps
    the server put on the frames as it sent them."""
    arrived = [10.0, 10.033, 10.3, 10.333, 11.5]  # the third frame read 0.27 s late; the last one outside the span
    stamps = [50.0, 50.033, 50.067, 50.1, 50.2]
    stats = motion_stats(arrived, [(10.0, 11.0)], stamps)
    assert stats is not None and stats["rate"] == 4.0 and math.isclose(stats["moving_rate"], 3 / 0.333)
    assert math.isclose(stats["max_gap_s"], 0.267) and math.isclose(stats["max_stamp_gap_s"], 0.034)
    assert motion_stats(arrived, [(10.0, 11.0)])["max_stamp_gap_s"] is None  # type: ignore[index]
    assert motion_stats(arrived, []) is None


def test_a_failed_runs_sqlite_database_is_kept_with_what_its_log_holds(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(bench_load.tempfile, "gettempdir", lambda: str(tmp_path / "kept"))
    (tmp_path / "kept").mkdir()
    database = tmp_path / "load-3.db"
    writer = sqlite3.connect(database)
    writer.execute("PRAGMA journal_mode=WAL")
    writer.execute("PRAGMA wal_autocheckpoint=0")  # the row stays in the log only
    writer.execute("CREATE TABLE t (x)")
    writer.execute("INSERT INTO t VALUES (42)")
    writer.commit()
    bench_load.keep_database(f"sqlite:///{database}")
    writer.close()
    kept = next((tmp_path / "kept").glob("bench-load-failed-load-3-*.db"))
    assert str(kept) in capsys.readouterr().out
    with sqlite3.connect(kept) as copy:
        assert copy.execute("SELECT x FROM t").fetchall() == [(42,)]


def test_a_robot_standing_still_at_the_end_of_an_attempt_does_not_count_against_the_view():
    """Updates every 1/30 s for 3 s, then 0.5 s still (a failed attempt's end): 30 a second while it moved."""
    updates = [i / 30 for i in range(91)]
    stats = motion_stats(updates, [(0.0, 3.5)])
    assert stats is not None and math.isclose(stats["moving_rate"], 30.0) and stats["rate"] < 27
    stalled = updates[:45] + [u + 0.3 for u in updates[45:]]  # the view 0.3 s late in the middle of the motion
    assert motion_stats(stalled, [(0.0, 3.8)])["moving_rate"] < 28  # type: ignore[index]


def test_a_run_is_judged_on_every_target_of_the_view():
    """API p99, teleoperation ack p99, the slowest viewer, the longest gap between the server's stamps. A run without
    the view is judged on the first two alone."""
    views = {"rate_min": 29.4, "max_stamp_gap_ms": 150.0}
    good = {"api_ms": {"p99": 90.0}, "teleop_ms": {"p99": 40.0}, "views": views}
    assert bench_load.missed_targets(good) == []
    slow = {"api_ms": {"p99": 132.0}, "teleop_ms": {"p99": 60.0},
            "views": views | {"rate_min": 27.0, "max_stamp_gap_ms": 250.0}}
    assert [m.split(" ")[0] for m in bench_load.missed_targets(slow)] == ["API", "teleop", "slowest", "longest"]
    assert bench_load.missed_targets(good | {"views": views | {"rate_min": math.nan}})  # no attempt seen: not met
    assert bench_load.missed_targets({"api_ms": {}, "teleop_ms": {}, "views": None}) == []


def test_a_cpu_quota_holds_a_worker_to_its_share():
    """``--cpu-quota``: a process spinning in a group of 0.2 cores gets about that much CPU time, and the group
    is gone afterwards. Where this machine gives no writable cgroup CPU controller the option refuses to run."""
    try:
        quotas = cpuquota.WorkerQuotas(0.2, prefix="trustlab-test")
    except SystemExit as exc:
        pytest.skip(f"no writable cgroup CPU controller here: {exc}")
    # It spins for 1.5 s once it is in the group, then says how much CPU time it had meanwhile.
    spinner = subprocess.Popen([sys.executable, "-c", "import sys, time\nsys.stdin.readline()\n"
                                "cpu, end = time.process_time(), time.monotonic() + 1.5\n"
                                "while time.monotonic() < end: pass\nprint(time.process_time() - cpu)"],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        quotas.place({"worker-0": [spinner.pid]})
        used = float(spinner.communicate("go\n", timeout=10)[0])
        throttled = quotas.throttled_s()["worker-0"]
    finally:
        folders = list(quotas.groups.values())
        quotas.close()
    assert used < 0.2 * 1.5 * 1.5  # about its share of the 1.5 s (unlimited, it would have had up to 1.5 s)
    assert throttled > 0.3  # it waited for its quota most of the time
    assert folders and not any(folder.exists() for folder in folders)


def test_each_worker_is_held_with_the_processes_it_started(monkeypatch):
    """``--cpu-quota`` with ``--workers 2``: a group per worker (with its view process and planner), none for the
    supervisor or nginx; one process is one group with everything it started."""
    parents = {1: 0, 2: 1, 3: 1, 4: 1, 5: 2, 6: 2, 7: 5, 8: 3, 9: 4}  # 1 supervisor; 2, 3 workers; 4 nginx
    roles = {1: "serve", 2: "serve", 3: "serve", 4: "nginx", 5: "planner", 6: "view", 7: "helper", 8: "view",
             9: "nginx"}
    monkeypatch.setattr(bench_load, "_parents", lambda: parents | {10: 0})  # 10: a process of another program
    monkeypatch.setattr(bench_load.Server, "role", staticmethod(roles.get))
    server = object.__new__(bench_load.Server)
    server.proc = type("Proc", (), {"pid": 1})()
    server.workers = 2
    groups = server.worker_groups()
    assert {name: sorted(pids) for name, pids in groups.items()} == {"worker-0": [2, 5, 6, 7], "worker-1": [3, 8]}
    server.workers = 1
    assert sorted(server.worker_groups()["worker-0"]) == sorted(parents)
