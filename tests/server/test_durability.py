"""kill -9 of a real server in the middle of a bot run loses nothing acknowledged (SPEC §10)."""

import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import closing, contextmanager

import httpx
import pytest
from sqlalchemy import create_engine, text
from websockets.sync.client import connect

from experiment.iohmm import paper_params
from server.bots import Bot, BotStats
from server.cli_server import _SyncSocket

N_BOTS = 3


def free_port() -> int:
    with closing(socket.socket()) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(db: str, port: int, log) -> tuple[subprocess.Popen, str | None]:
    """``trustlab serve`` in a subprocess; returns it and the admin token it printed (first run only)."""
    offset = log.tell()
    process = subprocess.Popen([sys.executable, "-c", "from server.cli import app; app()", "serve", "--port", str(port),
                                "--database-url", db], stdout=log, stderr=subprocess.STDOUT, text=True)
    token = None
    for _ in range(600):
        try:
            httpx.get(f"http://127.0.0.1:{port}/openapi.json", timeout=1).raise_for_status()
            break
        except httpx.HTTPError:
            time.sleep(0.05)
    else:
        process.kill()
        raise RuntimeError("server did not start")
    log.flush()
    with open(log.name, encoding="utf-8") as text_log:
        text_log.seek(offset)
        for line in text_log:
            if "admin token (shown once" in line:
                token = line.rsplit(" ", 1)[-1].strip()
    return process, token


def make_bots(port: int, stats: BotStats) -> list[Bot]:
    @contextmanager
    def sockets(path):
        with connect(f"ws://127.0.0.1:{port}{path}", open_timeout=5) as ws:
            yield _SyncSocket(ws)

    return [Bot(httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10), sockets, "fast", paper_params(), 7, stats,
                external_id=f"durable-{i}") for i in range(N_BOTS)]


def run_all(bots: list[Bot]) -> list[BaseException | None]:
    results: list[BaseException | None] = [None] * len(bots)

    def one(i: int) -> None:
        try:
            bots[i].run()
        except BaseException as exc:  # the server dies under the bots
            results[i] = exc

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(bots))]
    for t in threads:
        t.start()
    return results, threads


@pytest.mark.slow
def test_sigkill_mid_run_loses_no_acknowledged_trial(tmp_path):
    db = f"sqlite:///{tmp_path / 'durable.db'}"
    port = free_port()
    log = open(tmp_path / "server.log", "a+", encoding="utf-8")
    server, admin = start_server(db, port, log)
    try:
        r = httpx.post(f"http://127.0.0.1:{port}/api/admin/studies", json={"slug": "fast", "template": "demo-fast"},
                       headers={"Authorization": f"Bearer {admin}"})
        assert r.status_code == 201, r.text
        stats = BotStats()
        bots = make_bots(port, stats)
        results, threads = run_all(bots)
        deadline = time.monotonic() + 60
        while sum(len(b.acknowledged) for b in bots) < 2 * N_BOTS and time.monotonic() < deadline:
            time.sleep(0.05)
        server.send_signal(signal.SIGKILL)
        server.wait()
        for t in threads:
            t.join(timeout=60)
    finally:
        if server.poll() is None:
            server.kill()
    acknowledged = {(b.external_id, *key): outcome for b in bots for key, outcome in b.acknowledged.items()}
    assert acknowledged, "the bots got no trial acknowledged before the kill"

    engine = create_engine(db)
    with engine.connect() as conn:
        rows = conn.execute(text("SELECT p.external_id, t.practice, t.block, t.trial, t.outcome FROM trial t "
                                 "JOIN participant p ON p.id = t.participant_id WHERE t.stage = 'done'")).all()
        assert conn.execute(text("PRAGMA integrity_check")).scalar() == "ok"
    engine.dispose()
    stored = {(e, bool(p), b, t): o for e, p, b, t, o in rows}
    for key, outcome in acknowledged.items():
        assert stored.get(key) == outcome, f"acknowledged trial {key} missing or changed after kill -9"

    # after a restart every bot resumes its session (same external id) and finishes
    resumed: list[Bot] = []
    server, _ = start_server(db, port, log)
    try:
        stats = BotStats()
        resumed = make_bots(port, stats)
        results, threads = run_all(resumed)
        for t in threads:
            t.join(timeout=300)
        assert results == [None] * N_BOTS and stats.completed == N_BOTS
    finally:
        server.kill()
        server.wait()
        log.close()
        for bot in bots + resumed:
            bot.http.close()
    engine = create_engine(db)
    with engine.connect() as conn:
        per_participant = conn.execute(text("SELECT participant_id, COUNT(*) FROM trial WHERE practice = 0 "
                                            "GROUP BY participant_id")).all()
        statuses = conn.execute(text("SELECT status FROM participant")).scalars().all()
    engine.dispose()
    assert statuses == ["completed"] * N_BOTS
    assert [n for _, n in per_participant] == [12] * N_BOTS  # no trial lost, none duplicated
