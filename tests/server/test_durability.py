"""kill -9 of a real server in the middle of a bot run loses nothing acknowledged (SPEC §10)."""

import signal
import time

import httpx
import pytest
from sqlalchemy import create_engine, text

from server.bots import Bot, BotStats
from tests.server.live import free_port, make_bots, run_all, start_server

N_BOTS = 3


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
        bots = make_bots(port, stats, N_BOTS)
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
        resumed = make_bots(port, stats, N_BOTS)
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
