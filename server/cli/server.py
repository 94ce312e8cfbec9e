"""``trustlab serve``, ``worker``, ``migrate``, ``admin-token``, ``export``, ``backup``, ``bots`` and ``report``:
the server-side commands (``deploy`` is in server.cli.deploy)."""

from __future__ import annotations

import contextlib
import json
import sys
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from sqlalchemy.engine import make_url

from experiment.iohmm import load_model
from experiment.templates import demo
from server.cli.common import DatabaseOpt, cli_settings, database_session, labelled_progress, refuse
from server.cli.deploy import deploy
from server.launch import run_server
from server.settings import Settings

if TYPE_CHECKING:
    from server.workers import WorkerGroup

DEMO_SLUG = "demo"


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command()(worker)
    app.command()(migrate)
    app.command("admin-token")(admin_token)
    app.command()(export)
    app.command()(backup)
    app.command()(bots)
    app.command()(deploy)  # server.cli.deploy
    app.command()(report)


def serve(host: Annotated[str | None, typer.Option(help="Interface to listen on (default 127.0.0.1).")] = None,
          port: Annotated[int | None, typer.Option(help="Port (default 8000).")] = None,
          database_url: DatabaseOpt = None,
          workers: Annotated[int, typer.Option(min=1, max=64, help="Server processes behind nginx (PostgreSQL "
                                               "only; see server/workers.py). Default 1: one process, no nginx.")] = 1,
          workers_at: Annotated[str | None, typer.Option(help="Run nginx alone, in front of workers that 'trustlab "
                                                         "worker' runs elsewhere: HOST:PORT,HOST:PORT,... (the first "
                                                         "is worker 0, the primary).")] = None) -> None:
    """Migrate the database, create the demo study if there is none, print the links and serve."""
    from server.private_files import DatabaseInUse, lock_database
    from server.workers import GroupError, check_group

    if workers_at is not None:
        if workers > 1 or database_url is not None:
            refuse("--workers-at runs nginx alone, in front of workers started with 'trustlab worker': give it "
                    "without --workers and --database-url (the workers use the database, nginx does not)")
        _serve_nginx_alone(cli_settings(host, port), workers_at)
        return
    settings = cli_settings(host, port, database_url)
    nginx = None
    if workers > 1:
        try:
            nginx = check_group(settings, workers)
        except GroupError as exc:
            refuse(str(exc))
    try:  # held while serving (a group runs on PostgreSQL only: nothing to lock)
        database_lock = lock_database(settings.database_url)
    except DatabaseInUse as exc:
        refuse(str(exc))
    with database_lock or contextlib.nullcontext():
        _migrate_and_serve(settings, workers, nginx)


def _migrate_and_serve(settings: Settings, workers: int, nginx: str | None) -> None:
    from server.db.migrate import upgrade
    from server.workers import WorkerGroup

    upgrade(settings.database_url)
    links = _prepare(settings)
    if nginx is None:
        from server.main import create_app

        app = create_app(settings)
        _print_links(settings, *links)
        run_server(app, host=settings.host, port=settings.port)
        return
    group = WorkerGroup(settings, nginx, local=workers, echo=lambda line: typer.echo(line, err=True))
    _start(group)
    typer.echo(f"{workers} workers behind nginx (sessions stick to a worker; admin and joins on worker 0)")
    _print_links(settings, *links)
    raise typer.Exit(group.supervise())


def _serve_nginx_alone(settings: Settings, workers_at: str) -> None:
    """``serve --workers-at``: nginx in front of workers on other machines; the database is theirs, not nginx's."""
    from server.workers import GroupError, WorkerGroup, find_nginx, worker_addresses

    try:
        addresses = worker_addresses(workers_at)
        nginx = find_nginx()
    except GroupError as exc:
        refuse(str(exc))
    group = WorkerGroup(settings, nginx, remote=addresses, echo=lambda line: typer.echo(line, err=True))
    _start(group)
    typer.echo(f"nginx on {settings.host}:{settings.port} in front of {len(addresses)} workers: "
               + ", ".join(f"{i} at {a}" for i, a in enumerate(addresses))
               + " (sessions stick to a worker; admin and joins on worker 0, which printed the links and admin token)")
    sys.stdout.flush()
    raise typer.Exit(group.supervise())


def _start(group: WorkerGroup) -> None:
    """Start the group's processes, or exit 1 with the reason they did not start."""
    from server.workers import GroupError

    try:
        group.start()
    except GroupError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None


def worker(index: Annotated[int, typer.Option(min=0, max=63, help="This worker's index in the group: 0 is the "
                                              "primary (admin API, joins, background jobs; it migrates the "
                                              "database).")],
           port: Annotated[int, typer.Option(min=1, max=65535, help="TCP port nginx reaches this worker on.")],
           public_url: Annotated[str | None, typer.Option(help="The address participants reach, nginx's (default: "
                                                          "TRUSTLAB_PUBLIC_URL): the links the workers hand out.")
                                 ] = None,
           host: Annotated[str, typer.Option(help="Interface to listen on: one nginx reaches.")] = "127.0.0.1",
           trusted_proxy: Annotated[list[str] | None, typer.Option(help="nginx's address (repeat for several): only "
                                                                   "its X-Forwarded-For is believed. Default on a "
                                                                   "loopback --host: the loopback address.")] = None,
           database_url: DatabaseOpt = None) -> None:
    """One worker of a group across machines, on a TCP address behind 'trustlab serve --workers-at' (nginx)."""
    from sqlalchemy.exc import SQLAlchemyError

    from server.db.migrate import revisions, upgrade
    from server.workers import GroupError, check_postgres, trusted_proxies

    options = {"database_url": database_url, "public_url": public_url}
    given: dict[str, Any] = {name: value for name, value in options.items() if value}
    settings = Settings(worker_index=index, **given)
    try:
        check_postgres(settings)
        trusted = trusted_proxies(host, trusted_proxy or [])
        if not settings.public_url:
            raise GroupError("a worker needs --public-url (or TRUSTLAB_PUBLIC_URL), nginx's address as participants "
                             "reach it: the links in join responses and on the admin page point there, not at a worker")
        if index > 0:  # the primary migrates; two workers migrating at once would race
            try:
                current, head = revisions(settings.database_url)
            except SQLAlchemyError as exc:
                raise GroupError(f"cannot reach the database ({type(exc).__name__}): is --database-url right, and "
                                 "does PostgreSQL accept connections from this machine?") from None
            if current != head:
                raise GroupError(f"the database is at revision {current or 'none'}, this trustlab needs {head}: start "
                                 "worker 0 first (it migrates the database), or run 'trustlab migrate'")
    except GroupError as exc:
        refuse(str(exc))
    from server.main import create_app

    links = None
    if settings.primary:
        upgrade(settings.database_url)
        links = _prepare(settings)
    app = create_app(settings)
    typer.echo(f"worker {index} on {host}:{port} behind nginx; X-Forwarded-For believed from {', '.join(trusted)}"
               + (" (the primary: admin API, joins, background jobs)" if settings.primary else ""))
    if links is not None:
        _print_links(settings, *links)
    sys.stdout.flush()
    run_server(app, host=host, port=port, trusted_proxies=trusted)


def _prepare(settings: Settings) -> tuple[str | None, list[tuple[str, str]]]:
    """The admin token if it was just created, and every study's slug and status (the demo study created, open, if
    there is none)."""
    from server.models import Study
    from server.services.admin import ensure_admin_token
    from server.services.studies import create_study

    with database_session(settings) as session:
        token = ensure_admin_token(session)
        if session.query(Study).count() == 0:
            create_study(session, demo(), DEMO_SLUG, status="open")  # the demo is for trying at once
        return token, [(s.slug, s.status) for s in session.query(Study).order_by(Study.id)]


def _print_links(settings: Settings, token: str | None, studies: list[tuple[str, str]]) -> None:
    base = settings.base_url()
    # The URL without its password: this line ends up in terminals, service logs and screenshots.
    typer.echo(f"trustlab is serving {make_url(settings.database_url).render_as_string(hide_password=True)}")
    for slug, status in studies:
        note = {"open": "", "closed": "   [closed: nobody new can join until it is reopened on the admin page]"}.get(
            status, f"   [{status}: nobody can join until it is opened on the admin page]")
        typer.echo(f"  participant link ({slug}): {base}/join/{slug}   (API: POST {base}/api/studies/{slug}/join)"
                   + note)
    typer.echo(f"  admin page: {base}/admin   (log in with the admin token; API docs: {base}/docs)")
    if token:
        typer.echo(f"  admin token (shown once, store it now): {token}")
    else:
        typer.echo("  admin token: already set; 'trustlab admin-token --rotate' issues a new one and revokes the old")
    sys.stdout.flush()


def migrate(database_url: DatabaseOpt = None) -> None:
    """Apply the database migrations (Alembic upgrade head)."""
    from server.db.migrate import upgrade

    settings = cli_settings(database_url=database_url)
    upgrade(settings.database_url)
    typer.echo(f"database at {settings.database_url} is up to date")


def admin_token(rotate: Annotated[bool, typer.Option(help="Revoke every admin token and print a new one.")] = False,
                database_url: DatabaseOpt = None) -> None:
    """Create the admin token if there is none, or rotate it; tokens are stored hashed and shown once."""
    from server.db.migrate import upgrade
    from server.models import utcnow
    from server.services.admin import ensure_admin_token, rotate_admin_token

    settings = cli_settings(database_url=database_url)
    upgrade(settings.database_url)
    with database_session(settings) as session:
        token = rotate_admin_token(session, utcnow()) if rotate else ensure_admin_token(session)
    if token is None:
        typer.echo("an admin token already exists; use --rotate to replace it (the old one stops working)")
    else:
        typer.echo(token)


class ExportFormat(StrEnum):
    csv = "csv"
    psych_ds = "psych-ds"


def export(study: Annotated[str, typer.Argument(help="Study slug.")],
           out: Annotated[Path, typer.Option(help="Directory for the CSV files and the codebook (psych-ds: the "
                                                  "dataset's root).")],
           database_url: DatabaseOpt = None,
           include_preview: Annotated[bool, typer.Option(help="Include the experimenter's preview sessions (left "
                                                              "out by default: they are not data).")] = False,
           format_: Annotated[ExportFormat, typer.Option(
               "--format", help="csv: the CSV files, codebook and manifest; psych-ds: the same data as a Psych-DS "
                                "1.5 dataset (docs/analysis.md).")] = ExportFormat.csv,
           pseudonymise: Annotated[bool, typer.Option(help=(
               "Write the recruitment ids (external_id, the recruitment values but STUDY_ID) as salted hashes keyed "
               "per study: stable across this study's exports, different in another study's "
               "(docs/participants-rights.md)."))] = False) -> None:
    """Write trials.csv, surveys.csv, participants.csv, events.csv and codebook.csv of a study (or, with
    --format psych-ds, the study's Psych-DS dataset)."""
    from server.db.engine import make_engine, make_sessionmaker
    from server.errors import AppError
    from server.export import export_study
    from server.export.psychds import export_psychds

    write = export_psychds if format_ is ExportFormat.psych_ds else export_study
    settings = cli_settings(database_url=database_url)
    engine = make_engine(settings.database_url)
    try:
        counts = write(make_sessionmaker(engine), study, out, include_preview=include_preview,
                       pseudonymise=pseudonymise)
    except AppError as exc:
        typer.echo(f"error: {exc.detail}", err=True)
        raise typer.Exit(2) from None
    finally:
        engine.dispose()
    for name, rows in counts.items():
        typer.echo(f"  {name}: {rows} rows")
    typer.echo(f"written to {out}")


def backup(out: Annotated[Path, typer.Option(help="The backup file to write (it must not exist yet).")],
           database_url: DatabaseOpt = None) -> None:
    """Copy the SQLite database to OUT while the server runs (SQLite's online backup API); PostgreSQL: use pg_dump."""
    from sqlalchemy.engine import make_url

    from server.errors import AppError
    from server.services.backup import backup_sqlite, sqlite_path

    url = cli_settings(database_url=database_url).database_url
    try:
        source = sqlite_path(url)
        if source is None:
            shown = make_url(url).set(drivername="postgresql").render_as_string(hide_password=True)
            typer.echo(f"error: trustlab backup copies SQLite databases. Back up PostgreSQL with its own tool, "
                       f"while the server runs: pg_dump --format=custom --file=trustlab.dump '{shown}' "
                       "(restore with pg_restore)", err=True)
            raise typer.Exit(2)
        typer.echo(f"backing up {source} ...")
        done = backup_sqlite(source, out)
    except AppError as exc:
        typer.echo(f"error: {exc.detail}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"backup written to {done.path}: {done.bytes / 1e6:.1f} MB in {done.seconds:.1f} s, integrity check ok")


def report(study: Annotated[str, typer.Argument(help="Study slug, or an export directory (one with trials.csv).")],
           out: Annotated[Path, typer.Option(help="Directory for report.html, figures/, report.json, model.json "
                                                  "(and data/, the export, for a study slug).")],
           database_url: DatabaseOpt = None,
           model: Annotated[str | None,
                            typer.Option(help="Model JSON to report instead of fitting one, or 'paper'.")] = None,
           restarts: Annotated[int, typer.Option(min=1, max=10_000, help="Random restarts of the fit.")] = 20,
           seed: Annotated[int, typer.Option(min=0, help="Seed of the fit's restarts.")] = 0,
           p_high: Annotated[float | None, typer.Option(min=0.0, max=1.0, help="P(high complexity) for the policy "
                                                        "(default: the share of high-complexity trials in the "
                                                        "data).")] = None,
           include_preview: Annotated[bool, typer.Option(help="Include the experimenter's preview sessions (left "
                                                              "out by default: they are not data).")] = False,
           as_json: Annotated[bool,
                              typer.Option("--json",
                                           help="Print paths and key figures as one JSON object.")] = False) -> None:
    """The analysis report (paper §4–§5 for this study's data): HTML with PNG figures."""
    from sqlalchemy.exc import SQLAlchemyError

    from experiment.iohmm import ModelError
    from experiment.records import DataError
    from experiment.report import build_report
    from server.db.engine import make_engine, make_sessionmaker
    from server.errors import AppError
    from server.services.report import study_report
    from server.services.studies import SLUG_PATTERN

    progress = None if as_json else labelled_progress("EM iterations")
    options: dict[str, Any] = dict(model=model, restarts=restarts, seed=seed, p_high=p_high, progress=progress)
    try:
        if (Path(study) / "trials.csv").is_file():
            built = build_report(study, **options)
        elif not SLUG_PATTERN.fullmatch(study):
            raise ValueError(f"{study!r} is neither a study slug nor an export directory with trials.csv")
        else:
            engine = make_engine(cli_settings(database_url=database_url).database_url)
            try:
                built = study_report(make_sessionmaker(engine), study, out, include_preview=include_preview, **options)
            finally:
                engine.dispose()
        files = built.write(out)
    except AppError as exc:
        typer.echo(f"error: {exc.detail}", err=True)
        raise typer.Exit(2) from None
    except (DataError, ModelError, ValueError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    except SQLAlchemyError as exc:
        typer.echo(f"error: cannot read the study from the database ({type(exc).__name__}); is it migrated "
                   "('trustlab migrate') and is --database-url right?", err=True)
        raise typer.Exit(2) from None
    summary = {"report": str(files.html), "figures": [str(f) for f in files.figures],
               "report_json": str(files.key_figures),
               "model": str(files.model), "key_figures": built.key_figures()}
    if as_json:
        typer.echo(json.dumps(summary, allow_nan=False))
    else:
        typer.echo(f"report written to {files.html} ({len(files.figures)} figures in {files.html.parent / 'figures'})")


def bots(url: Annotated[str, typer.Argument(help="Base URL of a running trustlab server, e.g. http://127.0.0.1:8000")],
         study: Annotated[str, typer.Option(help="Study slug.")],
         participants: Annotated[int, typer.Option(min=1, max=100_000, help="How many simulated participants.")],
         concurrency: Annotated[int, typer.Option(min=1, max=2000, help="How many run at once.")] = 4,
         model: Annotated[str, typer.Option(help="Model JSON the bots' decisions follow, or 'paper'.")] = "paper",
         seed: Annotated[int, typer.Option(min=0, help="Seed of the bots' decisions.")] = 0,
         ramp: Annotated[float,
                         typer.Option(min=0, max=3600,
                                      help="Seconds over which the bots arrive (spread evenly).")] = 0.0,
         as_json: Annotated[bool,
                            typer.Option("--json", help="Print the summary as one JSON object.")] = False) -> None:
    """Simulated participants over HTTP and websocket; exits 1 if any bot failed."""
    from server.harness.crowd import run_remote_bots

    summary = run_remote_bots(url, study, load_model(model), participants=participants, concurrency=concurrency,
                              seed=seed, ramp_s=ramp, progress=None if as_json else _progress)
    if as_json:
        typer.echo(json.dumps(summary.to_dict()))
    else:
        lat = summary.latency_ms
        typer.echo(f"\n{summary.completed}/{summary.participants} completed, {len(summary.errors)} errors, "
                   f"{summary.trials} trials in {summary.seconds:.1f} s")
        if lat:
            typer.echo(f"participant API latency ms: p50 {lat['p50']:.1f}  p95 {lat['p95']:.1f}  p99 {lat['p99']:.1f}  "
                       f"max {lat['max']:.1f}")
        for error in summary.errors[:20]:
            typer.echo(f"  {error}", err=True)
    if summary.errors:
        raise typer.Exit(1)


def _progress(done: int, total: int) -> None:
    sys.stderr.write(f"\rparticipants: {done}/{total}")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()
