"""``trustlab replay``: a participant's trials rebuilt from the database as 3D replays that play offline."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from server.cli.common import DatabaseOpt, cli_settings, database_session, refuse


def register(app: typer.Typer) -> None:
    app.command()(replay)


def replay(study: Annotated[str, typer.Argument(help="Study slug.")],
           participant: Annotated[str, typer.Option(help="The participant's public id (as in the exports).")],
           out: Annotated[Path, typer.Option(help="Directory for the replay files.")],
           trial: Annotated[list[str] | None,
                            typer.Option(help="A trial as practice:block:trial (0:1:3 is block 1's trial 3, 1:0:2 "
                                              "practice trial 2); repeat for several. Each gets a file of its own. "
                                              "Without it: every trial, in one file.")] = None,
           database_url: DatabaseOpt = None) -> None:
    """Rebuild trials from the database alone (scene, decision window, the robot's attempt or the re-simulated
    teleoperation, camera changes) and write each as one HTML file: viser's 3D player beside the trial's timeline,
    playing offline. A whole participant is one file with every trial. A trial whose reconstruction does not reach
    its recorded outcome (e.g. a log cut short by a crash) says what is missing."""
    from server.errors import AppError
    from server.services.replay import load_trials, parse_trial
    from server.viewer.replay_page import file_label, replay_page, replay_trials

    try:
        refs = [parse_trial(text) for text in trial] if trial else None
        with database_session(cli_settings(database_url=database_url)) as session:
            loaded = load_trials(session, study, participant, refs)
    except AppError as exc:
        refuse(exc.detail)
    if not loaded.trials:
        refuse(f"participant {participant!r} has no trials yet")
    out.mkdir(parents=True, exist_ok=True)

    def progress(done: int, total: int, one) -> None:
        typer.echo(f"[{done}/{total}] {one.label}: reconstructed", err=True)

    replayed = replay_trials(loaded, progress)
    for item in replayed:
        state = "reproduced" if item.reproduced else "INCOMPLETE: " + "; ".join(item.replay.missing)
        typer.echo(f"  {item.trial.label}: {item.replay.recorded}; {state} ({len(item.recording) / 1024:.0f} KiB "
                   "recording)")
    files = ([(f"replay-{participant}-{file_label(item.trial.ref)}.html", [item]) for item in replayed] if refs
             else [(f"replay-{participant}.html", replayed)])
    for name, items in files:
        path = out / name
        path.write_text(replay_page(loaded, items), encoding="utf-8")
        typer.echo(f"written {path} ({path.stat().st_size / 1024:.0f} KiB, {len(items)} trial"
                   f"{'s' if len(items) > 1 else ''})")
