"""SQLite files only their owner can read, and one server per SQLite file.

The database holds the secret that participants' tokens are derived from and every participant's data, so the
database file, its -wal and -shm files (SQLite creates them with the database file's mode) and its backups are
created with mode 0600, whatever the process's umask; an existing database that others could read is made private
when it is migrated. A server holds an exclusive lock on ``<database>.lock`` for as long as it runs: a second
server on the same file (whose requests would take turns with the first's without either knowing, and whose
group commit and sweeper would run twice) refuses to start and names the process that serves it.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import IO

from sqlalchemy.engine import make_url

PRIVATE_MODE = 0o600
#: The files SQLite keeps beside a database in WAL mode (and in rollback-journal mode).
SQLITE_COMPANIONS = ("-wal", "-shm", "-journal")


class DatabaseInUse(RuntimeError):
    """Another server holds the database's lock (the message names the file and the process)."""


def sqlite_file(database_url: str) -> Path | None:
    """The database file of a SQLite URL (None for PostgreSQL or an in-memory database)."""
    url = make_url(database_url)
    if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
        return None
    return Path(url.database)


def create_private(path: Path) -> None:
    """Create ``path`` empty with mode 0600 if it is missing, else make it 0600 (SQLite opens an empty file as a new
    database, and gives its companion files the database file's mode)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    os.close(os.open(path, os.O_CREAT | os.O_WRONLY, PRIVATE_MODE))
    os.chmod(path, PRIVATE_MODE)


def make_database_private(database_url: str) -> None:
    """A SQLite database's file (created if missing) and the companion files there are, mode 0600."""
    path = sqlite_file(database_url)
    if path is None:
        return
    create_private(path)
    for suffix in SQLITE_COMPANIONS:
        companion = path.with_name(path.name + suffix)
        if companion.exists():
            os.chmod(companion, PRIVATE_MODE)


def lock_database(database_url: str) -> IO[str] | None:
    """Hold ``<database>.lock`` exclusively until the returned file is closed (the process ends); None for
    PostgreSQL, which serves several servers. Raises DatabaseInUse if another process holds it."""
    path = sqlite_file(database_url)
    if path is None:
        return None
    lock_path = path.with_name(path.name + ".lock")
    create_private(lock_path)
    lock = open(lock_path, "r+", encoding="utf-8")  # noqa: SIM115 -- held open for the server's life
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = lock.read().strip() or "unknown"
        lock.close()
        raise DatabaseInUse(f"another trustlab server (process {holder}) is serving {path.resolve()}: stop it first, "
                            "or serve another database (--database-url). One server per SQLite file.") from None
    lock.truncate(0)
    lock.write(str(os.getpid()))
    lock.flush()
    return lock
