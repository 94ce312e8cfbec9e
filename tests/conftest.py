"""Shared fixtures: a migrated database template per test session, a copy per test."""

from __future__ import annotations

import os
import shutil
import time
import uuid
import weakref
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import create_engine, event, text
from sqlalchemy.engine import URL, Engine, make_url
from sqlalchemy.exc import ProgrammingError
from sqlalchemy.pool import NullPool

from server.db.migrate import upgrade


def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test an id of its own: the suite runs in two processes (pytest-xdist), which know a test by its id
    and silently run only one of several tests that share one.

    schemathesis names each operation's test ``test_api[POST /api/...]``, but under pytest 9 the id is built from
    the function's name alone (``test_api``, 45 times): it gets its name back. Any other id that is still shared
    stops the run here rather than dropping tests unseen."""
    for item in items:
        parent, _, last = item.nodeid.rpartition("::")
        if last == getattr(item, "originalname", None) and last != item.name:
            _set_nodeid(item, f"{parent}::{item.name}")
    shared = sorted(nodeid for nodeid, count in Counter(item.nodeid for item in items).items() if count > 1)
    if shared:
        raise pytest.UsageError(f"tests that share an id (pytest-xdist would run only one of each): {shared[:5]}")
    _long_files_first(items)


#: The files that take a minute or more (CI's --durations), longest first. The two test processes take whole files
#: in the order collected (``--dist loadfile --no-loadscope-reorder``): these go first, so that the run ends on short
#: files, not with one process on a long one while the other has nothing left. (xdist's own order, by number of tests,
#: put these single-test files last.)
LONG_FILES = (
    "tests/server/test_fuzz.py",
    "tests/browser/test_participant_flow.py",
    "tests/server/test_kill_repeatedly.py",
    "tests/server/test_workers.py",
    "tests/browser/test_admin.py",
    "tests/server/test_loop_cli.py",
    "tests/browser/test_scene_proof.py",
    "tests/browser/test_viewer.py",
    "tests/browser/test_teleop_person.py",
    "tests/server/test_replay_kill.py",
    "tests/browser/test_replay.py",
    "tests/server/test_hostile_sockets.py",
)


def _long_files_first(items: list[pytest.Item]) -> None:
    """The files of ``LONG_FILES`` first, in its order; every other file after them as collected. A file's tests
    stay together and in their order (a stable sort by file)."""
    rank = {path: i for i, path in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.partition("::")[0], len(LONG_FILES)))


def _set_nodeid(item: pytest.Item, nodeid: str) -> None:
    if hasattr(item, "_id"):  # pytest >= 9: a structured id
        from _pytest.nodes import NodeId

        item._id = NodeId.parse(nodeid)
    else:
        item._nodeid = nodeid


#: Set to a PostgreSQL URL (e.g. by .ci/run) to run the server tests against PostgreSQL too.
#: Its role needs CREATEDB; each test gets a new database (PostgreSQL >= 13 for DROP ... WITH (FORCE)).
POSTGRES_URL = os.environ.get("TRUSTLAB_TEST_POSTGRES_URL")
BACKENDS = ["sqlite"] + (["postgresql"] if POSTGRES_URL else [])


#: Every engine that has connected (the apps under test make their own; TestClient without ``with``
#: never runs the app's shutdown, which would dispose of it).
_ENGINES: weakref.WeakSet[Engine] = weakref.WeakSet()


@event.listens_for(Engine, "engine_connect")
def _remember_engine(connection: Any) -> None:
    _ENGINES.add(connection.engine)


def _dispose_engines(database: str) -> None:
    """Close the pooled connections to ``database`` before it is dropped.

    Otherwise the server ends them and the driver's connection objects, still "open" on the
    client side, raise ResourceWarning (an error under ``filterwarnings = error``) when collected.
    """
    for engine in list(_ENGINES):
        if engine.url.database == database:
            engine.dispose()


def postgres_database_url(name: str) -> str:
    """``TRUSTLAB_TEST_POSTGRES_URL`` pointing at database ``name`` instead (host, port and query kept)."""
    assert POSTGRES_URL is not None
    url: URL = make_url(POSTGRES_URL).set(database=name)
    return url.render_as_string(hide_password=False)


def _postgres_admin() -> Engine:
    assert POSTGRES_URL is not None
    return create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT", poolclass=NullPool)


def create_postgres_database(*, template: str | None = None) -> str:
    """A new, empty (or copied from ``template``) PostgreSQL database; returns its name."""
    name = f"trustlab_test_{uuid.uuid4().hex[:12]}"
    admin = _postgres_admin()
    try:
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"' + (f' TEMPLATE "{template}"' if template else "")))
    finally:
        admin.dispose()
    return name


#: Tries to drop a test database. WITH (FORCE) may not end an autovacuum worker visiting the new database (PostgreSQL
#: 15 refuses: "must be a member of the role whose process is being terminated"); the worker is done in moments.
DROP_TRIES, DROP_RETRY_S = 20, 0.25


def drop_postgres_database(name: str) -> None:
    _dispose_engines(name)
    admin = _postgres_admin()
    try:
        for attempt in range(DROP_TRIES):
            try:
                with admin.connect() as conn:
                    conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
                return
            except ProgrammingError as exc:
                if "pg_signal_backend" not in str(exc) or attempt == DROP_TRIES - 1:
                    raise
                time.sleep(DROP_RETRY_S)
    finally:
        admin.dispose()


@pytest.fixture(autouse=True)
def _plan_attempts_in_process(monkeypatch: pytest.MonkeyPatch) -> None:
    """Apps under test (and the servers a test starts, which inherit the environment) plan attempts in-process
    unless a test asks for the helper process: a TestClient used without ``with`` never runs the app's shutdown,
    which stops the helper. Fixtures wider than a test do not see this: ``make_client`` (tests/server/factories.py)
    passes the same setting explicitly."""
    monkeypatch.setenv("TRUSTLAB_PLANNER_PROCESSES", "0")


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("db") / "template.db"
    upgrade(f"sqlite:///{path}")
    return path


@pytest.fixture(scope="session")
def postgres_template() -> Iterator[str]:
    """A PostgreSQL database migrated once per session; each test gets a copy (CREATE DATABASE ... TEMPLATE)."""
    name = create_postgres_database()
    try:
        upgrade(postgres_database_url(name))
        yield name
    finally:
        drop_postgres_database(name)


@pytest.hookimpl(tryfirst=True)  # before pytest reads the test's parametrize marks and the fixture's own params
def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """A module whose subject is not storage (its requests go through code that the other modules run on both
    databases) says so with ``STORAGE_INCIDENTAL = True``, under a comment saying why: its tests take the
    ``database_url`` of SQLite only. The PostgreSQL runs are kept for what differs between the two: transactions and
    locks, crashes, migrations, the exports' and reports' queries, deletion, the stored documents."""
    if "database_url" in metafunc.fixturenames and getattr(metafunc.module, "STORAGE_INCIDENTAL", None):
        metafunc.definition.add_marker(pytest.mark.parametrize("database_url", ["sqlite"], indirect=True))


@pytest.fixture(params=BACKENDS)
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh, migrated database for one test (SQLite copy, or a new PostgreSQL database)."""
    if request.param == "sqlite":
        path = tmp_path / "trustlab.db"
        shutil.copy(request.getfixturevalue("sqlite_template"), path)
        yield f"sqlite:///{path}"
        return
    name = create_postgres_database(template=request.getfixturevalue("postgres_template"))
    try:
        yield postgres_database_url(name)
    finally:
        drop_postgres_database(name)


@pytest.fixture(params=BACKENDS)
def empty_database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh database with no tables at all (for the migration tests)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'empty.db'}"
        return
    name = create_postgres_database()
    try:
        yield postgres_database_url(name)
    finally:
        drop_postgres_database(name)
