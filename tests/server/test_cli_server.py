"""Server-side commands: migrate, admin-token, export."""

import csv

from fastapi.testclient import TestClient
from typer.testing import CliRunner

from server.cli import app
from server.main import create_app
from server.settings import Settings
from tests.server.factories import join, make_client, make_study

runner = CliRunner()


def test_admin_token_is_created_once_and_rotates(tmp_path):
    url = f"sqlite:///{tmp_path / 'a.db'}"
    assert runner.invoke(app, ["migrate", "--database-url", url]).exit_code == 0
    first = runner.invoke(app, ["admin-token", "--database-url", url])
    assert first.exit_code == 0 and first.stdout.startswith("tla_")
    again = runner.invoke(app, ["admin-token", "--database-url", url])
    assert "already exists" in again.stdout
    rotated = runner.invoke(app, ["admin-token", "--rotate", "--database-url", url]).stdout.strip()
    client = TestClient(create_app(Settings(database_url=url, world_loop=False)))
    assert client.get("/api/admin/studies",
                      headers={"Authorization": f"Bearer {first.stdout.strip()}"}).status_code == 401
    assert client.get("/api/admin/studies", headers={"Authorization": f"Bearer {rotated}"}).status_code == 200


def test_export_command_writes_the_files(database_url, tmp_path):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    join(client, PROLIFIC_PID="e1")
    result = runner.invoke(app, ["export", "s1", "--out", str(tmp_path / "out"), "--database-url", database_url])
    assert result.exit_code == 0, result.output
    with open(tmp_path / "out" / "participants.csv", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["external_id"] for r in rows] == ["e1"]
    assert {"trials.csv", "surveys.csv", "events.csv", "codebook.csv"} <= {p.name for p in (tmp_path / "out").iterdir()}
    missing = runner.invoke(app, ["export", "nope", "--out", str(tmp_path / "x"), "--database-url", database_url])
    assert missing.exit_code == 2 and "nope" in missing.output
