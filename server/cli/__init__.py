"""The ``trustlab`` command line (SPEC §9): ``app``, the console script's entry point.

Imports go one way: this package imports its command groups (``analysis``, ``server``, ``deploy``, ``data``), which
share ``common``; they import the rest of trustlab (``server.launch`` serves the app, ``server.workers`` runs a group),
and nothing outside the package imports it back.
"""

from __future__ import annotations

import typer

from server.cli import analysis, data, languages, replay, server

app = typer.Typer(help="trustlab: run trust-in-autonomy experiments and close the loop from data to robot policy.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)

analysis.register(app)  # the analysis commands first, then the server ones, as in 'trustlab --help'
server.register(app)
data.register(app)
replay.register(app)
languages.register(app)
