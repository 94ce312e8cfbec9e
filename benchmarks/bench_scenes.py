"""3D view under load: /robot/j1 update rate per viewer and server CPU for N sessions (SPEC §8).

Run: ``python benchmarks/bench_scenes.py [--sessions 1 10 30] [--seconds 10]``.

For each N a fresh server runs in a subprocess (the real app under uvicorn on a
free loopback port, SQLite, world loop on). N participants join and start a
high-complexity practice trial; the server then plays, through the world hub's
playback, a long "attempt" in each trial's scene that moves every joint all the
time (so every 30 Hz tick changes every robot frame: the worst case per tick).
One simulated viser client per session connects through the relay
(``WS /viewer/{token}``, subprotocol ``viser-v1.1.1``), decodes every frame
(zstd + msgpack) and counts the ``SetOrientationMessage`` of ``/robot/j1``.

Prints per N: the j1 update rate each client received (min / median, target
>= 29/s at 30 sessions), bytes per client per second, the server process's
CPU (% of one core, from /proc/<pid>/stat) and the clients' own CPU (they run
in this process and compete for the same cores).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TARGET_RATE = 29.0
SUBPROTOCOL = "viser-v1.1.1"
HELLO = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [-1.0, -2.4, 1.9], "fov": 0.87,
         "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 1000, "look_at": [1.25, 0.0, 0.6],
         "up_direction": [0.0, 0.0, 1.0]}


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

    from server.main import create_app
    from server.migrate import upgrade
    from server.services import sessions, trials
    from server.services.admin import ensure_admin_token
    from server.settings import Settings

    url = f"sqlite:///{database}"
    upgrade(url)
    app = create_app(Settings(database_url=url, host="127.0.0.1", port=port, sweep_interval_s=3600))
    with app.state.sessionmaker.begin() as session:
        admin = ensure_admin_token(session)

    @app.post("/_bench/wave/{token}")
    def wave(token: str) -> dict:
        """Benchmark only: play the endless wave in the participant's current trial scene."""
        with app.state.sessionmaker() as session:
            participant = sessions.participant_by_token(session, token)
            runtime = app.state.runtimes.get(sessions.version_of(session, participant))
            planned = trials.planned_trial(participant, runtime)
            scene = app.state.world.scene(runtime.config.seed, participant.public_id, planned)
            app.state.world.play(participant.public_id, Wave(scene, phase=participant.id * 0.7), time.monotonic(), 1.0)
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


class Client:
    def __init__(self, token: str):
        self.token = token
        self.j1: list[float] = []  # arrival times of /robot/j1 orientation updates
        self.bytes: list[tuple[float, int]] = []
        self.replayed = asyncio.Event()

    async def run(self, port: int, stop: asyncio.Event) -> None:
        import msgspec
        import websockets
        import zstandard
        unzstd = zstandard.ZstdDecompressor()
        async with websockets.connect(f"ws://127.0.0.1:{port}/viewer/{self.token}", subprotocols=[SUBPROTOCOL],
                                      max_size=None, compression=None) as ws:
            await ws.send(msgspec.msgpack.encode(HELLO))
            while not stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.5)
                except TimeoutError:
                    continue
                now = time.monotonic()
                raw, packed = struct.unpack_from("<QQ", frame)
                messages = msgspec.msgpack.decode(unzstd.decompress(frame[16:16 + packed], max_output_size=raw))["messages"]
                self.bytes.append((now, len(frame)))
                for m in messages:
                    kind = m["type"]
                    if kind == "SetOrientationMessage" and m["name"] == "/robot/j1":
                        self.j1.append(now)
                    elif kind == "ReplayDoneMessage":
                        self.replayed.set()


def setup_sessions(base: str, admin: str, n: int) -> list[str]:
    import httpx

    from experiment.templates import demo
    config = demo()
    config = config.model_copy(update={"timing": config.timing.model_copy(update={"decision_window_s": 60.0})})
    tokens = []
    with httpx.Client(base_url=base, timeout=30) as http:
        r = http.post("/api/admin/studies", json={"slug": "bench", "config": config.model_dump(mode="json")},
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

    from server.models import Participant
    from server.services.sessions import hash_token
    engine = create_engine(f"sqlite:///{database}")
    with Session(engine) as session, session.begin():
        for token in tokens:
            participant = session.scalar(select(Participant).where(Participant.token_hash == hash_token(token)))
            participant.step = {"phase": "practice", "index": index}
    engine.dispose()


async def measure(port: int, tokens: list[str], seconds: float, server_pid: int) -> dict:
    stop = asyncio.Event()
    clients = [Client(t) for t in tokens]
    tasks = [asyncio.create_task(c.run(port, stop)) for c in clients]
    try:
        await asyncio.wait_for(asyncio.gather(*(c.replayed.wait() for c in clients)), 60)
        await asyncio.sleep(2.0)  # warm up
        t0, cpu0, own0 = time.monotonic(), cpu_seconds(server_pid), os.times()
        await asyncio.sleep(seconds)
        t1, cpu1, own1 = time.monotonic(), cpu_seconds(server_pid), os.times()
    finally:
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
    span = t1 - t0
    rates = [sum(t0 <= t < t1 for t in c.j1) / span for c in clients]
    gaps = [b - a for c in clients for a, b in zip(c.j1, c.j1[1:]) if t0 <= a < t1]
    volume = [sum(n for t, n in c.bytes if t0 <= t < t1) / span for c in clients]
    return {"n": len(tokens), "min": min(rates), "median": statistics.median(rates), "max_gap_ms": 1000 * max(gaps),
            "p99_gap_ms": 1000 * statistics.quantiles(gaps, n=100)[98] if len(gaps) > 100 else float("nan"),
            "kib": statistics.median(volume) / 1024, "server_cpu": 100 * (cpu1 - cpu0) / span,
            "client_cpu": 100 * ((own1.user - own0.user) + (own1.system - own0.system)) / span}


def run_case(n: int, seconds: float) -> dict:
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        database = str(Path(tmp) / "bench.db")
        server = subprocess.Popen([sys.executable, __file__, "--serve", str(port), database], stdout=subprocess.PIPE,
                                  text=True, cwd=ROOT)
        try:
            assert server.stdout is not None
            admin = json.loads(server.stdout.readline())["admin"]
            base = f"http://127.0.0.1:{port}"
            _wait_until_up(base)
            tokens = setup_sessions(base, admin, n)
            to_practice_trial(database, tokens, 1)  # practice trial 2: high complexity, the robot's own attempt
            import httpx
            with httpx.Client(base_url=base, timeout=30) as http:
                for token in tokens:
                    http.post(f"/api/p/{token}/trials/start",
                              json={"practice": True, "block": 0, "trial": 2}).raise_for_status()
                    assert http.post(f"/_bench/wave/{token}").raise_for_status().json()["obstacles"] > 0
            return asyncio.run(measure(port, tokens, seconds, server.pid))
        finally:
            server.terminate()
            try:
                server.wait(10)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 10, 30])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--serve", nargs=2, metavar=("PORT", "DB"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(int(args.serve[0]), args.serve[1])
        return
    print(f"3D view load: every robot frame moving, one simulated viewer per session, {args.seconds:g} s per case, "
          f"{os.cpu_count()} CPUs")
    print(f"{'sessions':>8}{'j1/s min':>10}{'j1/s median':>13}{'max gap ms':>12}{'p99 gap ms':>12}{'KiB/s/client':>14}"
          f"{'server CPU %':>14}{'clients CPU %':>15}")
    worst = math.inf
    for n in args.sessions:
        r = run_case(n, args.seconds)
        print(f"{r['n']:>8}{r['min']:>10.1f}{r['median']:>13.1f}{r['max_gap_ms']:>12.0f}{r['p99_gap_ms']:>12.0f}"
              f"{r['kib']:>14.1f}{r['server_cpu']:>14.1f}{r['client_cpu']:>15.1f}")
        if n == max(args.sessions):
            worst = r["min"]
    verdict = "PASS" if worst >= TARGET_RATE else "FAIL"
    print(f"{verdict}: min /robot/j1 rate at {max(args.sessions)} sessions {worst:.1f}/s (target >= {TARGET_RATE:g}/s)")


if __name__ == "__main__":
    main()
