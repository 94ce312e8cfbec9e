"""A hostile or broken client and the event log: payload bounds, the per-session budget and rate, exports that
write every stored row (values stored before requests were read strictly are written repaired), a download that
fails part way is aborted, and ``trustlab check-data`` finds and repairs such values."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import zipfile
from dataclasses import replace
from types import SimpleNamespace

import httpx
import pytest
from sqlalchemy import select, text
from typer.testing import CliRunner

from experiment.codebook import EXPORT_FILES
from experiment.iohmm import paper_params
from experiment.writable import REPLACEMENT, TOO_DEEP
from server.cli import app as cli
from server.harness.live import live_server
from server.models import AdminAudit, Event, Participant, utcnow
from server.services.events import EventBudget
from tests.server.factories import add_simulated_participants, auth, fast_config, join, make_client, make_study

runner = CliRunner()

#: Payloads the pages send (static/js: trial.js, participant.js, teleop*.js), each as events.js stamps it.
PAGE_PAYLOADS = [
    {"code": "KeyW", "stage": "teleop", "page": "0123456789ab", "seq": 1234},
    {"trial": "b1t12", "decision_ms_left": 4200, "decision_window_s": 5.0, "page": "0123456789ab", "seq": 7},
    {"path": "/api/p/x/intervene", "status": 409, "detail": "x" * 200, "page": "0123456789ab", "seq": 9},
    {"fps": 12.5, "frame_ms": 80, "page": "0123456789ab", "seq": 10},
    {"trial": "b1t3", "viewer": {"mode": "3d", "size": [640, 480]}, "page": "0123456789ab", "seq": 11},
]


def nested(depth: int) -> dict:
    """An object nested ``depth`` levels deep (the object itself is level 1)."""
    value: dict = {"leaf": 1}
    for _ in range(depth - 1):
        value = {"a": value}
    return value


def post_events(client, token: str, *payloads: dict):
    return client.post(f"/api/p/{token}/events", json={"events": [{"kind": "x", "payload": p} for p in payloads]})


def test_event_payloads_past_their_bounds_are_refused_and_the_pages_payloads_pass(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    token = join(client)["token"]
    assert post_events(client, token, *PAGE_PAYLOADS).status_code == 200
    assert post_events(client, token, nested(8)).status_code == 200
    refused = {
        "nested deeper than 8 levels": nested(9),
        "more than 64 keys": {f"k{i}": i for i in range(65)},
        "longer than 1000 characters": {"s": "x" * 1001},
        "integers must lie within": {"n": 2**53},
        "larger than 4096 bytes": {f"k{i}": "y" * 900 for i in range(5)},
    }
    for reason, payload in refused.items():
        response = post_events(client, token, payload)
        assert response.status_code == 422 and reason in json.dumps(response.json()), (reason, response.text)
    assert post_events(client, token, {"n": -(2**53 - 1)}).status_code == 200  # JavaScript's range, both ends
    # Read strictly before validation: a lone surrogate, NaN, a number that overflows, 500 levels deep.
    for body in (b'{"events":[{"kind":"x","payload":{"s":"\\ud800"}}]}',
                 b'{"events":[{"kind":"x","payload":{"n":NaN}}]}',
                 b'{"events":[{"kind":"x","payload":{"n":1e309}}]}',
                 b'{"events":[{"kind":"x","payload":' + b'{"a":' * 500 + b"1" + b"}" * 500 + b"}]}"):
        response = client.post(f"/api/p/{token}/events", content=body, headers={"Content-Type": "application/json"})
        assert response.status_code == 422, response.text
    with client.app.state.services.sessionmaker() as session:
        assert session.scalar(select(Event.id).where(Event.kind == "client.x").offset(len(PAGE_PAYLOADS) + 1)) \
            is not None  # the pages' payloads, the 8-deep one and the -(2^53-1) one were stored, nothing else
        assert len(session.scalars(select(Event.id).where(Event.kind == "client.x")).all()) == len(PAGE_PAYLOADS) + 2
    described = client.get("/openapi.json").json()["components"]["schemas"]["EventCreate"]
    assert "nested at most 8 levels" in described["properties"]["payload"]["description"]


def test_a_session_past_its_event_budget_is_refused_and_its_study_goes_on(database_url):
    client, admin = make_client(database_url=database_url, event_budget_events=5, event_budget_bytes=1024)
    make_study(client, admin)
    token = join(client)["token"]
    assert post_events(client, token, *([{"a": 1}] * 5)).status_code == 200
    refused = post_events(client, token, {"a": 1})
    assert refused.status_code == 413 and refused.json()["code"] == "event_budget_spent", refused.text
    assert "budget of client events" in refused.json()["detail"] and "5 events" in refused.json()["detail"]
    assert client.get(f"/api/p/{token}/state").status_code == 200  # the study goes on
    assert client.post(f"/api/p/{token}/consent", json={"agree": True}).status_code == 200
    other = join(client)["token"]  # another session has its own budget: bytes this time
    assert post_events(client, other, {"s": "z" * 900}).status_code == 200
    too_big = post_events(client, other, {"s": "z" * 200})
    assert too_big.status_code == 413 and "bytes of payload" in too_big.json()["detail"]
    services = client.app.state.services  # as after a restart: what is stored is counted from the database
    client.app.state.services = replace(services, event_budget=EventBudget(services.settings))
    assert post_events(client, token, {"a": 1}).status_code == 413
    with client.app.state.services.sessionmaker() as session:
        counts = [len(session.scalars(select(Event.id).join(Participant).where(
            Participant.id == Event.participant_id, Event.kind.startswith("client."))).all())]
    assert counts == [6]  # 5 + 1: nothing past either budget was stored


def test_event_requests_past_the_rate_get_429_with_retry_after(database_url):
    client, admin = make_client(database_url=database_url, event_rate_per_s=0.1, event_rate_burst=3)
    make_study(client, admin)
    token, other = join(client)["token"], join(client)["token"]
    assert [post_events(client, token, {"a": 1}).status_code for _ in range(3)] == [200] * 3
    limited = post_events(client, token, {"a": 1})
    assert limited.status_code == 429 and limited.json()["code"] == "rate_limited"
    assert 1 <= int(limited.headers["retry-after"]) <= 10 and "event requests" in limited.json()["detail"]
    assert post_events(client, other, {"a": 1}).status_code == 200  # per session
    assert client.get(f"/api/p/{token}/state").status_code == 200


# -- values stored before requests were read strictly ----------------------------------------------------------

#: Stored JSON texts no strict writer writes as they are, each with what an export writes instead.
HOSTILE_PAYLOADS = {
    '{"s":"\\ud800 left"}': {"s": REPLACEMENT + " left"},
    '{"x":1e400,"ok":2}': {"x": None, "ok": 2},
    '{"a":' * 500 + "1" + "}" * 500: None,  # checked below: cut at 32 levels
    '{"a":' * 3000 + "1" + "}" * 3000: None,  # too deep for the drivers' parsers too: cut before parsing
}


def store_raw(session, table: str, column: str, row_id: int, stored: str) -> None:
    """Put JSON text into a row as a deployed database may hold it (bypassing every check and serialiser)."""
    value = "CAST(:v AS json)" if session.bind.dialect.name == "postgresql" else ":v"
    session.execute(text(f"UPDATE {table} SET {column} = {value} WHERE id = :id"), {"v": stored, "id": row_id})


def hostile_study(database_url: str):
    """A study with 3 simulated participants whose events and recruitment hold values stored unchecked."""
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    ids = add_simulated_participants(client, "s1", n=3, model=paper_params())
    payloads = list(HOSTILE_PAYLOADS)
    if database_url.startswith("sqlite"):
        # PostgreSQL's json type refuses these; SQLite holds them (the second is not JSON at all)
        payloads += ['{"n":NaN,"i":-Infinity}', '{"broken":']
    with client.app.state.services.sessionmaker.begin() as session:
        participants = session.scalars(select(Participant).where(Participant.public_id.in_(ids))).all()
        for i, stored in enumerate(payloads):
            event = Event(study_id=participants[0].study_id, participant_id=participants[i % 3].id, kind="client.x",
                          payload={}, server_monotonic_s=1.0, created_at=utcnow())
            session.add(event)
            session.flush()
            store_raw(session, "event", "payload", event.id, stored)
        store_raw(session, "participant", "recruitment", participants[1].id, '{"PROLIFIC_PID":"p\\udfff"}')
    return client, admin, ids, len(payloads)


def check_events_csv(body: bytes, n_hostile: int) -> None:
    rows = list(csv.DictReader(io.StringIO(body.decode("utf-8"))))
    written = [json.loads(r["payload"]) for r in rows if r["kind"] == "client.x"]
    assert len(written) == n_hostile
    assert written[0] == {"s": REPLACEMENT + " left"} and written[1] == {"x": None, "ok": 2}
    for deep in written[2:4]:
        depth = 1
        while isinstance(deep, dict):
            deep, depth = deep["a"], depth + 1
        assert deep == TOO_DEEP and depth == 33  # 32 levels kept, the 33rd written as the marker
    if n_hostile == 6:
        assert written[4] == {"n": None, "i": None}
        assert written[5] == '{"broken":'  # kept as a string


def test_stored_hostile_values_are_exported_whole(database_url, tmp_path):
    client, admin, ids, n_hostile = hostile_study(database_url)
    with client.app.state.services.sessionmaker() as session:
        n_events = len(session.scalars(select(Event.id)).all())

    events = client.get("/api/admin/studies/s1/export/events.csv", headers=auth(admin))
    assert events.status_code == 200
    check_events_csv(events.content, n_hostile)
    assert len(list(csv.DictReader(io.StringIO(events.text)))) == n_events

    participants = client.get("/api/admin/studies/s1/export/participants.csv", headers=auth(admin))
    recruitment = {r["participant_id"]: r["recruitment"] for r in csv.DictReader(io.StringIO(participants.text))}
    assert json.loads(recruitment[ids[1]]) == {"PROLIFIC_PID": "p" + REPLACEMENT}

    archive_response = client.get("/api/admin/studies/s1/export.zip", headers=auth(admin))
    assert archive_response.status_code == 200
    with zipfile.ZipFile(io.BytesIO(archive_response.content)) as archive:
        assert archive.testzip() is None
        manifest = json.loads(archive.read("manifest.json"))
        for name in EXPORT_FILES:
            data = archive.read(name)
            data.decode("utf-8")  # every file is UTF-8
            assert hashlib.sha256(data).hexdigest() == manifest["files"][name]["sha256"]
            assert len(list(csv.DictReader(io.StringIO(data.decode())))) == manifest["files"][name]["rows"]
        check_events_csv(archive.read("events.csv"), n_hostile)
        assert manifest["files"]["events.csv"]["rows"] == n_events
        assert manifest["files"]["trials.csv"]["rows"] > 0

    report = client.get("/api/admin/studies/s1/report", params={"restarts": "2"}, headers=auth(admin))
    assert report.status_code == 200, report.text
    with zipfile.ZipFile(io.BytesIO(report.content)) as archive:
        check_events_csv(archive.read("data/events.csv"), n_hostile)

    result = runner.invoke(cli, ["export", "s1", "--out", str(tmp_path / "out"), "--database-url", database_url])
    assert result.exit_code == 0, result.output
    check_events_csv((tmp_path / "out" / "events.csv").read_bytes(), n_hostile)
    assert f"events.csv: {n_events} rows" in result.output


def test_an_export_failing_part_way_aborts_the_download_and_is_logged(database_url, monkeypatch, caplog):
    import server.export.writers as writers

    real = writers.iter_values

    def failing(*args, **kwargs):
        pages = real(*args, **kwargs)
        yield next(pages)
        raise RuntimeError("injected: the database went away")

    with live_server(database_url) as live:
        created = live.admin("POST", "/api/admin/studies",
                             json={"status": "open", "slug": "s1", "config": fast_config().model_dump(mode="json")})
        assert created.status_code == 201, created.text
        add_simulated_participants(SimpleNamespace(app=live.app), "s1", n=2, model=paper_params())
        monkeypatch.setattr(writers, "iter_values", failing)
        caplog.set_level(logging.ERROR, logger="trustlab")
        for path in ("/export/trials.csv", "/export.zip"):
            with pytest.raises(httpx.RemoteProtocolError):  # an incomplete transfer, never a clean end
                with httpx.stream("GET", f"{live.url}/api/admin/studies/s1{path}",
                                  headers=auth(live.admin_token), timeout=30) as response:
                    assert response.status_code == 200  # the headers were sent before the failure
                    for _ in response.iter_bytes():
                        pass
        messages = [r.getMessage() for r in caplog.records]
        assert any("export trials.csv of study s1 failed after" in m for m in messages), messages
        assert any("export export.zip of study s1 failed after" in m for m in messages), messages


def test_check_data_lists_and_repairs_stored_values_once(database_url):
    client, admin, ids, n_hostile = hostile_study(database_url)
    found = runner.invoke(cli, ["check-data", "--database-url", database_url])
    assert found.exit_code == 1, found.output
    lines = [line for line in found.stdout.splitlines() if line.startswith("s1\t")]
    assert len(lines) == n_hostile + 1
    assert any(f"s1\t{ids[1]}\tparticipant.recruitment" in line and "surrogate" in line for line in lines)
    assert any("event.payload" in line and "nested deeper than 32" in line for line in lines)
    assert any("event.payload" in line and "non-finite" in line for line in lines)
    if database_url.startswith("sqlite"):
        assert any("event.payload" in line and "not JSON at all" in line for line in lines)

    repaired = runner.invoke(cli, ["check-data", "--repair", "--database-url", database_url])
    assert repaired.exit_code == 0 and f"{n_hostile + 1} values repaired" in repaired.output, repaired.output
    again = runner.invoke(cli, ["check-data", "--database-url", database_url])
    assert again.exit_code == 0 and "no problems found" in again.output, again.output
    assert runner.invoke(cli, ["check-data", "--repair", "--database-url", database_url]).exit_code == 0

    with client.app.state.services.sessionmaker() as session:
        audits = session.scalars(select(AdminAudit).where(AdminAudit.action == "data.repair")).all()
        assert len(audits) == n_hostile + 1  # one per value, none from the second (idempotent) run
        assert all(a.detail["table"] in ("event", "participant") and "problems" in a.detail for a in audits)
        assert not any("ud800" in json.dumps(a.detail) or "left" in json.dumps(a.detail) for a in audits)
        recruitment = session.scalar(select(Participant.recruitment).where(Participant.public_id == ids[1]))
        assert recruitment == {"PROLIFIC_PID": "p" + REPLACEMENT}
    events = client.get("/api/admin/studies/s1/export/events.csv", headers=auth(admin))
    check_events_csv(events.content, n_hostile)  # exports write the same after the repair

