"""Hostile input: join rate limits, oversized bodies (with and without Content-Length), formula cells in exports."""

from __future__ import annotations

import csv
import io
import json

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.harness.live import live_server
from server.models import Participant
from server.ratelimit import RateLimiter
from server.settings import Settings
from tests.server.factories import auth, join, make_client, make_study

#: Text a spreadsheet would run as a formula (SPEC §10), each typed where a participant or link can put text.
FORMULAS = ["=cmd|' /C calc'!A0", "+1", "-1+2", "@SUM(A1:A9)", "-4", '=HYPERLINK("http://x.invalid","y")']
#: Formula text hidden behind a tab or carriage return (spreadsheets strip them).
HIDDEN_FORMULAS = ["\t=1", "\r=1"]


def test_rate_limiter_refills_at_its_rate_and_keeps_keys_apart():
    limiter = RateLimiter.minutely(6, max_keys=3)
    assert [limiter.take("a", now=0.0) for _ in range(6)] == [0.0] * 6  # a minute's allowance at once
    assert limiter.take("a", now=0.0) == pytest.approx(10.0)  # then one every 10 s
    assert limiter.take("a", now=5.0) == pytest.approx(5.0)  # a refused request takes nothing
    assert limiter.take("a", now=10.0) == 0.0 and limiter.take("a", now=10.0) > 0
    assert limiter.take("b", now=10.0) == 0.0  # another key has its own bucket
    for key in "cdef":
        limiter.take(key, now=10.0)
    assert len(limiter._buckets) == 3  # bounded: the least recently used keys are dropped


def test_join_is_rate_limited_per_address(database_url):
    client, admin = make_client(database_url=database_url, join_rate_limit_per_ip=3)
    make_study(client, admin)
    for _ in range(3):
        join(client)
    refused = client.post("/api/studies/s1/join")
    assert refused.status_code == 429 and refused.json()["code"] == "rate_limited"
    assert "too many joins from this address" in refused.json()["detail"]
    assert 1 <= int(refused.headers["retry-after"]) <= 20  # 3 a minute: one more after 20 s at most
    assert client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "resume-me"}).status_code == 429
    elsewhere = TestClient(client.app, client=("192.0.2.7", 50000))  # another address (documentation range)
    assert elsewhere.post("/api/studies/s1/join").status_code == 200
    with client.app.state.services.sessionmaker() as session:
        assert len(session.scalars(select(Participant)).all()) == 4  # nothing was created by a refused join


def test_join_is_rate_limited_per_study(database_url):
    client, admin = make_client(database_url=database_url, join_rate_limit_per_study=3)
    make_study(client, admin, slug="s1")
    make_study(client, admin, slug="s2")
    addresses = [TestClient(client.app, client=(f"192.0.2.{i}", 50000)) for i in range(1, 6)]
    assert [c.post("/api/studies/s1/join").status_code for c in addresses] == [200, 200, 200, 429, 429]
    refused = addresses[-1].post("/api/studies/s1/join")
    assert "too many joins for this study" in refused.json()["detail"] and int(refused.headers["retry-after"]) >= 1
    assert addresses[-1].post("/api/studies/s2/join").status_code == 200  # other studies are not affected


def test_default_join_limits_leave_room_for_a_lab():
    """A lab where 20 participants join at once from one address, or a study filling at 5 joins a second."""
    settings = Settings(_env_file=None)
    assert settings.join_rate_limit_per_ip >= 20 and settings.join_rate_limit_per_study >= 300


def test_oversized_bodies_are_refused_with_or_without_content_length(sqlite_template, tmp_path):
    """Against a real server (uvicorn), as a client would send them: declared too large, or streamed chunked."""
    path = tmp_path / "limits.db"
    path.write_bytes(sqlite_template.read_bytes())
    limit = 64 * 1024
    with live_server(f"sqlite:///{path}", max_body_bytes=limit) as live:
        assert live.admin("POST", "/api/admin/studies",
                          json={"status": "open", "slug": "s1", "template": "demo-fast"}).status_code == 201
        token = httpx.post(f"{live.url}/api/studies/s1/join").json()["token"]
        events = f"{live.url}/api/p/{token}/events"
        json_type = {"content-type": "application/json"}

        declared = httpx.post(events, content=b"x" * (limit + 1), headers=json_type)
        assert declared.status_code == 413 and declared.json() == {"detail": f"request body larger than {limit} bytes",
                                                                   "code": "too_large"}

        def chunks(total: int):
            for _ in range(total // 8192):
                yield b" " * 8192

        for url in (events, f"{live.url}/api/admin/studies"):
            streamed = httpx.post(url, content=chunks(2 * limit), headers=json_type | auth(live.admin_token))
            assert streamed.request.headers.get("transfer-encoding") == "chunked"
            assert "content-length" not in streamed.request.headers
            assert streamed.status_code == 413 and streamed.json()["code"] == "too_large", streamed.text

        under = httpx.post(events, content=b'{"events": []}' + b" " * (limit - 100), headers=json_type)
        assert under.status_code == 200, under.text  # the limit is the limit, not less
        under_chunked = httpx.post(events, content=chunks(limit - 8192), headers=json_type)
        assert under_chunked.status_code == 422  # read whole and found not to be JSON: no 413


def test_export_neutralises_formula_text_and_keeps_numbers(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    tokens = {}
    for value in FORMULAS:  # as the external id and as other recruitment parameters of the join link
        tokens[value] = join(client, PROLIFIC_PID=value, STUDY_ID=value, SESSION_ID="=1+1")["token"]
    for value in HIDDEN_FORMULAS:  # not printable: refused at the door with a reason
        refused = client.post("/api/studies/s1/join", params={"PROLIFIC_PID": value})
        assert refused.status_code == 422 and "PROLIFIC_PID" in refused.json()["detail"]
    # answers to a page not asked are refused, never stored (free-text answers, formula text included, are
    # exported neutralised: tests/server/test_instruments_api.py)
    refused = client.post(f"/api/p/{tokens['+1']}/answers", json={"questionnaire": "trust", "answers": {"1": "=1+1"}})
    assert refused.status_code == 409
    # free text from the admin (exclusion reasons), including the hidden kinds
    with client.app.state.services.sessionmaker() as session:
        public_ids = dict(zip(FORMULAS, session.scalars(select(Participant.public_id).order_by(Participant.id)),
                              strict=True))
    reasons = dict(zip(FORMULAS, FORMULAS[::-1] + HIDDEN_FORMULAS, strict=False)) | {"-4": "\t=1",
                                                                                     "@SUM(A1:A9)": "\r=1"}
    for value, reason in reasons.items():
        response = client.post(f"/api/admin/studies/s1/participants/{public_ids[value]}/exclude",
                               json={"reason": reason},
                               headers=auth(admin))
        assert response.status_code == 200, response.text
    with client.app.state.services.sessionmaker.begin() as session:  # a negative number where numbers are exported
        session.scalar(select(Participant).where(Participant.public_id == public_ids["-4"])).score = -4.0

    response = client.get("/api/admin/studies/s1/export/participants.csv", headers=auth(admin))
    assert response.status_code == 200
    rows = {row["participant_id"]: row
            for row in csv.DictReader(io.StringIO(response.content.decode("utf-8"), newline=""))}
    for value in FORMULAS:
        row = rows[public_ids[value]]
        assert row["external_id"] == "'" + value  # prefixed, so a spreadsheet shows the text
        assert row["exclusion_reason"] == "'" + reasons[value]
        assert json.loads(row["recruitment"]) == {"PROLIFIC_PID": value, "STUDY_ID": value, "SESSION_ID": "=1+1"}
        assert row["recruitment"].startswith("{")  # a JSON cell is never a formula
    assert rows[public_ids["-4"]]["score"] == "-4"  # the number -4 stays a number ...
    assert rows[public_ids["-4"]]["external_id"] == "'-4"  # ... the text "-4" does not
    for row in list(csv.reader(io.StringIO(response.content.decode("utf-8"), newline="")))[1:]:
        for cell in row:
            assert not cell.startswith(("=", "+", "@", "\t", "\r")), cell
            assert not cell.startswith("-") or _is_number(cell), cell


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True
