"""3D view under load: the robot's update rate per viewer and server CPU for N sessions (SPEC §8).

Run: ``python benchmarks/bench_scenes.py [--sessions 1 10 30] [--seconds 10]``.

For each N a fresh server runs in a subprocess (the real app under uvicorn on a
free loopback port, SQLite, world loop on, the join rate limits raised as for
``bench_load.py``). N participants join and reach a high-complexity
practice trial, where the robot tries by itself. One headless viser client
per session (``server.harness.viewer_client``: through the relay
``WS /viewer/{token}``, subprotocol ``viser-v1.1.1``, every frame decoded)
opens the view; then every session at once starts the trial (it starts
``presenting``) and reports its scene shown in 3D as the page does
(``server.harness.bots.Bot.show_scene``), which opens its decision window. The server then plays, through the world
hub's playback, a long "attempt" in each trial's scene that moves every joint all the time (so every
30 Hz tick changes every robot frame: the worst case per tick).

Prints per N: the robot updates (frames moving the robot) each client received
per second (min / median, target >= 29/s at 30 sessions), the longest and the
99th-percentile gap between updates, bytes per client per second, the server
process's CPU (% of one core, from /proc/<pid>/stat) and the clients' own CPU
(their thread in this process; they compete for the same cores).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_load import JOIN_LIMITS_ENV, scored_rows  # noqa: E402 -- after the sys.path edit that makes benchmarks/ importable
from benchmarks.results_log import append_result  # noqa: E402 -- after the sys.path edit that makes benchmarks/ importable

TARGET_RATE = 29.0
#: Seconds of the wave before the measurement starts.
WARMUP_S = 2.0


# --- the server (subprocess) ---------------------------------------------------------------------

class Wave:
    """A never-ending "attempt" for the hub's playback: the robot parked at the shelf, every joint swinging."""

    def __init__(self, scene, phase: float):
        from experiment.world.path import ready_joints
        self.scene, self.phase = scene, phase
        self.ready = [float(v) for v in ready_joints()]
        self.duration = math.inf

    def state_at(self, t: float):
        from experiment.world import WorldState
        from experiment.world import constants as K
        from experiment.world.state import shelf_item_state
        w = 2 * math.pi * 0.2 * t + self.phase
        q = (self.ready[0] + 0.8 * math.sin(w), self.ready[1] + 0.15 * math.sin(1.3 * w),
             self.ready[2] + 0.15 * math.sin(0.7 * w), self.ready[3] + 0.1 * math.sin(w))
        gap = K.GRIPPER_MAX * (0.6 + 0.4 * math.sin(2 * w))
        return WorldState(t, self.scene.park, q, gap, gap, shelf_item_state(self.scene))


def serve(port: int, database: str) -> None:
    import uvicorn

    from server.db.migrate import upgrade
    from server.main import create_app
    from server.services import sessions, trials
    from server.services.admin import ensure_admin_token
    from server.settings import Settings

    url = f"sqlite:///{database}"
    upgrade(url)
    app = create_app(Settings(database_url=url, host="127.0.0.1", port=port, sweep_interval_s=3600))
    with app.state.services.sessionmaker.begin() as session:
        admin = ensure_admin_token(session)

    @app.post("/_bench/wave/{token}")
    def wave(token: str) -> dict:
        """Benchmark only: play the endless wave in the participant's current trial scene."""
        with app.state.services.sessionmaker() as session:
            participant = sessions.participant_by_token(session, token)
            runtime = sessions.runtime_of(session, app.state.services.runtimes, participant)
            planned = trials.planned_trial(participant, runtime)
            scene = app.state.services.hub.scene(runtime.config.seed, participant.public_id, planned)
            app.state.services.hub.play(participant.public_id, Wave(scene, phase=participant.id * 0.7),
                                        time.monotonic(), 1.0)
            return {"public_id": participant.public_id, "obstacles": len(scene.obstacles)}

    print(json.dumps({"admin": admin}), flush=True)
    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


# --- the clients (this process) ------------------------------------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (and its reaped children) in seconds, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(v) for v in fields[11:15]) / os.sysconf("SC_CLK_TCK")


def setup_sessions(base: str, admin: str, n: int) -> list[str]:
    import httpx

    from experiment.templates import demo
    config = demo()
    config = config.model_copy(update={"timing": config.timing.model_copy(update={"decision_window_s": 60.0})})
    tokens = []
    with httpx.Client(base_url=base, timeout=30) as http:
        r = http.post("/api/admin/studies",
                      json={"status": "open", "slug": "bench", "config": config.model_dump(mode="json")},
                      headers={"Authorization": f"Bearer {admin}"})
        r.raise_for_status()
        for _ in range(n):
            token = http.post("/api/studies/bench/join").raise_for_status().json()["token"]
            http.post(f"/api/p/{token}/consent", json={"agree": True}).raise_for_status()
            tokens.append(token)
    return tokens


def to_practice_trial(database: str, tokens: list[str], index: int) -> None:
    """Move every participant to practice trial ``index`` (the tests do the same; it is not an API)."""
    from sqlalchemy import create_engine, select
    from sqlalchemy.orm import Session

    from experiment.flow import PracticeStep
    from server.models import Participant
    from server.services.sessions import hash_token
    engine = create_engine(f"sqlite:///{database}")
    with Session(engine) as session, session.begin():
        for token in tokens:
            participant = session.scalar(select(Participant).where(Participant.token_hash == hash_token(token)))
            assert participant is not None, "a participant joined with this token"
            participant.step = PracticeStep(index=index)
    engine.dispose()


def start_and_show(base: str, token: str, view) -> None:
    """Start the session's trial, and report its scene shown in the 3D view as the page does (the decision window
    opens). The sessions do this at once, each in its thread: the window opens by itself ``scene_wait_s`` after
    the trial's start, and one session's report takes a few viewer polls."""
    import httpx

    from experiment.iohmm import paper_params
    from server.harness.bots import Bot
    from server.harness.client import BotStats
    with httpx.Client(base_url=base, timeout=30) as http:
        started = http.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": 2})
        assert started.raise_for_status().json()["trial"]["stage"] == "presenting"
        bot = Bot(http, None, "bench", paper_params(), 0, BotStats(), display=view)  # type: ignore[arg-type]  # only shows scenes: no socket
        bot.token = token
        deadline = time.monotonic() + 30
        while (state := bot.state())["trial"]["stage"] == "presenting":
            if time.monotonic() > deadline:
                raise RuntimeError(f"the 3D view did not show the scene: {state['trial']}")
            bot.show_scene(state["trial"])


def moved(stats: dict | None) -> dict:
    """``motion_stats`` of a span the robot moved in: never None."""
    assert stats is not None, "the robot moved"
    return stats


def measure(base: str, tokens: list[str], seconds: float, server_pid: int, warmup_s: float) -> dict:
    import httpx

    from server.harness.viewer_client import BotView, ViewerPool, motion_stats
    pool = ViewerPool(base)
    try:
        views = [BotView(pool) for _ in tokens]
        for token, view in zip(tokens, views, strict=True):
            view.open(token)
        clients = [view.client for view in views if view.client is not None]
        assert len(clients) == len(views), "every view is open"
        for client in clients:
            if not client.replayed.wait(60):
                raise RuntimeError(f"no scene replay: {client}")
        with ThreadPoolExecutor(len(tokens)) as threads:
            list(threads.map(lambda tv: start_and_show(base, *tv), zip(tokens, views, strict=True)))
        with httpx.Client(base_url=base, timeout=30) as http:
            for token in tokens:
                assert http.post(f"/_bench/wave/{token}").raise_for_status().json()["obstacles"] > 0
        time.sleep(warmup_s)
        t0, cpu0, own0 = time.monotonic(), cpu_seconds(server_pid), pool.cpu_seconds()
        time.sleep(seconds)
        t1, cpu1, own1 = time.monotonic(), cpu_seconds(server_pid), pool.cpu_seconds()
    finally:
        pool.stop()
    stats = [moved(motion_stats(client.updates, [(t0, t1)])) for client in clients]
    rates = [m["rate"] for m in stats]
    gaps = [g for m in stats for g in m["gaps"]]
    volume = [sum(n for t, n in client.frame_bytes if t0 <= t < t1) / (t1 - t0) for client in clients]
    errors = [client.error for client in clients if client.error]
    return {"n": len(tokens), "min": min(rates), "median": statistics.median(rates),
            "max_gap_ms": 1000 * max(m["max_gap_s"] for m in stats),
            "p99_gap_ms": 1000 * statistics.quantiles(gaps, n=100)[98] if len(gaps) > 100 else float("nan"),
            "kib": statistics.median(volume) / 1024, "server_cpu": 100 * (cpu1 - cpu0) / (t1 - t0),
            "client_cpu": 100 * (own1 - own0) / (t1 - t0), "errors": errors}


def run_case(n: int, seconds: float, warmup_s: float = WARMUP_S) -> dict:
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        database = str(Path(tmp) / "bench.db")
        server = subprocess.Popen([sys.executable, __file__, "--serve", str(port), database], stdout=subprocess.PIPE,
                                  text=True, cwd=ROOT, env=os.environ | JOIN_LIMITS_ENV)
        try:
            assert server.stdout is not None
            admin = json.loads(server.stdout.readline())["admin"]
            base = f"http://127.0.0.1:{port}"
            _wait_until_up(base)
            tokens = setup_sessions(base, admin, n)
            to_practice_trial(database, tokens, 1)  # practice trial 2: high complexity, the robot's own attempt
            result = measure(base, tokens, seconds, server.pid, warmup_s)
            opened = scored_rows(f"sqlite:///{database}")[2]
            if opened != {"3d": n}:  # every decision window opened by the 3D report, none by the wait limit
                result["errors"].append(f"decision windows opened by {opened}, expected 3d {n}")
            return result
        finally:
            server.terminate()
            try:
                server.wait(10)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()
            if server.stdout is not None:
                server.stdout.close()


def _wait_until_up(base: str) -> None:
    import httpx
    deadline = time.monotonic() + 30
    while True:
        try:
            httpx.get(base + "/openapi.json", timeout=2)
            return
        except httpx.TransportError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def main(argv: list[str] | None = None) -> bool:
    """Run the cases and print the table; True if the target rate held at the largest N with no viewer error."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 10, 30])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--serve", nargs=2, metavar=("PORT", "DB"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        serve(int(args.serve[0]), args.serve[1])
        return True
    print(f"3D view load: every robot frame moving, one simulated viewer per session, {args.seconds:g} s per case, "
          f"{os.cpu_count()} CPUs")
    print(f"{'sessions':>8}{'upd/s min':>10}{'upd/s median':>13}{'max gap ms':>12}{'p99 gap ms':>12}"
          f"{'KiB/s/client':>14}{'server CPU %':>14}{'clients CPU %':>15}")
    worst, errors, cases = math.inf, [], []
    for n in args.sessions:
        r = run_case(n, args.seconds)
        print(f"{r['n']:>8}{r['min']:>10.1f}{r['median']:>13.1f}{r['max_gap_ms']:>12.0f}{r['p99_gap_ms']:>12.0f}"
              f"{r['kib']:>14.1f}{r['server_cpu']:>14.1f}{r['client_cpu']:>15.1f}", flush=True)
        for error in r["errors"][:5]:
            print(f"    {error}")
        errors += r["errors"]
        cases.append(r | {"errors": r["errors"][:5]})
        if n == max(args.sessions):
            worst = r["min"]
    passed = worst >= TARGET_RATE and not errors
    print(f"{'PASS' if passed else 'FAIL'}: min robot update rate at {max(args.sessions)} sessions {worst:.1f}/s "
          f"(target >= {TARGET_RATE:g}/s), {len(errors)} errors (viewers, windows not opened by 3D)")
    append_result("bench_scenes.py", {"sessions": args.sessions, "seconds": args.seconds, "cpus": os.cpu_count()},
                  {"cases": cases, "min_rate_at_largest": worst, "target_rate": TARGET_RATE, "errors": len(errors),
                   "passed": passed})
    return passed


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
