"""The live participants table: belief history and quality flags, in a fixed number of queries per study."""

from __future__ import annotations

import csv
import io
from collections import defaultdict
from contextlib import contextmanager, nullcontext
from datetime import timedelta

from sqlalchemy import event, update

from experiment.config import PracticeConfig
from experiment.iohmm import paper_params
from server.harness.crowd import run_bots
from server.models import Participant, utcnow
from tests.server.factories import auth, fast_config, join, make_client, make_study


@contextmanager
def counted_statements(engine):
    statements: list[str] = []

    def count(_conn, _cursor, statement, *_args):
        statements.append(statement)

    event.listen(engine, "before_cursor_execute", count)
    try:
        yield statements
    finally:
        event.remove(engine, "before_cursor_execute", count)


def participants(client, admin):
    response = client.get("/api/admin/studies/s1/participants", headers=auth(admin))
    assert response.status_code == 200, response.text
    return {p["public_id"]: p for p in response.json()}


def straight_liner(client):
    """A participant who gives every Schaefer item the same answer, then stays on the first trial."""
    token = join(client, PROLIFIC_PID="same-answers")["token"]
    for path, body in (("consent", {"agree": True}), ("instructions/done", None)):
        assert client.post(f"/api/p/{token}/{path}", json=body).status_code == 200
    state = client.get(f"/api/p/{token}/state").json()
    questionnaire = state["questionnaire"]
    assert questionnaire["id"] == "schaefer_14"
    answers = {item["id"]: 50.0 for item in questionnaire["items"]}
    response = client.post(f"/api/p/{token}/answers", json={"questionnaire": "schaefer_14", "answers": answers})
    assert response.status_code == 200, response.text
    return response.json()


def test_belief_history_and_flags(database_url):
    client, admin = make_client(database_url=database_url)
    config = fast_config(practice=PracticeConfig(enabled=False), questionnaires_before=["schaefer_14"])
    make_study(client, admin, config=config)
    straight_liner(client)
    engine = client.app.state.services.engine
    with counted_statements(engine) as alone:
        [lonely] = participants(client, admin).values()
    assert lonely["belief_history"] == []
    assert [f["code"] for f in lonely["flags"]] == ["straight_lining"]
    assert lonely["flags"][0]["detail"] == "all 14 items of schaefer_14 (before) answered 50"

    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(),
                       participants=2, concurrency=1)
    assert summary.errors == [] and summary.completed == 2
    with counted_statements(engine) as crowd:
        table = participants(client, admin)
    assert len(table) == 3 and len(crowd) == len(alone)  # no query per participant

    export = client.get("/api/admin/studies/s1/export/trials.csv", headers=auth(admin))
    trials = csv.DictReader(io.StringIO(export.text))
    exported: defaultdict[str, list[float]] = defaultdict(list)
    for row in sorted(trials, key=lambda r: (int(r["block"]), int(r["trial"]))):
        if row["practice"] == "0":
            exported[row["participant_id"]].append(float(row["belief_after"]))
    for public_id, row in table.items():
        assert row["belief_history"] == [round(b, 4) for b in exported[public_id]]
        assert all(0 <= b <= 1 for b in row["belief_history"])
        if row["status"] == "completed":
            assert len(row["belief_history"]) == 12
            assert row["belief_history"][-1] == round(row["belief"], 4)

    with client.app.state.services.sessionmaker.begin() as session:  # the straight-liner went quiet five minutes ago
        session.execute(update(Participant).where(Participant.external_id == "same-answers")
                        .values(last_seen_at=utcnow() - timedelta(minutes=5)))
    quiet = next(p for p in participants(client, admin).values() if p["external_id"] == "same-answers")
    assert [f["code"] for f in quiet["flags"]] == ["straight_lining", "idle"]
