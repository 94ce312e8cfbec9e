"""Browser tests: the real app served by uvicorn in a thread, driven by Debian's Chromium via Playwright.

Never downloads a browser: Chromium must be at ``CHROMIUM`` (``.ci/run`` installs Debian's
``chromium`` package). Each test gets a fresh migrated SQLite database, its own server on a
free loopback port and a fresh browser profile.
"""

from __future__ import annotations

import shutil
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from playwright.sync_api import BrowserContext, Playwright, sync_playwright

from experiment.config import StudyConfig
from server.main import create_app
from server.services.admin import ensure_admin_token
from server.settings import Settings

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-quic"]
VIEWPORT = {"width": 1280, "height": 720}


@dataclass
class LiveServer:
    app: FastAPI
    url: str
    admin_token: str
    http: httpx.Client

    def admin(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return self.http.request(method, path, headers={"Authorization": f"Bearer {self.admin_token}"}, **kwargs)

    def create_study(self, slug: str, config: StudyConfig) -> dict[str, Any]:
        response = self.admin("POST", "/api/admin/studies", json={"slug": slug, "config": config.model_dump(mode="json")})
        assert response.status_code == 201, response.text
        return response.json()

    def api(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return self.http.request(method, path, **kwargs)


def _free_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    return sock


@pytest.fixture
def live_server(sqlite_template: Path, tmp_path: Path) -> Iterator[LiveServer]:
    path = tmp_path / "trustlab.db"
    shutil.copy(sqlite_template, path)
    sock = _free_socket()
    port = sock.getsockname()[1]
    app = create_app(Settings(database_url=f"sqlite:///{path}", port=port))
    with app.state.sessionmaker.begin() as session:
        token = ensure_admin_token(session)
    assert token is not None
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on", ws="websockets-sansio"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + 15
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=10) as http:
            yield LiveServer(app, url, token, http)
    finally:
        server.should_exit = True
        thread.join(timeout=15)
        sock.close()
        assert not thread.is_alive(), "the server did not stop"


@pytest.fixture(scope="session")
def playwright() -> Iterator[Playwright]:
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: install Debian's chromium package (.ci/run does)")
    with sync_playwright() as p:
        yield p


@pytest.fixture
def browser(playwright: Playwright, tmp_path: Path) -> Iterator[BrowserContext]:
    """A fresh Chromium profile at 1280×720."""
    context = playwright.chromium.launch_persistent_context(
        str(tmp_path / "profile"), executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True,
        viewport=VIEWPORT, service_workers="block")
    context.set_default_timeout(20_000)
    try:
        yield context
    finally:
        context.close()
