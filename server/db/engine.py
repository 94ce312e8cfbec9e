"""Database engine, declarative base and the unit-of-work session.

SQLite by default (WAL journal, synchronous=NORMAL with group commit in ``server.db.walsync``, foreign keys on, a busy
timeout so concurrent writers wait instead of failing), PostgreSQL through the same code.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import MetaData, create_engine, event
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker
from sqlalchemy.pool import QueuePool

from server import strict_json

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

SQLITE_BUSY_TIMEOUT_MS = 10_000


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


def make_engine(database_url: str, *, read_only: bool = False, **kwargs: Any) -> Engine:
    """An engine for ``database_url`` with the pragmas trustlab relies on for SQLite.

    JSON columns are written as standard JSON only (a NaN is an error, never a stored ``NaN``), and a database
    error's message leaves out the statement's parameters: they are participants' data, not the server log's.

    ``read_only`` (the 3D view process, which only reads): SQLite transactions begin deferred and never take the
    write lock (under WAL a reader neither waits for the writer nor holds it up), and any write is refused.
    """
    kwargs = {"json_serializer": strict_json.dumps, "hide_parameters": True} | kwargs
    if database_url.startswith("sqlite"):
        # One connection, handed out first come first served: every transaction takes SQLite's write lock
        # (below), so a second connection could only wait for it, in SQLite's busy handler, which polls
        # with growing sleeps and lets newcomers overtake: under load some requests then wait for seconds.
        pool = {"poolclass": QueuePool, "pool_size": 1, "max_overflow": 0,
                "pool_timeout": SQLITE_BUSY_TIMEOUT_MS / 1000}
        if ":memory:" in database_url or database_url in ("sqlite://", "sqlite+pysqlite://"):
            pool = {}
        engine = create_engine(database_url, connect_args={"check_same_thread": False,
                                                           "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000}, **pool | kwargs)
        event.listen(engine, "connect", _sqlite_pragmas)
        if read_only:
            event.listen(engine, "connect", _sqlite_query_only)
            event.listen(engine, "begin", _sqlite_begin_deferred)
        else:
            event.listen(engine, "begin", _sqlite_begin_immediate)
        return engine
    return create_engine(database_url, pool_pre_ping=True, **kwargs)


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    # Let SQLAlchemy, not the driver, manage transactions (so BEGIN IMMEDIATE below works).
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    # A commit survives kill -9; the server makes acknowledged commits survive a power cut too, with an fsync
    # of the log off the event loop (server.db.walsync). Checkpoints and the last close fsync as well.
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.close()


def _sqlite_begin_immediate(connection: Any) -> None:
    # Take the write lock at the start of every transaction: read-then-write
    # units of work then serialise instead of failing with "database is locked"
    # when two requests upgrade their read locks at once.
    connection.exec_driver_sql("BEGIN IMMEDIATE")


def _sqlite_query_only(dbapi_connection: Any, _record: Any) -> None:
    dbapi_connection.execute("PRAGMA query_only=ON")


def _sqlite_begin_deferred(connection: Any) -> None:
    connection.exec_driver_sql("BEGIN")


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)
