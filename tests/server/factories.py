"""Plain keyword-only helpers that build apps, studies and participants for tests."""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient

from experiment.config import StudyConfig
from experiment.templates import demo, demo_fast
from server.main import create_app
from server.services.admin import ensure_admin_token
from server.settings import Settings

def make_client(*, database_url: str, **settings: Any) -> tuple[TestClient, str]:
    """A TestClient on a fresh app (world loop off unless asked) and its admin token."""
    app = create_app(Settings(database_url=database_url, world_loop=settings.pop("world_loop", False), **settings))
    with app.state.sessionmaker.begin() as session:
        token = ensure_admin_token(session)
    assert token is not None
    return TestClient(app), token


def fast_config(config: StudyConfig | None = None, **changes: Any) -> StudyConfig:
    """A study that runs fast (short decision window, sped-up robot) for API tests."""
    config = config or demo()
    return config.model_copy(update={"timing": demo_fast().timing, **changes})


def make_study(client: TestClient, admin_token: str, *, config: StudyConfig | None = None, slug: str = "s1") -> dict:
    response = client.post("/api/admin/studies", json={"slug": slug, "config": (config or fast_config()).model_dump(mode="json")},
                           headers=auth(admin_token))
    assert response.status_code == 201, response.text
    return response.json()


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def join(client: TestClient, slug: str = "s1", **params: str) -> dict:
    response = client.post(f"/api/studies/{slug}/join", params=params)
    assert response.status_code == 200, response.text
    return response.json()
