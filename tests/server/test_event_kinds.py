"""The event log's kinds (``experiment.events``): every kind the server writes is registered and fits the log's
column, and a page's kind whose stored form (``client.<kind>``) would not fit is refused."""

from __future__ import annotations

import ast
from pathlib import Path

from sqlalchemy import create_engine, select

from experiment.events import CLIENT_KIND_LENGTH, KIND_LENGTH, EventKind, client_kind
from server.models import Event
from tests.server.factories import join, make_client, make_study

SERVER = Path(__file__).resolve().parents[2] / "server"


def logged_kinds() -> list[tuple[str, ast.expr]]:
    """Where ``server/`` calls ``log_event``, and the kind it passes."""
    found = []
    for path in sorted(SERVER.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and len(node.args) >= 4 and \
                    getattr(node.func, "id", getattr(node.func, "attr", None)) == "log_event":
                found.append((f"{path.relative_to(SERVER.parent)}:{node.lineno}", node.args[3]))
    return found


def test_every_kind_the_server_logs_is_registered_and_fits_the_log():
    kinds = logged_kinds()
    assert len(kinds) >= len(EventKind)
    for where, kind in kinds:
        match kind:
            case ast.Attribute(value=ast.Name(id="EventKind"), attr=name):
                assert name in EventKind.__members__, where
            case ast.Constant(value=str(value)):
                assert value in set(EventKind), (where, value)
            case _:
                raise AssertionError(f"{where}: log_event's kind is not EventKind.X: {ast.unparse(kind)}")
    assert max(len(kind) for kind in EventKind) <= KIND_LENGTH


def test_a_page_kind_whose_stored_form_would_not_fit_the_log_is_refused(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    token = join(client)["token"]
    longest = "k" * CLIENT_KIND_LENGTH
    for kind, status in ((longest + "k", 422), (longest, 200)):
        assert client.post(f"/api/p/{token}/events", json={"events": [{"kind": kind}]}).status_code == status, kind
    engine = create_engine(database_url)
    try:
        with engine.connect() as connection:
            stored = connection.scalars(select(Event.kind).where(Event.kind.startswith("client."))).all()
    finally:
        engine.dispose()
    assert stored == [client_kind(longest)] and len(stored[0]) == KIND_LENGTH
