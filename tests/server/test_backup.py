"""``trustlab backup``: an online copy of the SQLite database, taken while bots run against a real server."""

from __future__ import annotations

import shutil
import sqlite3
import threading
import time
from contextlib import closing
from pathlib import Path

import pytest
from alembic.script import ScriptDirectory
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from server.cli import app as cli
from server.db.migrate import alembic_config
from server.harness.live import live_server
from server.main import create_app
from server.settings import Settings
from tests.server.factories import auth, fast_config

runner = CliRunner()
N_BOTS = 3

#: Trials in the order they were started (row id), with what a finished one recorded.
TRIALS = ("SELECT p.public_id, t.practice, t.block, t.trial, t.stage, t.human_action, t.outcome, t.experience, "
          "t.reward, t.score, t.completed_at FROM trial t JOIN participant p ON p.id = t.participant_id ORDER BY t.id")
#: Items answered per questionnaire page (a page is written in one transaction).
ANSWER_PAGES = ("SELECT p.public_id, a.context, a.questionnaire, COUNT(*) FROM answer a JOIN participant p "
                "ON p.id = a.participant_id GROUP BY p.public_id, a.context, a.questionnaire")


def rows(path: Path, query: str) -> list[tuple]:
    with closing(sqlite3.connect(path)) as conn:
        return conn.execute(query).fetchall()


def backup(url: str, out: Path) -> None:
    result = runner.invoke(cli, ["backup", "--out", str(out), "--database-url", url])
    assert result.exit_code == 0, result.output
    assert "integrity check ok" in result.output


def test_backup_during_a_bot_run_is_a_consistent_prefix(sqlite_template, tmp_path):
    live_db = tmp_path / "live.db"
    shutil.copy(sqlite_template, live_db)
    url = f"sqlite:///{live_db}"
    backups: list[Path] = []
    with live_server(url) as live:
        assert live.admin("POST", "/api/admin/studies",
                          json={"status": "open", "slug": "s1",
                                "config": fast_config().model_dump(mode="json")}).status_code == 201
        summary = {}
        bots = threading.Thread(target=lambda: summary.update(run=live.bots("s1", participants=N_BOTS)))
        bots.start()
        done_at_last_backup = 0
        while bots.is_alive():  # a backup whenever a few more trials were written since the last one
            done = rows(live_db, "SELECT COUNT(*) FROM trial WHERE stage = 'done'")[0][0]
            if done >= done_at_last_backup + 4:
                backups.append(tmp_path / f"backup-{len(backups)}.db")
                backup(url, backups[-1])
                done_at_last_backup = done
            time.sleep(0.05)
        bots.join()
        assert summary["run"].errors == [] and summary["run"].completed == N_BOTS
        backups.append(tmp_path / "backup-final.db")
        backup(url, backups[-1])
    final = rows(live_db, TRIALS)
    final_answers = {tuple(key): n for *key, n in rows(live_db, ANSWER_PAGES)}
    during = [b for b in backups[:-1] if 0 < len(rows(b, TRIALS)) < len(final)]
    assert len(during) >= 2, "no backup was taken while the bots were writing"

    head = ScriptDirectory.from_config(alembic_config(url)).get_current_head()
    for path in backups:
        assert rows(path, "PRAGMA integrity_check") == [("ok",)]
        assert rows(path, "PRAGMA journal_mode") == [("delete",)] and not Path(f"{path}-wal").exists()
        assert rows(path, "SELECT version_num FROM alembic_version") == [(head,)]
        assert_consistent_prefix(path, final, final_answers)
        # the app opens the copy as it is: the admin API lists its participants
        client = TestClient(create_app(Settings(database_url=f"sqlite:///{path}", world_loop=False)))
        listed = client.get("/api/admin/studies/s1/participants", headers=auth(live.admin_token))
        assert listed.status_code == 200 and len(listed.json()) == len(rows(path, "SELECT id FROM participant"))
        client.app.state.services.engine.dispose()
    assert rows(backups[-1], TRIALS) == final  # taken after the run: everything


def assert_consistent_prefix(path: Path, final: list[tuple], final_answers: dict[tuple, int]) -> None:
    """Every session in the copy is its final session cut at one commit: finished trials, score and step agree."""
    copy = rows(path, TRIALS)
    people = rows(path, "SELECT public_id, score, step FROM participant")
    for public_id, score, step in people:
        mine = [t for t in copy if t[0] == public_id]
        theirs = [t for t in final if t[0] == public_id]
        done = [t for t in mine if t[4] == "done"]
        assert done == theirs[:len(done)], f"{public_id}: the copy's finished trials are not the final ones"
        assert all(None not in (t[5], t[6], t[7], t[8], t[9], t[10]) for t in done), "a finished trial half written"
        assert len(mine) - len(done) <= 1 and mine[:len(done)] == done, (
            f"{public_id}: unfinished trials before finished")
        scored = [t for t in done if not t[1]]
        assert score == pytest.approx(scored[-1][9] if scored else 0.0), f"{public_id}: score and trials disagree"
        if len(mine) > len(done):  # the trial in progress is the one the step points at
            practice, block, trial = mine[-1][1:4]
            expected = '"phase": "practice"' if practice else f'"block": {block}'
            assert expected in step and theirs[len(done)][1:4] == (practice, block, trial), (public_id, step)
    for *key, n in rows(path, ANSWER_PAGES):
        assert n == final_answers[tuple(key)], f"questionnaire page {key} copied in part"


def test_backup_refuses_what_it_cannot_do_with_a_reason(tmp_path, sqlite_template):
    source = tmp_path / "db.sqlite"
    shutil.copy(sqlite_template, source)
    postgres = runner.invoke(cli, ["backup", "--out", str(tmp_path / "x"), "--database-url",
                                   "postgresql+psycopg://trustlab:secret@localhost/trustlab"])
    assert postgres.exit_code == 2 and "pg_dump" in postgres.output and "secret" not in postgres.output
    missing = runner.invoke(cli,
                            ["backup", "--out", str(tmp_path / "x"), "--database-url",
                             "sqlite:///" + str(tmp_path / "no.db")])
    assert missing.exit_code == 2 and "no SQLite database" in missing.output and not (tmp_path / "no.db").exists()
    memory = runner.invoke(cli, ["backup", "--out", str(tmp_path / "x"), "--database-url", "sqlite://"])
    assert memory.exit_code == 2 and "in-memory" in memory.output
    backup(f"sqlite:///{source}", tmp_path / "b.db")
    again = runner.invoke(cli, ["backup", "--out", str(tmp_path / "b.db"), "--database-url", f"sqlite:///{source}"])
    assert again.exit_code == 2 and "exists already" in again.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.db", "db.sqlite"]  # no partial file left behind
