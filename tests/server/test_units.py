"""Where a unit of work runs (``server.db.units.Database.run``): on the started app's event loop, one at a time, with
SQLite and with PostgreSQL alike; a unit that fails leaves nothing behind."""

import asyncio
import threading

import pytest
from sqlalchemy import func, select

from server.errors import Invalid
from server.models import Event, Study
from server.services.audit import log_event
from tests.server.factories import make_client, make_study


def test_units_run_on_the_event_loop_one_at_a_time_and_a_failed_one_writes_nothing(database_url):
    client, admin = make_client(database_url=database_url)
    with client:  # started: the database turn exists only on the running loop
        make_study(client, admin)
        app = client.app
        with app.state.services.sessionmaker() as session:
            study_id = session.scalar(select(Study.id).where(Study.slug == "s1"))
        loop_thread = client.portal.call(threading.get_ident)
        inside = {"now": 0, "most": 0}
        threads: list[int] = []

        def work(session):
            inside["now"] += 1
            inside["most"] = max(inside["most"], inside["now"])
            threads.append(threading.get_ident())
            log_event(session, study_id, None, "unit_test")
            session.flush()
            inside["now"] -= 1

        def failing(session):
            log_event(session, study_id, None, "unit_test_failed")
            session.flush()
            raise Invalid("refused after writing")

        async def many() -> None:
            await asyncio.gather(*(app.state.services.database.run(work) for _ in range(8)))

        client.portal.call(many)
        with pytest.raises(Invalid):
            client.portal.call(app.state.services.database.run, failing)

        assert threads == [loop_thread] * 8
        assert inside["most"] == 1
        with app.state.services.sessionmaker() as session:
            kinds = dict(session.execute(select(Event.kind, func.count()).where(Event.kind.like("unit_test%"))
                                         .group_by(Event.kind)).all())
        assert kinds == {"unit_test": 8}


def test_a_worker_threads_unit_takes_the_turn_so_the_loop_never_blocks_on_the_database(database_url):
    """The sweeper, exports and fits open their units in worker threads (``Database``): they wait for the database
    turn as the loop's units do, so a unit on the loop waits for the thread without blocking the event loop
    (before, it blocked in SQLite's one-connection pool, and the loop with it)."""
    client, admin = make_client(database_url=database_url)
    with client:
        make_study(client, admin)
        app = client.app
        inside, leave = threading.Event(), threading.Event()
        order: list[str] = []

        def in_thread() -> None:
            with app.state.services.database.begin() as session:
                session.scalar(select(func.count()).select_from(Study))
                inside.set()
                leave.wait(timeout=30)
                order.append("thread")

        async def meanwhile() -> list[str]:
            await asyncio.to_thread(inside.wait, 30)
            unit = asyncio.ensure_future(app.state.services.database.run(lambda session: order.append("loop")))
            for _ in range(20):  # the loop runs on while the unit waits for the thread's turn
                await asyncio.sleep(0)
            waiting = [] if unit.done() else ["unit waited"]
            leave.set()
            await unit
            return waiting

        thread = threading.Thread(target=in_thread)
        thread.start()
        try:
            assert client.portal.call(meanwhile) == ["unit waited"]
        finally:
            leave.set()
            thread.join(30)
        assert order == ["thread", "loop"]
        # a reader in a thread takes the turn as well (``Database()``: the exports' pages)
        with app.state.services.database() as session:
            assert session.scalar(select(func.count()).select_from(Study)) == 1


def test_work_in_a_worker_thread_runs_to_its_end_however_its_caller_is_cancelled(database_url):
    """``Database.in_thread``: a cancelled caller is cancelled only once the thread is done (a thread cannot be
    stopped, and it may hold a connection), and ``settle`` (the server's shutdown) waits for every such thread."""
    client, _ = make_client(database_url=database_url)
    with client:
        database = client.app.state.services.database
        release, finished = threading.Event(), []

        def work(label: str) -> str:
            release.wait(10)
            finished.append(label)
            return label

        async def cancel_one_and_settle() -> list[str]:
            cancelled = asyncio.create_task(database.in_thread(work, "cancelled"))
            asyncio.create_task(database.in_thread(work, "left running"))
            await asyncio.sleep(0.05)
            cancelled.cancel()
            await asyncio.sleep(0.1)
            seen = [f"cancelled task done: {cancelled.done()}", f"finished: {finished}"]
            release.set()
            with pytest.raises(asyncio.CancelledError):
                await cancelled
            await database.settle()
            return seen + [f"settled with {sorted(finished)}"]

        assert client.portal.call(cancel_one_and_settle) == [
            "cancelled task done: False", "finished: []", "settled with ['cancelled', 'left running']"]
