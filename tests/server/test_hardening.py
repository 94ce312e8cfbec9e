"""Hardening against a hostile or broken client, and against a broken host (issue 36): every page served with
its security headers, nothing with participants' data cached, docs without a CDN, random completion codes,
private database files, a full disk answered 503, one server per SQLite file, proxy headers believed only from
the configured proxy, and bounded slow requests."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.main import create_app
from server.routes.pages import STATIC_DIR
from server.settings import Settings
from tests.server.factories import app_routes, auth, join, make_client, make_study

#: What every HTML response must carry (server.routes.pages.PAGE_HEADERS; each page its own policy).
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
