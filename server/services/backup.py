"""Online backup of a SQLite database, safe while the server runs and writes (``trustlab backup``).

SQLite's backup API (``sqlite3.Connection.backup``) copies the database page by
page. It runs here in one step, inside one read transaction: in WAL mode (which
``server.db.engine`` sets) that is a snapshot of the last commit before it began, and
writers are not blocked while it is taken. A copy made in several steps would
restart whenever the server commits, and might never finish under load.

The copy is written next to the target under a temporary name, checked with
``PRAGMA integrity_check``, switched to a single-file journal mode, and only then
renamed to the target, so the target is either absent or a whole, checked backup.
PostgreSQL databases are backed up with PostgreSQL's own tools (``pg_dump``).
"""

from __future__ import annotations

import os
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy.engine import make_url

from server.db.engine import SQLITE_BUSY_TIMEOUT_MS
from server.errors import Conflict, Invalid, NotFound
from server.private_files import create_private


@dataclass(frozen=True)
class Backup:
    path: Path
    bytes: int
    seconds: float


def sqlite_path(database_url: str) -> Path | None:
    """The database file of a SQLite URL; None for any other database."""
    url = make_url(database_url)
    if url.get_backend_name() != "sqlite":
        return None
    if not url.database or url.database == ":memory:":
        raise Invalid(f"{database_url} is an in-memory database; there is no file to back up")
    return Path(url.database)


def backup_sqlite(source: Path, out: Path) -> Backup:
    """Copy the SQLite database ``source`` to ``out`` (which must not exist yet)."""
    if not source.is_file():
        raise NotFound(f"no SQLite database at {source}")
    if out.exists():
        raise Conflict(f"{out} exists already; choose a new file name (a backup never overwrites one)")
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    partial.unlink(missing_ok=True)
    create_private(partial)  # mode 0600: the copy holds the token secret as the database does
    start = time.perf_counter()
    try:
        with _connect(source) as src, _connect(partial) as dst:
            src.backup(dst)  # pages=-1: one step, one snapshot
            problems = [row[0] for row in dst.execute("PRAGMA integrity_check")]
            if problems != ["ok"]:
                raise Invalid(f"the copy of {source} failed its integrity check: {'; '.join(problems[:5])}")
            dst.execute("PRAGMA journal_mode=DELETE")  # one self-contained file (the server turns WAL on again)
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return Backup(out, out.stat().st_size, time.perf_counter() - start)


def _connect(path: Path) -> closing[sqlite3.Connection]:
    # closing(): a sqlite3 connection used as a context manager only commits, it does not close
    return closing(sqlite3.connect(path, timeout=SQLITE_BUSY_TIMEOUT_MS / 1000))
