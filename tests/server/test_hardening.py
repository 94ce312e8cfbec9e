"""Hardening against a hostile or broken client, and against a broken host (issue 36): every page served with
its security headers, nothing with participants' data cached, docs without a CDN, random completion codes,
private database files, a full disk answered 503, one server per SQLite file, proxy headers believed only from
the configured proxy, and bounded slow requests."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, text

from server.harness.live import free_port, start_server
from server.main import create_app
from server.routes.pages import STATIC_DIR
from server.services.completion_codes import PUBLIC_DEFAULT_CODES
from server.settings import Settings
from tests.server.factories import app_routes, auth, fast_config, join, make_client, make_study

#: What every HTML response must carry (server.http_headers.PAGE_HEADERS; each page its own policy).
PAGE_HEADER_NAMES = ("content-security-policy", "x-content-type-options", "referrer-policy", "cache-control")
#: The pages there are; the enumeration below must find each of them serving HTML.
KNOWN_PAGES = {"/admin", "/join/{slug}", "/p/{token}", "/viewer/{token}/", "/docs"}


def _fill(path: str, token: str) -> str:
    values = {"slug": "s1", "token": token, "model_id": "1", "name": "trials.csv"}
    return re.sub(r"\{(\w+)(?::\w+)?\}", lambda m: values.get(m.group(1), "1"), path)


def _check_page_headers(response, where: str) -> None:
    for name in PAGE_HEADER_NAMES:
        assert name in response.headers, f"{where}: no {name}"
    assert response.headers["cache-control"] == "no-store", where
    assert response.headers["x-content-type-options"] == "nosniff", where
    assert "frame-ancestors" in response.headers["content-security-policy"], where


def test_every_route_and_static_file_that_serves_html_carries_the_page_headers(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    token = join(client)["token"]
    html = set()
    with client:  # the viewer's page needs the app's lifespan (its view manager)
        for method, path, _ in app_routes(client.app):
            if method != "GET":
                continue
            response = client.get(_fill(path, token), headers=auth(admin), follow_redirects=False)
            if response.headers.get("content-type", "").startswith("text/html"):
                html.add(path)
                _check_page_headers(response, path)
        served = []
        for file in sorted(p for p in STATIC_DIR.rglob("*") if p.is_file()):
            response = client.get("/static/" + file.relative_to(STATIC_DIR).as_posix())
            if file.suffix in (".html", ".htm"):
                assert response.status_code == 404 and response.json()["code"] == "not_found", file
            assert not response.headers.get("content-type", "").startswith("text/html"), file
            served.append(response.status_code == 200)
    assert KNOWN_PAGES <= html, KNOWN_PAGES - html
    assert sum(served) >= 20  # the scripts, styles and vendored libraries are still there


def test_api_docs_are_self_hosted_from_pinned_files_or_off(database_url):
    client, _ = make_client(database_url=database_url)
    page = client.get("/docs")
    assert page.status_code == 200
    assert "http://" not in page.text and "https://" not in page.text  # no CDN, no floating version
    assets = re.findall(r'(?:src|href)="(/static/[^"]+)"', page.text)
    assert len(assets) == 2
    for asset in assets:
        assert client.get(asset).status_code == 200, asset
    pinned = (STATIC_DIR / "vendor" / "swagger-ui" / "VERSION").read_text()
    assert re.search(r"swagger-ui-dist \d+\.\d+\.\d+", pinned)
    assert client.get("/redoc").status_code == 404  # FastAPI's other docs page loads a CDN's latest version
    off = TestClient(create_app(Settings(database_url=database_url, world_loop=False, api_docs=False)))
    response = off.get("/docs")
    assert response.status_code == 404 and response.json()["code"] == "not_found"
    assert off.get("/openapi.json").status_code == 200


def test_participant_and_admin_responses_and_the_view_are_never_cached(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    joined = client.post("/api/studies/s1/join")
    token = joined.json()["token"]
    responses = {"join": joined, "state": client.get(f"/api/p/{token}/state"),
                 "unknown session": client.get("/api/p/" + "x" * 32 + "/state"),
                 "admin": client.get("/api/admin/studies", headers=auth(admin)),
                 "admin refused": client.get("/api/admin/studies"),
                 "export": client.get("/api/admin/studies/s1/export/participants.csv", headers=auth(admin))}
    with client:
        responses["view"] = client.get(f"/viewer/{token}/")
    for name, response in responses.items():
        assert response.headers.get("cache-control") == "no-store", name
    assert client.get("/static/js/api.js").headers.get("cache-control") != "no-store"  # scripts may be cached


# -- completion codes ------------------------------------------------------------------------------------------------

def test_a_study_gets_completion_codes_of_its_own_in_place_of_the_public_defaults(database_url):
    client, admin = make_client(database_url=database_url)
    first = make_study(client, admin, slug="s1")["config"]["completion"]
    second = make_study(client, admin, slug="s2")["config"]["completion"]
    for name, public in PUBLIC_DEFAULT_CODES.items():
        assert first[name] != public and second[name] != public and first[name] != second[name], name
        assert re.fullmatch(r"[A-Z2-9]{10}", first[name])
    token = join(client)["token"]
    declined = client.post(f"/api/p/{token}/consent", json={"agree": False}).json()
    assert declined["completion"]["code"] == first["code_declined"]
    # a new version with the defaults again (from a template) keeps the study's codes; a lab's own code is kept
    again = fast_config().model_dump(mode="json")
    again["completion"]["code_completed"] = "LAB-OWN-1"
    again["shelf_size"] += 1
    saved = client.put("/api/admin/studies/s1/config", json={"config": again}, headers=auth(admin))
    assert saved.status_code == 200, saved.text
    now = client.get("/api/admin/studies/s1", headers=auth(admin)).json()["config"]["completion"]
    assert now == first | {"code_completed": "LAB-OWN-1"}


# -- private database files ------------------------------------------------------------------------------------------

def _mode(path: Path) -> int:
    return path.stat().st_mode & 0o777


def test_sqlite_database_its_wal_and_backups_are_readable_by_their_owner_only(tmp_path, monkeypatch):
    from server.db.migrate import upgrade
    from server.services.backup import backup_sqlite

    monkeypatch.setattr(os, "umask", os.umask)  # the umask is restored below whatever happens
    old = os.umask(0o022)  # a usual umask: files readable by everyone unless created otherwise
    try:
        path = tmp_path / "lab.db"
        upgrade(f"sqlite:///{path}")
        client, admin = make_client(database_url=f"sqlite:///{path}")
        make_study(client, admin)
        join(client)  # a write: the -wal and -shm files exist while the app's connections are open
        files = [path, *(path.with_name(path.name + s) for s in ("-wal", "-shm"))]
        assert all(f.exists() for f in files)
        assert {f.name: _mode(f) for f in files} == {f.name: 0o600 for f in files}
        done = backup_sqlite(path, tmp_path / "backups" / "lab-backup.db")
        assert _mode(done.path) == 0o600
        client.app.state.services.engine.dispose()
        os.chmod(path, 0o644)  # a database made before this change is made private when it is migrated
        upgrade(f"sqlite:///{path}")
        assert _mode(path) == 0o600
    finally:
        os.umask(old)


# -- a full disk -----------------------------------------------------------------------------------------------------

def _fill_the_disk(client: TestClient, database_url: str) -> None:
    """Every write from now on fails as on a full disk: SQLite's page limit at the database's size (SQLITE_FULL),
    PostgreSQL's disk_full (53100) raised by a trigger on the participant table."""
    engine = client.app.state.services.engine
    if database_url.startswith("sqlite"):
        @event.listens_for(engine, "connect")
        def no_more_pages(dbapi_connection, _record):
            pages = dbapi_connection.execute("PRAGMA page_count").fetchone()[0]
            dbapi_connection.execute(f"PRAGMA max_page_count = {pages}")
        engine.dispose()
        return
    with engine.begin() as connection:
        connection.execute(text("CREATE FUNCTION disk_full() RETURNS trigger AS $$ BEGIN RAISE EXCEPTION "
                                "'could not extend file: No space left on device' USING ERRCODE = 'disk_full'; "
                                "END $$ LANGUAGE plpgsql"))
        connection.execute(text("CREATE TRIGGER disk_full BEFORE INSERT ON participant "
                                "FOR EACH ROW EXECUTE FUNCTION disk_full()"))


def test_a_full_disk_is_a_503_with_retry_after_not_a_bare_500(database_url):
    client, admin = make_client(database_url=database_url, join_rate_limit_per_ip=10_000)
    make_study(client, admin)
    _fill_the_disk(client, database_url)
    client = TestClient(client.app, raise_server_exceptions=False)
    for _ in range(2_000):  # SQLite: joins until the free space of the database's last pages is used
        response = client.post("/api/studies/s1/join")
        if response.status_code != 200:
            break
    assert response.status_code == 503, response.text
    assert response.json() == {"detail": "the server's disk is full: nothing was saved; please try again in a minute",
                               "code": "disk_full"}
    assert int(response.headers["retry-after"]) > 0


# -- a real `trustlab serve`: one server per SQLite file, proxy headers, slow request heads ---------------------------

#: The served server's join limit per address and its deadline for a request head, low so that tests are quick.
SERVED_ENV = {"TRUSTLAB_JOIN_RATE_LIMIT_PER_IP": "3", "TRUSTLAB_REQUEST_HEAD_TIMEOUT_S": "1"}


@dataclass
class Served:
    process: subprocess.Popen
    port: int
    database: Path


@pytest.fixture(scope="module")
def served(tmp_path_factory) -> Iterator[Served]:
    """``trustlab serve`` on a new SQLite file (only SQLite has a file to lock; the rest is the same on both)."""
    root = tmp_path_factory.mktemp("served")
    database, port = root / "lab.db", free_port()
    with open(root / "server.log", "w+", encoding="utf-8") as log:
        process, _ = start_server(f"sqlite:///{database}", port, log, env=SERVED_ENV)
        try:
            yield Served(process, port, database)
        finally:
            process.terminate()
            process.wait(timeout=30)


def test_a_second_server_on_the_same_sqlite_file_refuses_to_start_and_names_the_first(served):
    second = subprocess.run([sys.executable, "-c", "from server.cli import app; app()", "serve", "--port",
                             str(free_port()), "--database-url", f"sqlite:///{served.database}"],
                            capture_output=True, text=True, timeout=120, env=os.environ | SERVED_ENV)
    assert second.returncode == 2, second.stdout + second.stderr
    assert f"process {served.process.pid}" in second.stderr and str(served.database.resolve()) in second.stderr
    assert "admin page:" not in second.stdout  # refused before serving anything
    assert httpx.get(f"http://127.0.0.1:{served.port}/api/ready-check").status_code == 404  # the first still serves


def test_x_forwarded_for_is_believed_from_no_one_unless_a_proxy_is_configured(served):
    """The join limit (3 a minute here) counts the connection's address: forged headers do not make new clients."""
    statuses = [httpx.post(f"http://127.0.0.1:{served.port}/api/studies/demo/join",
                           headers={"X-Forwarded-For": f"203.0.113.{i}"}).status_code for i in range(4)]
    assert statuses == [200, 200, 200, 429]


def test_served_database_files_are_readable_by_their_owner_only(served):
    files = [served.database, *(served.database.with_name(served.database.name + s) for s in ("-wal", "-shm", ".lock"))]
    assert {f.name: _mode(f) for f in files} == {f.name: 0o600 for f in files}


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    """Whether the server closes ``sock`` within ``seconds`` (what it still sends first is read and dropped)."""
    sock.settimeout(seconds)
    try:
        while sock.recv(4096):
            pass
        return True
    except TimeoutError:
        return False


def test_a_connection_that_never_completes_its_request_head_is_closed(served):
    silent = socket.create_connection(("127.0.0.1", served.port))
    half = socket.create_connection(("127.0.0.1", served.port))
    kept = socket.create_connection(("127.0.0.1", served.port))
    with silent, half, kept:
        half.sendall(b"GET /api/ready-check HTTP/1.1\r\nHost: x\r\n")  # the blank line that ends the head never comes
        kept.sendall(b"GET /api/ready-check HTTP/1.1\r\nHost: x\r\n\r\n")
        kept.settimeout(10)
        assert kept.recv(1024).startswith(b"HTTP/1.1 404")
        assert _closed_within(silent, 5) and _closed_within(half, 5)  # deadline 1 s here (10 s by default)
        kept.sendall(b"GET /api/ready-check HTTP")  # a kept-alive connection's next head has the same deadline
        assert _closed_within(kept, 5)
    assert httpx.get(f"http://127.0.0.1:{served.port}/api/ready-check").status_code == 404  # others are served


def test_proxy_headers_are_believed_only_from_the_configured_proxies(monkeypatch, sqlite_template, tmp_path):
    """``run_server``'s uvicorn options: alone, none by default or the setting's; behind the group's nginx, its own."""
    import shutil

    import uvicorn

    from server import launch

    shutil.copy(sqlite_template, tmp_path / "proxy.db")
    options: list[dict] = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **kwargs: options.append(kwargs))
    monkeypatch.setattr(launch, "tune_process", lambda: None)  # not in the test process (gc.freeze)
    for allowed in ([], ["10.0.0.5"]):
        app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'proxy.db'}", world_loop=False,
                                  view_process=False, forwarded_allow_ips=allowed))
        launch.run_server(app, host="127.0.0.1", port=8000)
        launch.run_server(app, uds=str(tmp_path / "w.sock"))
        launch.run_server(app, host="127.0.0.1", port=8001, trusted_proxies=["127.0.0.1"])
    alone, unix, worker, alone_behind, *_ = options
    assert alone["proxy_headers"] is False and "forwarded_allow_ips" not in alone
    assert (alone_behind["proxy_headers"], alone_behind["forwarded_allow_ips"]) == (True, ["10.0.0.5"])
    assert (unix["proxy_headers"], unix["forwarded_allow_ips"]) == (True, "*")  # only nginx reaches the socket
    assert (worker["proxy_headers"], worker["forwarded_allow_ips"]) == (True, ["127.0.0.1"])
