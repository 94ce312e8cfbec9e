"""Where a unit of work runs (``server.units.run_unit``): on the started app's event loop, one at a time, with SQLite
and with PostgreSQL alike; a unit that fails leaves nothing behind."""

import asyncio
import threading

import pytest
from sqlalchemy import func, select

from server.units import run_unit
from server.errors import Invalid
from server.models import Event, Study
from server.services.audit import log_event
from tests.server.factories import make_client, make_study


def test_units_run_on_the_event_loop_one_at_a_time_and_a_failed_one_writes_nothing(database_url):
    client, admin = make_client(database_url=database_url)
    with client:  # started: the database turn exists only on the running loop
        make_study(client, admin)
        app = client.app
        with app.state.sessionmaker() as session:
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
            await asyncio.gather(*(run_unit(app, work) for _ in range(8)))

        client.portal.call(many)
        with pytest.raises(Invalid):
            client.portal.call(run_unit, app, failing)

        assert threads == [loop_thread] * 8
        assert inside["most"] == 1
        with app.state.sessionmaker() as session:
            kinds = dict(session.execute(select(Event.kind, func.count()).where(Event.kind.like("unit_test%"))
                                         .group_by(Event.kind)).all())
        assert kinds == {"unit_test": 8}
