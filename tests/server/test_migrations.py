"""The Alembic migrations build exactly the schema the models describe, and are reversible.

Runs on every backend in ``tests.conftest.BACKENDS`` (SQLite always; PostgreSQL
when ``TRUSTLAB_TEST_POSTGRES_URL`` is set).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import DateTime, MetaData, String, Table, insert, inspect, select
from sqlalchemy.engine import Engine

from experiment.flow import CONSENT
from server import models
from server.db.engine import Base, make_engine, make_sessionmaker
from server.db.migrate import MIGRATIONS, alembic_config, downgrade, upgrade

MODEL_TABLES = set(Base.metadata.tables)


@pytest.fixture
def engine(empty_database_url: str) -> Iterator[Engine]:
    engine = make_engine(empty_database_url)
    try:
        yield engine
    finally:
        engine.dispose()


def schema_diff(engine: Engine, metadata: MetaData = Base.metadata) -> list[Any]:
    """What ``alembic revision --autogenerate`` would emit to bring the database to ``metadata``.

    ``compare_type=True`` as in ``migrations/env.py``: Alembic compiles each model type for the
    database's dialect, so ``TZDateTime`` is compared through its impl, ``DateTime(timezone=True)``
    (``TIMESTAMP WITH TIME ZONE`` on PostgreSQL; SQLite has one ``DATETIME`` type).
    """
    with engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True, "target_metadata": metadata})
        return compare_metadata(context, metadata)


def tables(engine: Engine) -> set[str]:
    return set(inspect(engine).get_table_names()) - {"alembic_version"}


def current_revision(engine: Engine) -> str | None:
    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def test_models_and_migrations_match(empty_database_url: str, engine: Engine) -> None:
    upgrade(empty_database_url)
    assert tables(engine) == MODEL_TABLES
    assert schema_diff(engine) == []


def test_the_comparison_sees_type_changes(empty_database_url: str, engine: Engine) -> None:
    """The no-differences check above is not vacuous: a changed type in the models would show up."""
    upgrade(empty_database_url)
    changed = MetaData(naming_convention=Base.metadata.naming_convention)
    for table in Base.metadata.tables.values():
        table.to_metadata(changed)
    changed.tables["study"].c.title.type = String(100)
    changed.tables["study"].c.created_at.type = DateTime(timezone=False)
    diffs = [d for diff in schema_diff(engine, changed) for d in (diff if isinstance(diff, list) else [diff])]
    found = {(d[0], d[2], d[3]) if d[0].startswith("modify_") else (d[0], str(d[1])) for d in diffs}
    expected = {("modify_type", "study", "title")}
    if engine.dialect.name == "postgresql":  # naive vs aware timestamps are different types there
        expected.add(("modify_type", "study", "created_at"))
    assert found == expected
    assert isinstance(models.Study.__table__.c.created_at.type, models.TZDateTime)


def test_downgrade_to_base_and_upgrade_again(empty_database_url: str, engine: Engine) -> None:
    upgrade(empty_database_url)
    head = current_revision(engine)
    assert head == ScriptDirectory.from_config(alembic_config(empty_database_url)).get_current_head()

    downgrade(empty_database_url, "base")
    assert tables(engine) == set()
    assert current_revision(engine) is None

    upgrade(empty_database_url)
    assert tables(engine) == MODEL_TABLES
    assert current_revision(engine) == head
    assert schema_diff(engine) == []


def test_every_revision_steps_down_and_up(empty_database_url: str, engine: Engine) -> None:
    """Each migration's downgrade undoes exactly its upgrade (a 'stairway' over the history)."""
    script = ScriptDirectory.from_config(alembic_config(empty_database_url))
    for revision in reversed(list(script.walk_revisions())):
        before = tables(engine)
        upgrade(empty_database_url, revision.revision)
        after_upgrade = tables(engine)
        downgrade(empty_database_url, "-1")
        assert tables(engine) == before
        upgrade(empty_database_url, revision.revision)
        assert tables(engine) == after_upgrade
        assert current_revision(engine) == revision.revision
    assert schema_diff(engine) == []


def test_migration_files_are_dated() -> None:
    names = sorted(path.name for path in (MIGRATIONS / "versions").glob("*.py"))
    assert names
    for name in names:
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}_[a-z0-9_]+\.py", name), name


def _table_as_migrated(connection: Any, model: Any) -> Table:
    """The model's table with only the columns the database has at its current revision (their types kept)."""
    present = {column["name"] for column in inspect(connection).get_columns(model.__tablename__)}
    return Table(model.__tablename__, MetaData(),
                 *[column._copy() for column in model.__table__.columns if column.name in present])


def test_ended_sessions_get_finished_at(empty_database_url: str, engine: Engine) -> None:
    """0004 fills finished_at of ended sessions that lack it: abandoned ones from their abandoned event (else their
    last-seen time), others from their last-seen time; set times and active sessions are left alone."""
    upgrade(empty_database_url, "0003")
    t = [datetime(2026, 11, 30, hour, tzinfo=UTC) for hour in range(6)]
    # Core inserts of the columns that exist at 0003 (the models may have more by now, with defaults).
    with engine.begin() as connection:
        participant = _table_as_migrated(connection, models.Participant)
        study_id = connection.execute(insert(models.Study).values(slug="s", title="S")).inserted_primary_key[0]
        version_id = connection.execute(insert(models.StudyVersion).values(
            study_id=study_id, version=1, config={}, config_hash="h")).inserted_primary_key[0]
        ids = {}
        for name, status, finished in (("swept", "abandoned", None), ("no_event", "abandoned", None),
                                       ("declined", "declined", None), ("completed", "completed", t[5]),
                                       ("active", "active", None)):
            ids[name] = connection.execute(insert(participant).values(
                public_id=name, token_hash=name, study_id=study_id, study_version_id=version_id, status=status,
                step=CONSENT, last_seen_at=t[1], finished_at=finished)).inserted_primary_key[0]
        connection.execute(insert(models.Event).values(study_id=study_id, participant_id=ids["swept"],
                                                       kind="abandoned", server_monotonic_s=0.0, created_at=t[3]))
    upgrade(empty_database_url)
    with make_sessionmaker(engine)() as session:
        finished = dict(session.execute(select(models.Participant.public_id, models.Participant.finished_at)).all())
    assert finished == {"swept": t[3], "no_event": t[1], "declined": t[1], "completed": t[5], "active": None}
