"""The participant and admin APIs: state machine, idempotency, errors, versions, abandonment."""

from datetime import timedelta

import pytest
from sqlalchemy import func, select

from experiment.flow import ShelfSurveyStep
from server.models import Answer, Participant, Trial, utcnow
from server.sweeper import sweep
from tests.server.factories import auth, fast_config, join, make_client, make_study


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    return client, admin


def post(client, token, what, body=None, key=None):
    return client.post(f"/api/p/{token}/{what}", json=body, headers={"Idempotency-Key": key} if key else {})


def to_practice(client, token):
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    state = post(client, token, "instructions/done").json()
    assert state["phase"] == "practice" and state["ready_to_start"] == {"practice": True, "block": 0, "trial": 1}
    return state


def count(client, model, **where):
    with client.app.state.services.sessionmaker() as session:
        query = select(func.count()).select_from(model)
        for column, value in where.items():
            query = query.where(getattr(model, column) == value)
        return session.scalar(query)


def test_state_machine_and_reload(api):
    client, admin = api
    # A decision window far longer than the test: the reload must find the trial still in it even on a loaded
    # machine (the fast config's 50 ms window could pass between the start and the reload).
    slow = fast_config()
    make_study(client, admin, slug="slow",
               config=slow.model_copy(update={"timing": slow.timing.model_copy(update={"decision_window_s": 60.0})}))
    token = join(client, "slow")["token"]
    state = client.get(f"/api/p/{token}/state").json()
    assert state["phase"] == "consent" and "research study" in state["text"]
    to_practice(client, token)
    first = post(client, token, "trials/start", {"practice": True, "block": 0, "trial": 1}).json()
    again = post(client, token, "trials/start", {"practice": True, "block": 0, "trial": 1}).json()
    assert first["trial"]["robot_action"] == again["trial"]["robot_action"] == "auto"
    assert count(client, Trial) == 1  # starting twice made one trial
    reloaded = client.get(f"/api/p/{token}/state").json()
    assert reloaded["step"] == first["step"] and reloaded["trial"]["trial"] == 1


def test_out_of_order_requests_get_409_with_a_reason(api):
    client, _ = api
    token = join(client)["token"]
    response = post(client, token, "instructions/done")
    assert response.status_code == 409 and "consent" in response.json()["detail"]
    post(client, token, "consent", {"agree": True})
    repeat = post(client, token, "consent", {"agree": True})
    assert repeat.status_code == 409
    response = post(client, token, "trials/start", {"practice": False, "block": 1, "trial": 1})
    assert response.status_code == 409 and "instructions" in response.json()["detail"]


def test_idempotency_key_replays_the_response(api):
    client, _ = api
    token = join(client)["token"]
    a = post(client, token, "consent", {"agree": True}, key="k1")
    b = post(client, token, "consent", {"agree": True}, key="k1")
    assert a.status_code == b.status_code == 200 and a.json() == b.json()
    different = post(client, token, "consent", {"agree": False}, key="k1")
    assert different.status_code == 422 and "different request" in different.json()["detail"]


def test_decline_ends_with_the_decline_code(api):
    client, admin = api
    token = join(client)["token"]
    state = post(client, token, "consent", {"agree": False}).json()
    code = client.get("/api/admin/studies/s1", headers=auth(admin)).json()["config"]["completion"]["code_declined"]
    assert state["phase"] == "declined" and state["completion"]["code"] == code


@pytest.mark.parametrize(("method", "path", "body", "status"), [
    ("get", "/api/p/{bad}/state", None, 404),
    ("post", "/api/p/{token}/consent", {"agree": "maybe"}, 422),
    ("post", "/api/p/{token}/consent", {"agree": True, "extra": 1}, 422),
    ("post", "/api/p/{token}/answers", {"questionnaire": "shelf_trust_reliance", "answers": {"trust": 5}}, 409),
    ("post", "/api/p/{token}/trials/start", {"block": -1, "trial": 1}, 422),
    ("post", "/api/studies/nope/join", None, 404),
    ("get", "/api/admin/studies", None, 401),
])
def test_bad_requests_get_a_4xx_with_a_reason(api, method, path, body, status):
    client, _ = api
    token = join(client)["token"]
    url = path.format(token=token, bad="x" * 32)
    response = getattr(client, method)(url, **({"json": body} if body is not None else {}))
    assert response.status_code == status, response.text
    assert response.json()["detail"]


def test_malformed_and_oversized_bodies(api):
    client, _ = api
    token = join(client)["token"]
    response = client.post(f"/api/p/{token}/consent", content=b"{not json",
                           headers={"content-type": "application/json"})
    assert response.status_code == 422
    huge = client.post(f"/api/p/{token}/events", content=b"x" * 400_000, headers={"content-type": "application/json"})
    assert huge.status_code == 413 and "larger than" in huge.json()["detail"]


def test_invalid_answers_name_the_problem(api):
    client, _ = api
    token = join(client)["token"]
    to_practice(client, token)
    with client.app.state.services.sessionmaker.begin() as session:  # jump to the first shelf survey
        participant = session.scalar(select(Participant))
        participant.step = ShelfSurveyStep(block=1, shelf=1, trial=3)
        participant.block_order = ["trust_aware", "trust_agnostic"]
    response = post(client, token, "answers",
                    {"questionnaire": "shelf_trust_reliance_named", "answers": {"trust": 11, "reliance": 3}})
    assert response.status_code == 422 and "trust" in response.json()["detail"]
    ok = post(client, token, "answers",
              {"questionnaire": "shelf_trust_reliance_named", "answers": {"trust": 7, "reliance": 3}})
    assert ok.status_code == 200 and count(client, Answer) == 2


def test_intervene_after_the_window_is_refused(api):
    client, _ = api
    token = join(client)["token"]
    to_practice(client, token)
    assert post(client, token, "trials/start", {"practice": True, "block": 0, "trial": 1}).status_code == 200
    state = post(client, token, "trials/shown", {"practice": True, "block": 0, "trial": 1, "view": "text"}).json()
    assert state["trial"]["stage"] == "decision"
    with client.app.state.services.sessionmaker.begin() as session:
        trial = session.scalar(select(Trial))
        trial.decision_deadline_at = utcnow() - timedelta(seconds=1)
    response = post(client, token, "trials/intervene", {"practice": True, "block": 0, "trial": 1})
    assert response.status_code == 409 and "window has closed" in response.json()["detail"]
    assert client.get(f"/api/p/{token}/state").json()["last_trial"]["human_action"] == "rely"


def test_editing_a_started_study_makes_a_new_version(api):
    client, admin = api
    join(client)
    config = fast_config(title="Renamed").model_dump(mode="json")
    detail = client.put("/api/admin/studies/s1/config", json={"config": config}, headers=auth(admin)).json()
    assert detail["version"] == 2 and detail["title"] == "Renamed"
    join(client, PROLIFIC_PID="later")
    versions = [p["version"] for p in client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()]
    assert versions == [1, 2]
    bad = client.put("/api/admin/studies/s1/config", json={"config": {"title": ""}}, headers=auth(admin))
    assert bad.status_code == 422 and "blocks" in bad.json()["detail"]


def test_closed_study_refuses_new_participants_but_resumes_known_ones(api):
    client, admin = api
    join(client, PROLIFIC_PID="known")
    client.post("/api/admin/studies/s1/close", headers=auth(admin))
    assert client.post("/api/studies/s1/join").status_code == 410
    assert join(client, PROLIFIC_PID="known")["created"] is False  # the same browser (its resume key) resumes


def test_idle_sessions_are_abandoned_and_refused(api):
    client, _ = api
    token = join(client)["token"]
    app = client.app
    changed = sweep(app.state.services.sessionmaker, app.state.services.runtimes, app.state.services.hub,
                    now=utcnow() + timedelta(hours=2))
    assert changed == 1
    state = client.get(f"/api/p/{token}/state").json()
    assert state["phase"] == "abandoned"
    assert post(client, token, "consent", {"agree": True}).status_code == 410


def test_exclude_and_withdraw(api):
    client, admin = api
    token = join(client, PROLIFIC_PID="w1")["token"]
    post(client, token, "consent", {"agree": True})
    pid = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()[0]["public_id"]
    r = client.post(f"/api/admin/studies/s1/participants/{pid}/exclude", json={"reason": "on the phone"},
                    headers=auth(admin))
    assert r.status_code == 200
    row = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()[0]
    assert row["excluded"] and row["exclusion_reason"] == "on the phone"
    r = client.post(f"/api/admin/studies/s1/participants/{pid}/withdraw", json={"reason": "asked by email"},
                    headers=auth(admin))
    assert r.status_code == 200
    row = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()[0]
    assert row["status"] == "withdrawn" and row["external_id"] is None
    assert client.get(f"/api/p/{token}/state").json()["phase"] == "withdrawn"


def test_admin_token_is_required_and_checked(api):
    client, admin = api
    assert client.get("/api/admin/studies", headers=auth("tla_wrong")).status_code == 401
    assert client.get("/api/admin/studies", headers=auth(admin)).status_code == 200


def test_openapi_schema_is_served(api):
    client, _ = api
    schema = client.get("/openapi.json").json()
    assert "/api/p/{token}/state" in schema["paths"] and "StateRead" in schema["components"]["schemas"]


def test_non_finite_numbers_are_refused(api):
    client, _ = api
    token = join(client)["token"]
    raw = b'{"events": [{"kind": "x", "client_time_ms": NaN}]}'
    r = client.post(f"/api/p/{token}/events", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422
    raw = b'{"events": [{"kind": "x", "payload": {"a": Infinity}}]}'
    r = client.post(f"/api/p/{token}/events", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422 and "not a JSON number" in r.json()["detail"]


def test_a_study_whose_policy_cannot_run_is_refused(api):
    client, admin = api
    config = fast_config().model_dump(mode="json")
    model = {"format": "trustlab-iohmm", "version": 1, "params": {
        "initial": {"p_high": 0.5},
        "transitions": {c: {a: {e: {"from_low": None, "from_high": None} for e in ("negative", "positive")}
                            for a in ("auto", "ask")} for c in ("low", "high")},
        "emissions": {c: {"auto": {"p_rely_low": 0.5, "p_rely_high": 0.9}} for c in ("low", "high")}}}
    config["blocks"][0]["policy"] = {"kind": "trust_aware", "model": model}
    r = client.post("/api/admin/studies", json={"slug": "broken", "config": config}, headers=auth(admin))
    assert r.status_code == 422 and "cannot run" in r.json()["detail"]
    assert client.get("/api/admin/studies/broken", headers=auth(admin)).status_code == 404
