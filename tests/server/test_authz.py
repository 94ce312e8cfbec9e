"""Authorization of every route (SPEC §10 Security), token strength, and tokens kept out of logs, exports and rows.

The routes are read from the app itself, so a route added later is checked too, and a
route whose access rule this file does not know fails ``test_every_route_has_an_access_rule``.
"""

from __future__ import annotations

import base64
import io
import logging
import re
import secrets
import shutil
import string
import threading
import time
import zipfile

import pytest
from sqlalchemy import MetaData, create_engine, select
from starlette.websockets import WebSocketDisconnect

from server.harness.bots import bot_resume_key
from server.harness.live import live_server
from server.models import Answer, Event, Participant, Trial, utcnow
from server.routes.viewer import SUBPROTOCOL
from server.services.admin import rotate_admin_token
from server.services.sessions import app_secret, hash_token
from tests.server.factories import app_routes, auth, fast_config, join, make_client, make_study

ADMIN_PREFIX = "/api/admin/"
SESSION_PREFIX = "/api/p/{token}/"
VIEWER_PATHS = {"/viewer/{token}", "/viewer/{token}/"}
#: Routes anyone may call: the API description, static pages that carry no data, joining a study, and what the
#: pages say before a session exists (the message catalogue of a language, the language a join link would get).
PUBLIC = {("GET", "/openapi.json"), ("GET", "/docs"), ("GET", "/docs/oauth2-redirect"), ("GET", "/redoc"),
          ("GET", "/join/{slug}"), ("GET", "/p/{token}"), ("GET", "/admin"), ("POST", "/api/studies/{slug}/join"),
          ("GET", "/api/schema/teleop.json"), ("GET", "/api/messages/{language}"),
          ("GET", "/api/studies/{slug}/language")}
#: A body per participant route that the session at practice would accept ({} for routes added later).
SESSION_BODIES = {"consent": {"agree": True}, "trials/start": {"practice": True, "block": 0, "trial": 1},
                  "trials/intervene": {"practice": True, "block": 0, "trial": 1},
                  "trials/shown": {"practice": True, "block": 0, "trial": 1, "view": "2d"}, "heartbeat": {},
                  "answers": {"questionnaire": "trust", "answers": {"1": 50}}, "camera": {"view": "local"},
                  "answers/draft": {"questionnaire": "trust", "context": "before", "answers": {"1": 50}},
                  "events": {"events": [{"kind": "probe", "payload": {"x": 1}}]}, "withdraw": {"confirm": True}}
URL_SAFE = set(string.ascii_letters + string.digits + "-_")
#: The test's own HTTP client logs the URLs it requests; those lines are not the server's.
CLIENT_LOGGERS = ("httpx", "httpcore")


def access_rule(method: str, path: str) -> str:
    if path.startswith(ADMIN_PREFIX):
        return "admin token"
    if path.startswith(SESSION_PREFIX):
        return "session token"
    if path in VIEWER_PATHS:
        return "viewer"
    if (method, path) in PUBLIC:
        return "public"
    return "unknown"


def fill(path: str, **values: str) -> str:
    """``path`` with its parameters replaced by ``values`` (any other parameter by a plausible made-up value)."""
    return re.sub(r"\{(\w+)\}", lambda m: values.get(m.group(1), "1"), path)


@pytest.fixture
def two_studies(database_url):
    """Participants of two studies; alice is at the practice trials, bob has just joined."""
    client, admin = make_client(database_url=database_url)
    for slug in ("s1", "s2"):
        make_study(client, admin, slug=slug)
    alice = join(client, "s1", PROLIFIC_PID="alice-ext")
    bob = join(client, "s2", PROLIFIC_PID="bob-ext")
    for step, body in (("consent", {"agree": True}), ("instructions/done", None)):
        assert client.post(f"/api/p/{alice['token']}/{step}", json=body).status_code == 200
    return client, admin, alice, bob


def public_id_of(client, token: str) -> str:
    with client.app.state.services.sessionmaker() as session:
        return session.scalar(select(Participant.public_id).where(Participant.token_hash == hash_token(token)))


def test_every_route_has_an_access_rule(two_studies):
    client, *_ = two_studies
    routes = app_routes(client.app)
    unknown = [(method, path) for method, path, _ in routes if access_rule(method, path) == "unknown"]
    assert unknown == [], "give these routes an access rule here (and a test of it)"
    rules = [access_rule(method, path) for method, path, _ in routes]
    assert rules.count("admin token") >= 12 and rules.count("session token") >= 8


def test_admin_routes_refuse_missing_malformed_wrong_and_participant_tokens(two_studies):
    client, admin, alice, _ = two_studies
    with client.app.state.services.sessionmaker.begin() as session:
        current = rotate_admin_token(session, utcnow())  # the first token is revoked now
    refused = {
        "no header": {},
        "empty header": {"Authorization": ""},
        "scheme only": {"Authorization": "Bearer"},
        "other scheme": {"Authorization": "Basic " + base64.b64encode(f"admin:{current}".encode()).decode()},
        "no scheme": {"Authorization": current},
        "made-up token": {"Authorization": "Bearer tla_" + secrets.token_urlsafe(32)},
        "truncated token": {"Authorization": f"Bearer {current[:-1]}"},
        "revoked token": auth(admin),
        "participant token": auth(alice["token"]),
    }
    values = {"slug": "s1", "public_id": public_id_of(client, alice["token"]), "name": "trials.csv"}
    admin_routes = [(m, p) for m, p, _ in app_routes(client.app) if access_rule(m, p) == "admin token"]
    for method, path in admin_routes:
        url = fill(path, **values)
        # POST /api/admin/report-access gave this client the report-reading cookie (test_report.py tests what it
        # opens): each route here is tried without it.
        client.cookies.clear()
        for what, headers in refused.items():
            response = client.request(method, url, headers=headers, json={})
            assert response.status_code == 401, f"{method} {path} with {what}: {response.status_code} {response.text}"
            assert response.json().keys() == {"detail", "code"} and "admin" in response.json()["detail"], what
            assert response.headers["www-authenticate"] == "Bearer"
        query = client.request(method, url + f"?token={current}&access_token={current}", json={})
        assert query.status_code == 401, f"{method} {path} took the token from the query string"
        assert client.request(method, url, headers=auth(current), json={}).status_code != 401, f"{method} {path}"


def test_a_session_token_reaches_only_its_own_session(two_studies):
    client, admin, alice, bob = two_studies
    alice_id, bob_id = public_id_of(client, alice["token"]), public_id_of(client, bob["token"])

    def alice_now():
        state = client.get(f"/api/p/{alice['token']}/state").json()
        with client.app.state.services.sessionmaker() as session:
            pid = session.scalar(select(Participant.id).where(Participant.public_id == alice_id))
            rows = [len(session.scalars(select(t).where(t.participant_id == pid)).all())
                    for t in (Trial, Answer, Event)]
        return {k: v for k, v in state.items() if k != "server_time"}, rows

    before = alice_now()
    secrets_of_alice = [alice["token"], alice_id, "alice-ext"]
    made_up = ["x" * 32, secrets.token_urlsafe(24),
               alice["token"][:-2] + ("AA" if alice["token"][-2:] != "AA" else "BB"),
               alice_id, admin, hash_token(alice["token"])[:40]]
    session_routes = [(m, p) for m, p, _ in app_routes(client.app) if access_rule(m, p) == "session token"]
    for method, path in session_routes:
        body = SESSION_BODIES.get(path.removeprefix(SESSION_PREFIX), {})
        if method == "WEBSOCKET":
            for token in made_up:
                with (pytest.raises(WebSocketDisconnect) as closed,
                      client.websocket_connect(fill(path, token=token)) as ws):
                    ws.receive_text()
                assert closed.value.code == 4404, f"{path} with a made-up token"
            continue
        for token in made_up:  # unknown (404), or not even shaped like a token (422): a reason, no data
            response = client.request(method, fill(path, token=token), json=body)
            expected = 404 if 16 <= len(token) <= 128 else 422
            assert response.status_code == expected, (f"{method} {path} with {token!r}: "
                                                      f"{response.status_code} {response.text}")
            assert response.json().keys() <= {"detail", "code", "problems", "message"}  # message: a catalogue key
            assert not any(s in response.text for s in secrets_of_alice[1:]), f"{method} {path}"
        response = client.request(method, fill(path, token=bob["token"]), json=body)  # bob acts on his own session
        assert response.status_code < 500 and not any(s in response.text for s in secrets_of_alice), f"{method} {path}"
    assert alice_now() == before, "another session's requests changed alice's session"
    assert client.get(f"/api/p/{bob['token']}/state").json()["phase"] != "consent"  # bob's own requests did count
    assert bob_id not in client.get(f"/api/p/{alice['token']}/state").text


def test_pages_and_the_viewer_give_nothing_for_unknown_tokens(two_studies):
    client, _, alice, _ = two_studies
    real, fake = client.get(f"/p/{alice['token']}"), client.get("/p/" + "x" * 32)
    assert real.status_code == fake.status_code == 200 and real.content == fake.content  # a static page, no data
    assert real.headers["referrer-policy"] == "no-referrer" and real.headers["cache-control"] == "no-store"
    with client:  # the viewer manager runs in the app's lifespan
        for token in ("x" * 32, secrets.token_urlsafe(24), "short"):
            for path in ("/viewer/{token}/", "/viewer/{token}"):
                response = client.get(fill(path, token=token), follow_redirects=False)
                assert response.status_code == 404 and response.json()["code"] == "not_found", path
            with pytest.raises(WebSocketDisconnect) as closed, \
                    client.websocket_connect(f"/viewer/{token}", subprotocols=[SUBPROTOCOL]) as ws:
                ws.receive_bytes()
            assert closed.value.code == 4404
        assert client.get(f"/viewer/{alice['token']}", follow_redirects=False).status_code == 307


def test_tokens_are_long_random_and_unrelated(database_url, sqlite_template, tmp_path):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    tokens = [join(client)["token"] for _ in range(20)]
    assert len(set(tokens)) == len(tokens)
    for token in tokens:
        assert set(token) <= URL_SAFE and len(token) * 6 >= 128, token  # >= 128 random bits (SPEC §10)
    assert len(set("".join(tokens))) > 50  # the whole url-safe alphabet shows up: not a counter or a timestamp
    assert admin.startswith("tla_") and len(admin.removeprefix("tla_")) * 6 >= 256

    # An external id with its browser's resume key resumes its own session: same token again, another id another
    # token (test_join_claims: the id alone claims nothing) ...
    first, again, other = (join(client, PROLIFIC_PID=pid)["token"] for pid in ("p-1", "p-1", "p-2"))
    assert first == again != other and len(first) * 6 >= 128
    # ... derived with this installation's secret: the same study and id elsewhere give another token.
    path = tmp_path / "elsewhere.db"
    shutil.copy(sqlite_template, path)
    elsewhere, elsewhere_admin = make_client(database_url=f"sqlite:///{path}")
    make_study(elsewhere, elsewhere_admin)
    assert join(elsewhere, PROLIFIC_PID="p-1")["token"] != first
    with client.app.state.services.sessionmaker() as session:  # only hashes are stored
        stored = session.scalars(select(Participant.token_hash)).all()
    assert set(stored) == {hash_token(t) for t in tokens + [first, other]} and not set(stored) & set(tokens)


def test_the_token_secret_is_created_once_when_the_first_joins_race(database_url):
    """The first joins of a new installation create the secret that resumable tokens derive from (it was a 500
    on PostgreSQL: both inserted it). The second transaction waits for the first and then uses its secret."""
    client, _ = make_client(database_url=database_url)
    factory, found = client.app.state.services.sessionmaker, {}

    def second() -> None:
        with factory.begin() as session:
            found["second"] = app_secret(session, "race_key")

    with factory.begin() as session:
        found["first"] = app_secret(session, "race_key")
        racer = threading.Thread(target=second)
        racer.start()
        time.sleep(0.3)  # let the second transaction get as far as it can (it waits for this one)
    racer.join(timeout=30)
    assert not racer.is_alive() and found["second"] == found["first"]


def test_tokens_never_reach_logs_exports_or_the_database(database_url, caplog):
    """A bot run against a real server with uvicorn's access log on: no participant token is written anywhere."""
    caplog.set_level(logging.INFO)
    with live_server(database_url, log_level="info") as live:
        assert live.admin("POST", "/api/admin/studies",
                          json={"status": "open", "slug": "s1",
                                "config": fast_config().model_dump(mode="json")}).status_code == 201
        summary = live.bots("s1", participants=2)
        assert summary.errors == [] and summary.completed == 2
        # the bots' tokens (joining again with their external ids and resume keys resumes them) and one anonymous
        # session
        tokens = [live.admin("POST", "/api/studies/s1/join", params={"PROLIFIC_PID": f"bot-0-{i:05d}"},
                             json={"resume_key": bot_resume_key(f"bot-0-{i:05d}")}).json()["token"] for i in range(2)]
        anonymous = live.admin("POST", "/api/studies/s1/join").json()["token"]
        tokens.append(anonymous)
        for method, what, body in (("GET", "state", None), ("POST", "heartbeat", {}),
                                   ("POST", "camera", {"view": "world"}),
                                   ("POST", "events", {"events": [{"kind": "probe", "payload": {"v": 1}}]})):
            assert live.admin(method, f"/api/p/{anonymous}/{what}", json=body).status_code == 200
        exported = live.admin("GET", "/api/admin/studies/s1/export.zip")
        assert exported.status_code == 200
    lines = [record.getMessage() for record in caplog.records if not record.name.startswith(CLIENT_LOGGERS)]
    assert any('"GET /api/p/…/state' in line for line in lines), "the access log was not captured"
    assert any("WebSocket /api/p/…/teleop" in line for line in lines), "the websocket log was not captured"
    assert not [line for line in lines if any(token in line for token in tokens)], "a token was logged"
    assert not [line for line in lines if "bot-0-0000" in line], "an external id (a session key) was logged"

    with zipfile.ZipFile(io.BytesIO(exported.content)) as archive:
        files = {name: archive.read(name).decode("utf-8") for name in archive.namelist()}
    assert "trials.csv" in files and files["trials.csv"].count("\n") > 20
    for name, text in files.items():
        assert not any(token in text for token in tokens), f"a token is in the exported {name}"

    engine = create_engine(database_url)
    try:
        metadata = MetaData()
        metadata.reflect(engine)
        with engine.connect() as conn:
            cells = "\n".join(repr(tuple(row)) for table in metadata.sorted_tables
                              for row in conn.execute(table.select()))
    finally:
        engine.dispose()
    assert "teleop_log" in cells  # the events table was read
    assert not any(token in cells for token in tokens), "a token is stored in the database"
