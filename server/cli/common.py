"""What the command groups share: the database option, settings, the session, the one-line error, progress bars."""

from __future__ import annotations

import sys
from collections.abc import Callable
from contextlib import contextmanager
from typing import Annotated, Any, NoReturn

import typer

from server.settings import Settings

DatabaseOpt = Annotated[str | None, typer.Option(help="SQLAlchemy URL (default: TRUSTLAB_DATABASE_URL or sqlite:///trustlab.db).")]


def cli_settings(host: str | None = None, port: int | None = None, database_url: str | None = None) -> Settings:
    given = {"host": host, "port": port, "database_url": database_url}
    overrides: dict[str, Any] = {k: v for k, v in given.items() if v is not None}
    return Settings(**overrides)


def refuse(message: str) -> NoReturn:
    """Bad input: a one-line error and exit code 2, before anything starts."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


@contextmanager
def database_session(settings: Settings):
    from server.db.engine import make_engine, make_sessionmaker

    engine = make_engine(settings.database_url)
    try:
        with make_sessionmaker(engine).begin() as session:
            yield session
    finally:
        engine.dispose()


def progress_bar(width: int = 30) -> Callable[[str, int, int], None]:
    """A one-line progress bar on stderr, redrawn in place: ``bar(label, done, total)``."""
    def draw(label: str, done: int, total: int) -> None:
        filled = width * done // max(total, 1)
        sys.stderr.write(f"\r{label}: [{'#' * filled}{'.' * (width - filled)}] {done}/{total}")
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()
    return draw


def labelled_progress(label: str) -> Callable[[int, int], None]:
    bar = progress_bar()
    return lambda done, total: bar(label, done, total)
