"""Group commit for SQLite: acknowledged writes are fsynced off the event loop, in batches."""

from __future__ import annotations

import asyncio
import shutil
import threading
import time
from pathlib import Path

from sqlalchemy import text

from server.db.engine import make_engine
from server.db.walsync import WalSync
from tests.server.factories import join, make_client, make_study


def _run(coroutine_function):
    """asyncio.run in a thread of its own (another test's library may have left an event loop running here)."""
    outcome: dict[str, object] = {}

    def target() -> None:
        try:
            outcome["result"] = asyncio.run(coroutine_function())
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the caller's thread
            outcome["error"] = exc

    thread = threading.Thread(target=target)
    thread.start()
    thread.join()
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    return outcome["result"]


def _engine(tmp_path: Path):
    engine = make_engine(f"sqlite:///{tmp_path / 'w.db'}")
    with engine.begin() as connection:
        connection.execute(text("CREATE TABLE t (x INTEGER)"))
    return engine


def test_only_write_statements_mark_the_log_dirty(tmp_path):
    engine = _engine(tmp_path)
    sync = WalSync.for_engine(engine)
    assert sync is not None and sync.wal_path.name == "w.db-wal"
    with engine.begin() as connection:
        sync.wrote(connection)
        connection.execute(text("SELECT count(*) FROM t")).all()
        assert not sync.wrote(connection)
        connection.execute(text("INSERT INTO t VALUES (1)"))
        assert sync.wrote(connection) and not sync.wrote(connection)
    engine.dispose()


def test_no_wal_sync_for_memory_or_postgres():
    assert WalSync.for_engine(make_engine("sqlite://")) is None
    assert WalSync.for_engine(make_engine("postgresql+psycopg://u@localhost/db")) is None


def test_every_waiter_returns_after_an_fsync_that_began_after_it_asked(tmp_path, monkeypatch):
    """Concurrent waiters share fsyncs, and none is released by an fsync that started before it asked."""
    engine = _engine(tmp_path)
    sync = WalSync.for_engine(engine)
    assert sync is not None
    fsync_starts: list[float] = []
    real_fsync = sync._fsync

    def slow_fsync() -> None:
        fsync_starts.append(time.monotonic())
        time.sleep(0.02)
        real_fsync()

    monkeypatch.setattr(sync, "_fsync", slow_fsync)

    async def writer(i: int) -> tuple[float, float]:
        await asyncio.sleep(0.003 * i)
        with engine.begin() as connection:
            connection.execute(text("INSERT INTO t VALUES (:x)"), {"x": i})
        asked = time.monotonic()
        await sync.durable()
        return asked, time.monotonic()

    async def main() -> list[tuple[float, float]]:
        return await asyncio.gather(*(writer(i) for i in range(40)))

    results = _run(main)
    assert 1 < len(fsync_starts) < 40  # batched
    for asked, released in results:
        assert any(asked <= start <= released for start in fsync_starts)
    assert sync.syncs == len(fsync_starts)
    engine.dispose()


def test_a_failed_fsync_fails_its_waiters(tmp_path, monkeypatch):
    engine = _engine(tmp_path)
    sync = WalSync.for_engine(engine)
    assert sync is not None

    def broken() -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(sync, "_fsync", broken)

    async def main() -> None:
        await sync.durable()

    try:
        _run(main)
    except OSError as exc:
        assert exc.errno == 5
    else:
        raise AssertionError("the waiter was released without a durable log")
    engine.dispose()


def test_a_participant_write_is_synced_before_its_response(sqlite_template, tmp_path):
    path = tmp_path / "trustlab.db"
    shutil.copy(sqlite_template, path)
    client, token = make_client(database_url=f"sqlite:///{path}")
    make_study(client, token)
    sync = client.app.state.services.database.wal_sync
    assert sync is not None
    participant = join(client)["token"]
    before = sync.syncs
    assert client.post(f"/api/p/{participant}/consent", json={"agree": True}).status_code == 200
    assert sync.syncs > before
    before = sync.syncs
    assert client.get(f"/api/p/{participant}/state").status_code == 200  # seen a moment ago: nothing written
    assert sync.syncs == before
    admin = {"Authorization": f"Bearer {token}"}
    assert client.get("/api/admin/studies/s1/participants", headers=admin).status_code == 200  # an admin read
    assert sync.syncs == before
    assert client.post("/api/admin/studies/s1/close", headers=admin).status_code == 200
    assert sync.syncs > before  # an admin write


def test_waiters_on_several_event_loops_are_all_released(tmp_path):
    """Each event loop gets its own batches (test clients and the server may run apps on several)."""
    engine = _engine(tmp_path)
    sync = WalSync.for_engine(engine)
    assert sync is not None
    errors: list[BaseException] = []

    async def five_waiters() -> None:
        await asyncio.wait_for(asyncio.gather(*(sync.durable() for _ in range(5))), timeout=10)

    def run_loop() -> None:
        try:
            asyncio.run(five_waiters())
        except BaseException as exc:  # noqa: BLE001 -- reported below
            errors.append(exc)

    threads = [threading.Thread(target=run_loop) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    engine.dispose()
