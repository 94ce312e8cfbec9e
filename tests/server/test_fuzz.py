"""Property-based fuzzing of the whole HTTP API from its live OpenAPI schema (schemathesis).

Every operation in ``/openapi.json`` (so every route added later too) gets generated
requests, valid and invalid, sent with a valid admin token and with the path
parameters of a real study, participant and session, so that the requests get past
404 into the handlers. Each response must pass every schemathesis check: no 5xx,
a documented status code, a body matching the documented schema, the documented
content type, schema-violating requests refused and schema-valid ones not refused
(except for the documented reasons below), the admin token actually checked.

Each operation runs on a fresh database (SQLite; the PostgreSQL behaviour of the
same handlers is covered by the other server tests), derandomized, so a run is
reproducible and its cost bounded.
"""

from __future__ import annotations

import itertools
import shutil
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import schemathesis
from fastapi import FastAPI
from hypothesis import HealthCheck, settings
from schemathesis.checks import positive_data_acceptance
from schemathesis.config import OperationConfig, OperationsConfig

from server.main import create_app
from server.services.studies import RuntimeCache
from server.settings import Settings
from tests.server.factories import app_routes, auth, join, make_client, make_study

#: The app's live schema (built without starting the app or touching a database). Requests go to each test's own
#: app (``Target.app``), on a fresh database per operation.
schema = schemathesis.openapi.from_dict(create_app(Settings(database_url="sqlite://", world_loop=False)).openapi())
schema.config.seed = 6  # with derandomize below: the same requests on every run (schemathesis' default seed is random)
#: Creating a study and replacing its config take the same study config document, which StudyConfig checks the same
#: way in both. Its coverage phase (schemathesis' sweep of each field's bounds and wrong types, ~1,600 requests built
#: at collection in every test process) runs on the replacement only; the creation keeps the examples and fuzzing.
schema.config.operations = OperationsConfig(operations=[OperationConfig.from_dict(
    {"include-name": "POST /api/admin/studies", "phases": {"coverage": {"enabled": False}}})])

#: A study config document is checked by StudyConfig's cross-field rules and by solving its policies, which no
#: JSON schema expresses: a schema-valid document may still be refused with a 422 that lists the problems.
CONFIG_DOCUMENT_OPERATIONS = {"POST /api/admin/studies", "PUT /api/admin/studies/{slug}/config"}
#: An event's payload is bounded as a whole (bytes of compact JSON, nesting depth, integer range: see EventCreate),
#: which its JSON schema (a free-form object) cannot say: a schema-valid payload may be refused with a 422 naming
#: the bound (tests/server/test_hostile_events.py tests each bound).
BOUNDED_AS_A_WHOLE_OPERATIONS = {"POST /api/p/{token}/events"}

#: Participant operations and the phase the session must be at for them to do something (default: practice).
PHASE_FOR = {"/api/p/{token}/consent": "consent", "/api/p/{token}/instructions/done": "instructions"}


@dataclass
class Target:
    app: FastAPI
    admin: str
    slug: str
    tokens: dict[str, str]  # phase -> token of a session at that phase
    public_id: str
    keys: itertools.count

    def path_parameters(self, path: str, generated: dict[str, object]) -> dict[str, object]:
        """The generated path parameters with the real study, participant and session put in."""
        real = {"slug": self.slug, "public_id": self.public_id, "token": self.tokens[PHASE_FOR.get(path, "practice")]}
        return {name: real.get(name, value) for name, value in generated.items()}


@pytest.fixture(scope="module")
def runtimes() -> RuntimeCache:
    """Solved study policies, shared by the apps of this module (keyed by config hash, so sharing is safe)."""
    return RuntimeCache()


@pytest.fixture
def target(sqlite_template: Path, tmp_path: Path, runtimes: RuntimeCache) -> Target:
    path = tmp_path / "fuzz.db"
    shutil.copy(sqlite_template, path)
    # join is rate-limited per client address; the fuzzer's joins (all from one test client) must get through
    client, admin = make_client(database_url=f"sqlite:///{path}", join_rate_limit_per_ip=100_000,
                                join_rate_limit_per_study=100_000)
    client.app.state.services = replace(client.app.state.services, runtimes=runtimes)
    make_study(client, admin, slug="fuzz")
    tokens = {"consent": join(client, "fuzz")["token"], "instructions": join(client, "fuzz")["token"]}
    assert client.post(f"/api/p/{tokens['instructions']}/consent", json={"agree": True}).status_code == 200
    tokens["practice"] = join(client, "fuzz", PROLIFIC_PID="fuzzer")["token"]
    for step in ("consent", "instructions/done"):
        response = client.post(f"/api/p/{tokens['practice']}/{step}",
                               json={"agree": True} if step == "consent" else None)
        assert response.status_code == 200, response.text
    people = client.get("/api/admin/studies/fuzz/participants", headers=auth(admin)).json()
    assert [p["phase"] for p in people] == ["consent", "instructions", "practice"]
    return Target(client.app, admin, "fuzz", tokens, people[-1]["public_id"], itertools.count())


@schema.parametrize()
@settings(max_examples=20, derandomize=True, deadline=None, database=None, print_blob=False,
          suppress_health_check=list(HealthCheck))
def test_api(case, target: Target) -> None:
    case.path_parameters = target.path_parameters(case.path, case.path_parameters)
    if case.headers and isinstance(case.headers.get("Idempotency-Key"), str):
        # a key reused with another body is refused by design (422, see test_api); each example gets its own
        key = f"{next(target.keys)}-{case.headers['Idempotency-Key']}"[:128]
        case.headers = {**case.headers, "Idempotency-Key": key}
    case.operation.app = case.operation.schema.app = target.app  # also for the checks that send requests of their own
    refused_beyond_the_schema = CONFIG_DOCUMENT_OPERATIONS | BOUNDED_AS_A_WHOLE_OPERATIONS
    excluded = [positive_data_acceptance] if case.operation.label in refused_beyond_the_schema else []
    case.call_and_validate(headers=auth(target.admin), excluded_checks=excluded)


def test_every_api_route_is_fuzzed():
    """The fuzzed operations are exactly the app's routes under /api/ (none can be left out of the schema)."""
    app = create_app(Settings(database_url="sqlite://", world_loop=False))
    api_routes = {f"{method} {path}" for method, path, _ in app_routes(app) if path.startswith("/api/")}
    fuzzed = {operation.ok().label for operation in schemathesis.openapi.from_dict(app.openapi()).get_all_operations()}
    assert fuzzed == api_routes - {"WEBSOCKET /api/p/{token}/teleop"}  # the socket is tested in test_trials
    assert {"POST /api/studies/{slug}/join", "GET /api/admin/studies"} <= fuzzed


def test_each_operation_is_a_test_of_its_own_id(request: pytest.FixtureRequest):
    """The suite runs in two processes (pytest-xdist), which know a test by its id and run one test of each id:
    every fuzzed operation's test must have an id of its own (``tests/conftest.py`` gives them back their names).

    The ids are this run's own when its collection holds every fuzzed operation (the suite or this file: each xdist
    process collects every test); else (this test alone, a -k) a subprocess collects them, which takes 15-30 s."""
    operations = {operation.ok().label for operation in schema.get_all_operations()}
    module = request.node.nodeid.partition("::")[0]
    ids = [item.nodeid for item in request.session.items if item.nodeid.startswith(f"{module}::test_api")]
    if {nodeid.partition("[")[2].removesuffix("]") for nodeid in ids} != operations:
        collected = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-n", "0", "-p",
                                    "no:cacheprovider",
                                    f"{Path(__file__).name}::test_api"], cwd=Path(__file__).parent,
                                   capture_output=True, text=True, timeout=120)
        assert collected.returncode == 0, collected.stdout[-2000:] + collected.stderr[-2000:]
        ids = [line for line in collected.stdout.splitlines() if "::test_api" in line]
    assert len(ids) == len(set(ids)) == len(operations)
    assert {nodeid.partition("[")[2].removesuffix("]") for nodeid in ids} == operations
