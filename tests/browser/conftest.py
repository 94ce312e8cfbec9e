"""Browser tests: the real app served by uvicorn in a thread, driven by Debian's Chromium via Playwright.

Never downloads a browser: Chromium must be at ``CHROMIUM`` (``.ci/run`` installs Debian's
``chromium`` package). Each test gets a fresh migrated SQLite database, its own server on a
free loopback port and a fresh browser profile.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from playwright.sync_api import BrowserContext, Playwright, sync_playwright

from experiment.config import StudyConfig
from server.harness.browser import CHROMIUM, browser_session
from server.harness.live import BOT_TELEOP_SETTINGS
from server.harness.live import live_server as start_live_server
from server.settings import Settings


@dataclass
class LiveServer:
    app: FastAPI
    url: str
    admin_token: str
    http: httpx.Client

    def admin(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return self.http.request(method, path, headers={"Authorization": f"Bearer {self.admin_token}"}, **kwargs)

    def create_study(self, slug: str, config: StudyConfig) -> dict[str, Any]:
        response = self.admin("POST", "/api/admin/studies",
                              json={"status": "open", "slug": slug, "config": config.model_dump(mode="json")})
        assert response.status_code == 201, response.text
        return response.json()

    def api(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return self.http.request(method, path, **kwargs)


@contextmanager
def serving(sqlite_template: Path, tmp_path: Path, **settings: Any) -> Iterator[LiveServer]:
    """The app as deployed (``settings`` aside) on a copy of the migrated database."""
    path = tmp_path / "trustlab.db"
    shutil.copy(sqlite_template, path)
    production = {name: Settings.model_fields[name].default for name in BOT_TELEOP_SETTINGS}  # the page as deployed
    with (start_live_server(f"sqlite:///{path}", **production | settings) as live,
          httpx.Client(base_url=live.url, timeout=10) as http):
        yield LiveServer(live.app, live.url, live.admin_token, http)


@pytest.fixture
def live_server(sqlite_template: Path, tmp_path: Path) -> Iterator[LiveServer]:
    with serving(sqlite_template, tmp_path) as live:
        yield live


#: The test process's Playwright while it runs browser tests: started by the first, stopped when the process moves
#: on to a test outside tests/browser. Playwright's sync API runs an asyncio loop in the main thread, so a test of
#: another folder (asyncio.run) must not find it running; within the folder it starts once.
_PLAYWRIGHT: list[Playwright] = []
BROWSER_DIR = Path(__file__).resolve().parent


@pytest.fixture
def playwright() -> Playwright:
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: install Debian's chromium package (.ci/run does)")
    if not _PLAYWRIGHT:
        _PLAYWRIGHT.append(sync_playwright().start())
    return _PLAYWRIGHT[0]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """After a browser test's fixtures are torn down: stop Playwright when the next test is not a browser test."""
    yield
    if _PLAYWRIGHT and (nextitem is None or BROWSER_DIR not in Path(nextitem.path).resolve().parents):
        _PLAYWRIGHT.pop().stop()


@pytest.fixture
def browser(playwright: Playwright, tmp_path: Path) -> Iterator[BrowserContext]:
    """A fresh Chromium profile at 1280×720."""
    with browser_session(tmp_path / "profile", playwright=playwright) as context:
        context.set_default_timeout(20_000)
        yield context
