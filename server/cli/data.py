"""``trustlab check-data``: stored values that exports cannot write as they are, listed and (``--repair``) repaired."""

from __future__ import annotations

from typing import Annotated

import typer

from server.cli.common import DatabaseOpt, cli_settings, database_session


def register(app: typer.Typer) -> None:
    app.command("check-data")(check_data)


def check_data(repair: Annotated[bool, typer.Option(help="Store each value in its repaired form (as exports write "
                                                          "it), with an audit line per value.")] = False,
               database_url: DatabaseOpt = None) -> None:
    """List the values participants stored that are not standard JSON or UTF-8 (lone surrogates, NaN or Infinity,
    nesting past 32 levels): study, participant, table.column, row, problem. Exports write them repaired
    (surrogate -> U+FFFD, NaN/Infinity -> null, too deep -> a marker string); --repair stores that form.

    Exit code 0 when nothing is wrong (or all was repaired), 1 when problems were found and not repaired."""
    from server.services.data_check import find_problems
    from server.services.data_check import repair as repair_value

    settings = cli_settings(database_url=database_url)
    with database_session(settings) as session:
        found = list(find_problems(session))
        for problem in found:
            typer.echo(problem.line())
            if repair:
                repair_value(session, problem)
    if not found:
        typer.echo("no problems found: every stored value can be exported as it is")
        return
    if repair:
        typer.echo(f"{len(found)} values repaired (audit action data.repair)")
        return
    typer.echo(f"{len(found)} values that exports write repaired; run with --repair to store the repaired form",
               err=True)
    raise typer.Exit(1)
