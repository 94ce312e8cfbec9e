"""Study exports: CSV contents after a bot run, codebook, zip manifest, formula safety, access."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import zipfile
from collections import Counter
from contextlib import nullcontext
from datetime import UTC, datetime, timedelta
from decimal import Decimal

import pytest
from sqlalchemy import select

from experiment.codebook import (
    CODEBOOK,
    EXPORT_FILES,
    NUMERIC_TYPES,
    PROBABILITY_DECIMALS,
    TYPES,
    columns,
    format_cell,
    format_number,
)
from experiment.iohmm import paper_params, update_belief
from experiment.questionnaires import reverse_code
from experiment.records import MODEL_COLUMNS, read_sequences
from experiment.schedule import n_shelves
from experiment.task import (
    Complexity,
    Experience,
    HumanAction,
    Outcome,
    RobotAction,
    resolve_trial,
)
from server import export
from server.errors import NotFound
from server.export import pages
from server.harness.crowd import run_bots
from server.models import AdminAudit, Participant, Trial
from server.sweeper import sweep
from tests.server.factories import auth, fast_config, join, make_client, make_study

N_BOTS = 2
#: Beliefs are written to PROBABILITY_DECIMALS places, and a belief recomputed from an exported (rounded) belief
#: carries that rounding times the update's slope (a few): agreement to 1e-8 is what the format promises.
BELIEF_TOLERANCE = 100 * 10.0 ** -PROBABILITY_DECIMALS
CSV_FILES = [name for name in EXPORT_FILES]


def download(client, admin, name, slug="s1"):
    response = client.get(f"/api/admin/studies/{slug}/export/{name}", headers=auth(admin))
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "text/csv; charset=utf-8"
    assert response.headers["content-disposition"] == f'attachment; filename="{slug}-{name}"'
    return response.content


def rows_of(content: bytes) -> tuple[list[str], list[dict[str, str]]]:
    reader = csv.DictReader(io.StringIO(content.decode("utf-8")))
    return list(reader.fieldnames or []), list(reader)


def assert_no_float_noise(name: str, rows: list[dict[str, str]]) -> None:
    """No number cell carries more decimal places than its column declares (nor any number inside a JSON cell)."""
    for column in CODEBOOK[name]:
        cells = [row[column.name] for row in rows if row[column.name] != ""]
        if column.type == "json":
            numbers = [n for cell in cells for n in _json_floats(json.loads(cell))]
        elif column.type == "number":
            numbers = [float(cell) for cell in cells]
            assert all(cell == format_number(float(cell), column.decimals) for cell in cells), column
        elif column.type in NUMERIC_TYPES:  # integer, flag
            assert all(cell.removeprefix("-").isdigit() for cell in cells), column
            continue
        else:
            continue
        for number in numbers:
            places = -Decimal(repr(number)).normalize().as_tuple().exponent
            assert places <= (column.decimals or 0), f"{name} {column.name}: {number!r} has {places} decimal places"


def _json_floats(value):
    if isinstance(value, float):
        yield value
    elif isinstance(value, dict | list):
        for v in value.values() if isinstance(value, dict) else value:
            yield from _json_floats(v)


def test_export_after_a_bot_run(database_url, tmp_path, monkeypatch):
    client, admin = make_client(database_url=database_url)
    config = fast_config()
    make_study(client, admin, config=config)
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(),
                       participants=N_BOTS, concurrency=1)
    assert summary.errors == [] and summary.completed == N_BOTS
    files = {name: download(client, admin, name) for name in CSV_FILES}
    parsed = {name: rows_of(content) for name, content in files.items()}
    for name, (header, rows) in parsed.items():
        assert header == columns(name)
        assert_no_float_noise(name, rows)

    people = {p["participant_id"]: p for p in parsed["participants.csv"][1]}
    assert len(people) == N_BOTS and {p["status"] for p in people.values()} == {"completed"}
    assert all(p["finished_at"] for p in people.values())
    orders = Counter(p["block_order"] for p in people.values())
    assert orders == Counter({"trust_aware|trust_agnostic": 1, "trust_agnostic|trust_aware": 1})  # balanced
    assert all(p["completion_code"] and float(p["compensation"]) >= 0 for p in people.values())

    header, trials = parsed["trials.csv"]
    assert header[:len(MODEL_COLUMNS)] == list(MODEL_COLUMNS)
    practice = [t for t in trials if t["practice"] == "1"]
    scored = [t for t in trials if t["practice"] == "0"]
    n_scored = sum(b.schedule.n_trials for b in config.blocks)
    assert len(practice) == N_BOTS * len(config.practice.trials) == N_BOTS * 4
    assert len(scored) == N_BOTS * n_scored == N_BOTS * 12
    _check_trials(config, people, practice, scored)

    _, surveys = parsed["surveys.csv"]
    per_participant = sum(n_shelves(b.schedule.n_trials,
                                    config.shelf_size) * len(config.questionnaire(config.shelf_questionnaire).items)
                          + sum(len(config.questionnaire(q).items) for q in b.questionnaires_after)
                          for b in config.blocks)
    assert per_participant == 2 * (2 * 2 + 14)
    assert len(surveys) == N_BOTS * per_participant
    assert Counter(s["participant_id"] for s in surveys) == {pid: per_participant for pid in people}
    for s in surveys:
        q = config.questionnaire(s["questionnaire"])
        assert float(s["scored_value"]) == reverse_code(q, s["item"], float(s["value"]))
        assert s["study"] == "s1" and s["version"] == "1" and s["excluded"] == "0"
        assert s["block_name"] == people[s["participant_id"]]["block_order"].split("|")[int(s["block"]) - 1]
    assert Counter(s["context"].split(":")[0] for s in surveys) == {"shelf": N_BOTS * 8, "after": N_BOTS * 28}

    _, events = parsed["events.csv"]
    assert {e["participant_id"] for e in events} == set(people)
    assert sum(e["kind"] == "trial_completed" for e in events) == len(trials)
    assert all(isinstance(json.loads(e["payload"]), dict) for e in events)
    for name, column in (("trials.csv", "completed_at"), ("participants.csv", "finished_at"),
                         ("events.csv", "created_at")):
        stamp = parsed[name][1][0][column]
        assert stamp.endswith("Z") and datetime.fromisoformat(stamp).tzinfo == UTC

    # Exclusion shows in every file, and model fitting skips the excluded participant.
    excluded = sorted(people)[1]
    response = client.post(f"/api/admin/studies/s1/participants/{excluded}/exclude", json={"reason": "test"},
                           headers=auth(admin))
    assert response.status_code == 200, response.text
    counts = export.export_study(client.app.state.services.sessionmaker, "s1", tmp_path / "out")
    assert counts == {"trials.csv": len(trials), "surveys.csv": len(surveys), "participants.csv": N_BOTS,
                      "events.csv": len(events), "codebook.csv": sum(map(len, CODEBOOK.values()))}
    _, rows = rows_of((tmp_path / "out" / "trials.csv").read_bytes())
    assert {r["excluded"] for r in rows if r["participant_id"] == excluded} == {"1"}
    ids, sequences = read_sequences(tmp_path / "out" / "trials.csv")
    assert ids == [pid for pid in people if pid != excluded]
    assert [len(s.complexity) for s in sequences] == [n_scored]
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    for name in CSV_FILES:
        content = (tmp_path / "out" / name).read_bytes()
        assert manifest["files"][name] == {"rows": counts[name], "bytes": len(content),
                                           "sha256": hashlib.sha256(content).hexdigest()}

    # The zip holds exactly what the single files hold, and its manifest says so.
    response = client.get("/api/admin/studies/s1/export.zip", headers=auth(admin))
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    assert response.headers["content-disposition"] == 'attachment; filename="s1-export.zip"'
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert archive.testzip() is None
        assert archive.namelist() == [*CSV_FILES, "manifest.json"]
        manifest = json.loads(archive.read("manifest.json"))
        assert manifest["study"] == "s1" and [v["version"] for v in manifest["versions"]] == [1]
        for name in CSV_FILES:
            content = archive.read(name)
            assert content == (tmp_path / "out" / name).read_bytes()
            assert manifest["files"][name] == {"rows": counts[name], "bytes": len(content),
                                               "sha256": hashlib.sha256(content).hexdigest()}

    # Small pages and participant batches (many keyset pages) give the same bytes.
    monkeypatch.setattr(pages, "PARTICIPANT_BATCH", 1)
    monkeypatch.setattr(pages, "ID_PAGE", 1)
    factory = client.app.state.services.sessionmaker
    with factory() as session:
        target = export.export_target(session, "s1")
    for name in CSV_FILES:
        assert b"".join(export.iter_csv(factory, target, name, page_rows=3)) == (tmp_path / "out" / name).read_bytes()

    with factory() as session:
        lines = session.scalars(select(AdminAudit).where(AdminAudit.action == "study.export")
                                .order_by(AdminAudit.id)).all()
    assert [line.detail["file"] for line in lines] == [*CSV_FILES, "directory", "export.zip", "export.zip"]
    assert lines[-1].detail["rows"] == counts and lines[-1].detail["completed"] is True


def _check_trials(config, people, practice, scored):
    params = paper_params()
    by_participant: dict[str, list[dict[str, str]]] = {}
    for t in scored:
        by_participant.setdefault(t["participant_id"], []).append(t)
    for t in practice + scored:
        c, a, o = Complexity(t["complexity"]), RobotAction(t["robot_action"]), HumanAction(t["human_action"])
        result = resolve_trial(c, a, o, t["outcome"] == Outcome.SUCCESS.value, config.task)
        assert (t["outcome"], t["experience"], float(t["reward"])) == (result.outcome.value, result.experience.value,
                                                                       result.reward)
        assert t["reward"] == format_number(result.reward)  # numbers as numbers, e.g. -4, never '-4
        assert t["study"] == "s1" and t["version"] == "1" and t["excluded"] == "0"
        assert (t["teleop_success"] != "") == (o == HumanAction.INTERVENE)
        assert t["failure_mode"] == "" or t["outcome"] == "failure"
        if t["practice"] == "1":
            assert t["block"] == "0" and t["block_name"] == "practice" and t["belief_after"] == t["belief_before"]
    for pid, rows in by_participant.items():
        order = people[pid]["block_order"].split("|")
        assert [(int(r["block"]), int(r["trial"])) for r in rows] == [(b, i) for b in (1, 2) for i in range(1, 7)]
        assert [int(r["trial_overall"]) for r in rows] == list(range(1, 13))
        for block in (1, 2):
            in_block = [r for r in rows if r["block"] == str(block)]
            assert {r["block_name"] for r in in_block} == {order[block - 1]}
            assert Counter(r["complexity"] for r in in_block) == {"low": 3, "high": 3}
            assert Counter(r["shelf"] for r in in_block) == {"1": 3, "2": 3}
        score = 0.0
        belief = params.initial_high
        for r in rows:
            assert float(r["belief_before"]) == pytest.approx(belief, abs=BELIEF_TOLERANCE)
            belief = update_belief(params, float(r["belief_before"]), Complexity(r["complexity"]),
                                   RobotAction(r["robot_action"]), HumanAction(r["human_action"]),
                                   Experience(r["experience"]), "bayes")
            assert float(r["belief_after"]) == pytest.approx(belief, abs=BELIEF_TOLERANCE)
            score += float(r["reward"])
            assert float(r["score"]) == pytest.approx(score)
        assert float(people[pid]["score"]) == pytest.approx(score)


def test_cells_are_formatted_by_column_type():
    assert [format_cell("number", v) for v in (-4.0, 3.0, 0.25, -0.5, math.nan, None, 1e20)] == \
        ["-4", "3", "0.25", "-0.5", "", "", "1e+20"]
    assert [format_cell("integer", v) for v in (-2, 0, None)] == ["-2", "0", ""]
    assert [format_cell("flag", v) for v in (True, False, None)] == ["1", "0", ""]
    for text in ("=1+1", "+1", "-4", "@SUM(A1)", "\tx", "\rx"):
        assert format_cell("text", text) == "'" + text
        assert format_cell("category", text) == "'" + text
    assert [format_cell("text", t) for t in ("", "a=b", "P1", "'=x")] == ["", "a=b", "P1", "'=x"]
    assert format_cell("json", {"a": "=x"}) == '{"a":"=x"}'
    assert format_cell("datetime", datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)) == "2026-01-02T03:04:05.000000Z"
    assert format_cell("datetime", "2026-01-02 03:04:05.000007") == "2026-01-02T03:04:05.000007Z"


def test_formula_cells_are_neutralised_numbers_stay_numbers(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    evil = '=HYPERLINK("http://evil.example","click")'
    join(client, PROLIFIC_PID=evil)
    factory = client.app.state.services.sessionmaker
    with factory.begin() as session:
        participant = session.scalar(select(Participant))
        public_id = participant.public_id
        participant.excluded, participant.exclusion_reason = True, "+SUM(1,2) @admin"
        now = datetime.now(UTC)
        session.add(Trial(participant_id=participant.id, study_version_id=participant.study_version_id, practice=False,
                          block=1, block_name="trust_aware", policy="trust_aware", trial=1, trial_overall=1, shelf=1,
                          complexity="high", robot_action="auto", stage="done", human_action="rely", outcome="failure",
                          experience="negative", reward=-4.0, score=-4.0, belief_before=0.5, belief_after=0.25,
                          policy_belief=0.5, failure_mode="drop", started_at=now, decided_at=now, completed_at=now))
    _, people = rows_of(download(client, admin, "participants.csv"))
    assert people[0]["external_id"] == "'" + evil
    assert people[0]["exclusion_reason"] == "'+SUM(1,2) @admin"
    assert json.loads(people[0]["recruitment"]) == {"PROLIFIC_PID": evil}
    _, trials = rows_of(download(client, admin, "trials.csv"))
    assert [(t["participant_id"], t["reward"], t["score"], t["belief_after"], t["excluded"]) for t in trials] == \
        [(public_id, "-4", "-4", "0.25", "1")]
    raw = download(client, admin, "trials.csv").decode()
    assert ",-4,-4," in raw and "'-4" not in raw


def test_codebook_describes_every_column(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    _, codebook = rows_of(download(client, admin, "codebook.csv"))
    documented = {(r["file"], r["column"]) for r in codebook}
    exported = {(name, column) for name in CSV_FILES for column in rows_of(download(client, admin, name))[0]}
    assert documented == exported and len(codebook) == len(exported)
    assert {r["type"] for r in codebook} <= TYPES
    assert all(r["meaning"] for r in codebook)
    for name, column in MODEL_COLUMNS.items():
        row = next(r for r in codebook if r["file"] == "trials.csv" and r["column"] == name)
        assert column is None or row["allowed_values"] == "|".join(column)
    response = client.get("/api/admin/studies/s1/export.zip", headers=auth(admin))
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        manifest = json.loads(archive.read("manifest.json"))
    assert {name: f["rows"] for name, f in manifest["files"].items()} == {
        "trials.csv": 0, "surveys.csv": 0, "participants.csv": 0, "events.csv": 0, "codebook.csv": len(codebook)}


def test_exports_need_the_admin_token_and_a_known_study(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    paths = [f"/api/admin/studies/s1/export/{name}" for name in CSV_FILES] + ["/api/admin/studies/s1/export.zip"]
    for path in paths:
        assert client.get(path).status_code == 401
        assert client.get(path, headers=auth("tla_not-the-token")).status_code == 401
        missing = client.get(path.replace("/s1/", "/nope/"), headers=auth(admin))
        assert missing.status_code == 404 and missing.json() == {"detail": "no study 'nope'", "code": "not_found"}
    unknown = client.get("/api/admin/studies/s1/export/secrets.csv", headers=auth(admin))
    assert unknown.status_code == 422 and "trials.csv" in unknown.json()["detail"]
    with pytest.raises(NotFound):
        export.export_study(client.app.state.services.sessionmaker, "nope", "/nonexistent-never-created")


def test_every_ended_session_has_finished_at_and_reading_it_moves_nothing(database_url):
    """Declined, abandoned and withdrawn sessions get finished_at (completed ones: the bot run above); reading an
    ended session (state, scene, heartbeat) does not move its last_seen_at."""
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    declined, abandoned, withdrawn, active = (join(client)["token"] for _ in range(4))
    assert client.post(f"/api/p/{declined}/consent", json={"agree": False}).status_code == 200
    for token in (abandoned, withdrawn):
        assert client.post(f"/api/p/{token}/consent", json={"agree": True}).status_code == 200
    app, factory = client.app, client.app.state.services.sessionmaker
    long_ago = datetime(2026, 1, 1, tzinfo=UTC)
    with factory.begin() as session:  # only ``abandoned`` went quiet
        by_token = {p.public_id: p for p in session.scalars(select(Participant))}
        people = sorted(by_token.values(), key=lambda p: p.id)
        people[1].last_seen_at = long_ago
        public = [p.public_id for p in people]
    swept_at = long_ago + timedelta(hours=2)
    assert sweep(factory, app.state.services.runtimes, app.state.services.hub, now=swept_at) == 1
    response = client.post(f"/api/admin/studies/s1/participants/{public[2]}/withdraw", json={"reason": "asked"},
                           headers=auth(admin))
    assert response.status_code == 200, response.text

    with factory.begin() as session:  # an ended session's last_seen_at is old: reading it must leave it so
        for p in session.scalars(select(Participant).where(Participant.public_id.in_(public[:3]))):
            p.last_seen_at = long_ago
    for token in (declined, abandoned, withdrawn):
        assert client.get(f"/api/p/{token}/state").status_code == 200
        assert client.get(f"/api/p/{token}/trials/scene").status_code in (409, 410)
        assert client.post(f"/api/p/{token}/heartbeat", json={}).status_code in (200, 410)

    _, rows = rows_of(download(client, admin, "participants.csv"))
    by_id = {r["participant_id"]: r for r in rows}
    assert [by_id[pid]["status"] for pid in public] == ["declined", "abandoned", "withdrawn", "active"]
    assert all(by_id[pid]["finished_at"] for pid in public[:3]) and by_id[public[3]]["finished_at"] == ""
    assert by_id[public[1]]["finished_at"] == swept_at.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    assert {by_id[pid]["last_seen_at"] for pid in public[:3]} == {long_ago.strftime("%Y-%m-%dT%H:%M:%S.%fZ")}
