"""``trustlab serve``, ``migrate``, ``admin-token``, ``export`` and ``bots``: the server-side commands."""

from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer

from experiment.iohmm import load_model
from experiment.templates import demo
from server.settings import Settings

DEMO_SLUG = "demo"


def _settings(host: str | None = None, port: int | None = None, database_url: str | None = None) -> Settings:
    overrides = {k: v for k, v in {"host": host, "port": port, "database_url": database_url}.items() if v is not None}
    return Settings(**overrides)


DatabaseOpt = Annotated[str | None, typer.Option(help="SQLAlchemy URL (default: TRUSTLAB_DATABASE_URL or sqlite:///trustlab.db).")]


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command()(migrate)
    app.command("admin-token")(admin_token)
    app.command()(export)
    app.command()(bots)


def serve(host: Annotated[str | None, typer.Option(help="Interface to listen on (default 127.0.0.1).")] = None,
          port: Annotated[int | None, typer.Option(help="Port (default 8000).")] = None,
          database_url: DatabaseOpt = None) -> None:
    """Migrate the database, create the demo study if there is none, print the links and serve."""
    import uvicorn

    from server.main import create_app
    from server.migrate import upgrade
    from server.models import Study
    from server.services.admin import ensure_admin_token
    from server.services.studies import create_study

    settings = _settings(host, port, database_url)
    upgrade(settings.database_url)
    app = create_app(settings)
    with app.state.sessionmaker.begin() as session:
        token = ensure_admin_token(session)
        if session.query(Study).count() == 0:
            create_study(session, demo(), DEMO_SLUG)
        slugs = [s.slug for s in session.query(Study).order_by(Study.id)]
    base = settings.base_url()
    typer.echo(f"trustlab is serving {settings.database_url}")
    for slug in slugs:
        typer.echo(f"  participant link ({slug}): {base}/join/{slug}   (API: POST {base}/api/studies/{slug}/join)")
    typer.echo(f"  admin:  {base}/admin   API docs: {base}/docs")
    if token:
        typer.echo(f"  admin token (shown once, store it now): {token}")
    else:
        typer.echo("  admin token: already set; 'trustlab admin-token --rotate' issues a new one and revokes the old")
    sys.stdout.flush()
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="warning")


def migrate(database_url: DatabaseOpt = None) -> None:
    """Apply the database migrations (Alembic upgrade head)."""
    from server.migrate import upgrade

    settings = _settings(database_url=database_url)
    upgrade(settings.database_url)
    typer.echo(f"database at {settings.database_url} is up to date")


def admin_token(rotate: Annotated[bool, typer.Option(help="Revoke every admin token and print a new one.")] = False,
                database_url: DatabaseOpt = None) -> None:
    """Create the admin token if there is none, or rotate it; tokens are stored hashed and shown once."""
    from server.migrate import upgrade
    from server.models import utcnow
    from server.services.admin import ensure_admin_token, rotate_admin_token

    settings = _settings(database_url=database_url)
    upgrade(settings.database_url)
    with _session(settings) as session:
        token = rotate_admin_token(session, utcnow()) if rotate else ensure_admin_token(session)
    if token is None:
        typer.echo("an admin token already exists; use --rotate to replace it (the old one stops working)")
    else:
        typer.echo(token)


@contextmanager
def _session(settings: Settings):
    from server.db import make_engine, make_sessionmaker

    engine = make_engine(settings.database_url)
    try:
        with make_sessionmaker(engine).begin() as session:
            yield session
    finally:
        engine.dispose()


def export(study: Annotated[str, typer.Argument(help="Study slug.")],
           out: Annotated[Path, typer.Option(help="Directory for the CSV files and the codebook.")],
           database_url: DatabaseOpt = None) -> None:
    """Write trials.csv, surveys.csv, participants.csv, events.csv and codebook.csv of a study."""
    from server.db import make_engine, make_sessionmaker
    from server.errors import AppError
    from server.services.exports import export_study

    settings = _settings(database_url=database_url)
    engine = make_engine(settings.database_url)
    try:
        counts = export_study(make_sessionmaker(engine), study, out)
    except AppError as exc:
        typer.echo(f"error: {exc.detail}", err=True)
        raise typer.Exit(2) from None
    finally:
        engine.dispose()
    for name, rows in counts.items():
        typer.echo(f"  {name}: {rows} rows")
    typer.echo(f"written to {out}")


def bots(url: Annotated[str, typer.Argument(help="Base URL of a running trustlab server, e.g. http://127.0.0.1:8000")],
         study: Annotated[str, typer.Option(help="Study slug.")],
         participants: Annotated[int, typer.Option(min=1, max=100_000, help="How many simulated participants.")],
         concurrency: Annotated[int, typer.Option(min=1, max=2000, help="How many run at once.")] = 4,
         model: Annotated[str, typer.Option(help="Model JSON the bots' decisions follow, or 'paper'.")] = "paper",
         seed: Annotated[int, typer.Option(min=0, help="Seed of the bots' decisions.")] = 0,
         as_json: Annotated[bool, typer.Option("--json", help="Print the summary as one JSON object.")] = False) -> None:
    """Simulated participants over HTTP and websocket; exits 1 if any bot failed."""
    import httpx
    from websockets.sync.client import connect

    from server.bots import run_bots

    params = load_model(model)
    base = url.rstrip("/")
    ws_base = "ws" + base[4:] if base.startswith("http") else base

    @contextmanager
    def socket(path: str):
        with connect(ws_base + path, open_timeout=10, max_size=2**20) as ws:
            yield _SyncSocket(ws)

    summary = run_bots(lambda: httpx.Client(base_url=base, timeout=30), socket, study, params,
                       participants=participants, concurrency=concurrency, seed=seed,
                       progress=None if as_json else _progress)
    if as_json:
        typer.echo(json.dumps(summary.to_dict()))
    else:
        lat = summary.latency_ms
        typer.echo(f"\n{summary.completed}/{summary.participants} completed, {len(summary.errors)} errors, "
                   f"{summary.trials} trials in {summary.seconds:.1f} s")
        if lat:
            typer.echo(f"participant API latency ms: p50 {lat['p50']:.1f}  p95 {lat['p95']:.1f}  p99 {lat['p99']:.1f}  max {lat['max']:.1f}")
        for error in summary.errors[:20]:
            typer.echo(f"  {error}", err=True)
    if summary.errors:
        raise typer.Exit(1)


class _SyncSocket:
    def __init__(self, ws):
        self.ws = ws

    def send_text(self, data: str) -> None:
        self.ws.send(data)

    def receive_text(self) -> str:
        message = self.ws.recv(timeout=30)
        return message if isinstance(message, str) else message.decode()


def _progress(done: int, total: int) -> None:
    sys.stderr.write(f"\rparticipants: {done}/{total}")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()
