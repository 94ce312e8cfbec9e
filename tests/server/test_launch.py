"""Serving the app (``server.launch``): what is done before the first participant's request."""

from __future__ import annotations

import shutil

import fastapi.routing

from server.launch import build_routes
from tests.server.factories import make_client


def test_every_route_is_built_before_serving_so_no_request_builds_one(sqlite_template, tmp_path, monkeypatch):
    """This FastAPI builds an included router's routes on its first request (70-100 ms event-loop stalls under
    load); ``run_server`` builds them all first: a request then builds nothing, on any router."""
    shutil.copy(sqlite_template, tmp_path / "launch.db")
    client, admin = make_client(database_url=f"sqlite:///{tmp_path / 'launch.db'}")
    assert build_routes(client.app) >= 5  # the participant, admin, viewer, teleoperation... routers

    def built_on_a_request(*args, **kwargs):
        raise AssertionError("a route was built on a request")

    monkeypatch.setattr(fastapi.routing._IncludedRouter, "_build_effective_context", built_on_a_request)
    with client:
        assert client.get("/api/p/" + "x" * 32 + "/state").status_code == 404  # a participant route, matched
        assert client.get("/api/admin/studies", headers={"Authorization": f"Bearer {admin}"}).status_code == 200
        assert client.get("/api/schema/teleop.json").status_code == 200
        assert build_routes(client.app) >= 5  # built already: nothing to build again


def test_without_building_first_a_request_builds_its_router(sqlite_template, tmp_path, monkeypatch):
    """The check above can fail: the same requests without ``build_routes`` build routers as they come."""
    shutil.copy(sqlite_template, tmp_path / "lazy.db")
    client, _ = make_client(database_url=f"sqlite:///{tmp_path / 'lazy.db'}")
    built = []
    build = fastapi.routing._IncludedRouter._build_effective_context
    monkeypatch.setattr(fastapi.routing._IncludedRouter, "_build_effective_context",
                        lambda self, route: built.append(route) or build(self, route))
    with client:
        assert client.get("/api/p/" + "x" * 32 + "/state").status_code == 404
    assert built
