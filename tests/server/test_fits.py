"""The model registry through the admin API: fit a study's data, read the model, deploy it, run the deployed study.

The model-estimation data come from simulated participants written straight into the database
(``add_simulated_participants``: deterministic and fast); the deployed evaluation study is run by a bot
through the participant API, so its trial rows are made by the server as in a real run.
"""

from __future__ import annotations

import csv
import io
import threading
import time
from contextlib import nullcontext
from importlib import metadata

import pytest
from fastapi.testclient import TestClient

from experiment.agnostic import baseline_from_rates, intervention_rates
from experiment.belief_mdp import solve_belief_mdp
from experiment.config import AlwaysAskSpec, AlwaysAutoSpec, PracticeConfig, StudyConfig
from experiment.engine import StudyRuntime
from experiment.fit import fit_iohmm
from experiment.iohmm import PARAMETER_NAMES, paper_params
from experiment.provenance import content_hash, data_hash
from experiment.records import read_model_trials, read_sequences
from experiment.task import Complexity, TaskParams
from experiment.templates import model_estimation
from server.harness.crowd import run_bots
from server.main import create_app
from server.services import fits
from server.settings import Settings
from tests.server.factories import add_simulated_participants, auth, fast_config, make_client, make_study

RESTARTS, SEED = 3, 7


def estimation_config(**changes) -> StudyConfig:
    """Paper study 1 with machine pacing."""
    return fast_config(model_estimation(), practice=PracticeConfig(enabled=False), **changes)


def wait_for_fit(client: TestClient, admin: str, model_id: int) -> dict:
    deadline = time.monotonic() + 120
    while True:
        model = client.get(f"/api/admin/models/{model_id}", headers=auth(admin)).json()
        if model["status"] != "running":
            return model
        assert time.monotonic() < deadline, f"the fit did not finish: {model['progress']}"
        time.sleep(0.05)


def csv_rows(content: bytes) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(content.decode("utf-8"))))


@pytest.fixture
def app_client(database_url):
    client, admin = make_client(database_url=database_url)
    try:
        yield client, admin
    finally:
        client.app.state.services.fits.stop()


def test_fit_deploy_and_run_the_evaluation_study(app_client, tmp_path):
    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    ids = add_simulated_participants(client, "s1", n=6, model=paper_params(), seed=1)
    assert client.post(f"/api/admin/studies/s1/participants/{ids[-1]}/exclude", json={"reason": "test"},
                       headers=auth(admin)).status_code == 200

    started = client.post("/api/admin/studies/s1/fits", json={"restarts": RESTARTS, "seed": SEED}, headers=auth(admin))
    assert started.status_code == 202, started.text
    assert started.json()["status"] == "running" and started.json()["parameters"] == []
    model_id = started.json()["id"]
    model = wait_for_fit(client, admin, model_id)
    assert model["status"] == "done", model["error"]
    assert model["progress"]["iterations_done"] == model["progress"]["iterations_max"] == fits.MAX_ITERATIONS

    # The same fit, run directly on the exported trials.csv, gives the same model, bit for bit.
    exported = client.get("/api/admin/studies/s1/export/trials.csv", headers=auth(admin)).content
    path = tmp_path / "trials.csv"
    path.write_bytes(exported)
    participants, sequences = read_sequences(path)
    direct = fit_iohmm(sequences, restarts=RESTARTS, seed=SEED)
    download = client.get(f"/api/admin/models/{model_id}/document", headers=auth(admin))
    assert download.status_code == 200
    assert download.headers["content-disposition"] == (
        f'attachment; filename="model-{model_id}-{model["content_hash"][:12]}.json"')
    document = download.json()
    assert document == direct.to_document(fitted_on=document["fitted_on"])
    assert model["content_hash"] == content_hash(document)
    assert model["loglik"] == direct.loglik and model["converged"] == direct.converged
    values = direct.params.to_vector()
    assert [p["name"] for p in model["parameters"]] == PARAMETER_NAMES
    for p, value, se, status in zip(model["parameters"], values, direct.stderr, direct.status, strict=True):
        assert p["status"] == status
        assert p["value"] == (None if value != value else value)
        assert p["stderr"] == (None if se != se else se)

    # Provenance: the included participants only, the rows' hash, the versions, the code that fitted.
    provenance = model["provenance"]
    assert participants == ids[:-1] == provenance["participants"] == document["fitted_on"]["participants"]
    assert provenance["data_hash"] == data_hash(read_model_trials(path)) == document["fitted_on"]["data_hash"]
    assert provenance["study_versions"] == [1] and provenance["n_trials"] == sum(len(s) for s in sequences)
    assert (provenance["restarts"], provenance["seed"], provenance["p_high"]) == (RESTARTS, SEED, 0.5)
    assert provenance["code_version"] == metadata.version("trustlab") == document["fitted_on"]["code_version"]

    # Thresholds and the trust-agnostic baseline come from the same model and data.
    solution = solve_belief_mdp(direct.params, TaskParams(), p_high=0.5)
    assert model["policy"]["error"] is None
    assert model["policy"]["threshold"] == {c.value: solution.thresholds[c] for c in Complexity}
    baseline = baseline_from_rates(intervention_rates(sequences))
    assert model["agnostic"]["rates"] == baseline["rates"] and model["agnostic"]["action"] == baseline["action"]

    # A retry finds the same model; another seed is another fit.
    again = client.post("/api/admin/studies/s1/fits", json={"restarts": RESTARTS, "seed": SEED}, headers=auth(admin))
    assert again.status_code == 200 and again.json()["id"] == model_id
    other = client.post("/api/admin/studies/s1/fits", json={"restarts": RESTARTS, "seed": SEED + 1},
                        headers=auth(admin))
    assert other.status_code == 202 and other.json()["id"] != model_id
    wait_for_fit(client, admin, other.json()["id"])
    listed = client.get("/api/admin/studies/s1/models", headers=auth(admin)).json()
    assert [m["id"] for m in listed] == [other.json()["id"], model_id]

    # Deploy: two counterbalanced blocks, trust-aware with the model inline, trust-agnostic with the rates.
    body = {"slug": "eval", "template": "demo-fast", "status": "open"}
    created = client.post(f"/api/admin/models/{model_id}/evaluation-study", json=body, headers=auth(admin))
    assert created.status_code == 201 and created.json()["status"] == "open", created.text
    config = StudyConfig.model_validate(created.json()["config"])
    assert config.model == document and config.counterbalance == "all"
    aware, agnostic = (next(b.policy for b in config.blocks if b.policy.kind == k)
                       for k in ("trust_aware", "trust_agnostic"))
    assert aware.model == document and aware.p_high == 0.5
    assert (agnostic.intervention_rate_low, agnostic.intervention_rate_high) == tuple(
        baseline["rates"][c.value]["rate"] for c in Complexity)
    retried = client.post(f"/api/admin/models/{model_id}/evaluation-study", json=body, headers=auth(admin))
    assert retried.status_code == 200 and retried.json()["config_hash"] == created.json()["config_hash"]
    taken = client.post(f"/api/admin/models/{model_id}/evaluation-study", json={"slug": "s1"}, headers=auth(admin))
    assert taken.status_code == 409 and "already exists" in taken.json()["detail"]
    assert client.get(f"/api/admin/models/{model_id}", headers=auth(admin)).json()["evaluation_studies"] == ["eval"]
    assert model["evaluation_blocked"] is None

    # A bot runs the evaluation study: every trial row names the fitted model, its block's policy and the seed.
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "eval", paper_params(),
                       participants=1, concurrency=1)
    assert summary.errors == [] and summary.completed == 1
    rows = csv_rows(client.get("/api/admin/studies/eval/export/trials.csv", headers=auth(admin)).content)
    runtime = StudyRuntime(config)
    scored = [r for r in rows if r["practice"] == "0"]
    assert len(scored) == sum(b.schedule.n_trials for b in config.blocks) and len(rows) > len(scored)
    assert {r["model_hash"] for r in rows} == {model["content_hash"]}
    assert {r["seed"] for r in rows} == {str(config.seed)}
    for row in rows:
        expected = runtime.provenance(row["block_name"], practice=row["practice"] == "1")
        assert row["policy_hash"] == expected.policy_hash
    assert len({r["policy_hash"] for r in scored}) == 2  # the two policies differ


def test_requests_that_cannot_be_served(app_client, monkeypatch):
    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    assert client.post("/api/admin/studies/s1/fits", json={}).status_code == 401
    missing = client.post("/api/admin/studies/nope/fits", json={}, headers=auth(admin))
    assert missing.status_code == 404 and "nope" in missing.json()["detail"]
    empty = client.post("/api/admin/studies/s1/fits", json={}, headers=auth(admin))
    assert empty.status_code == 409 and "no trials" in empty.json()["detail"]
    for bad in ({"restarts": 0}, {"restarts": 1001}, {"p_high": 1.5}, {"seed": -1}, {"restart": 3}):
        response = client.post("/api/admin/studies/s1/fits", json=bad, headers=auth(admin))
        assert response.status_code == 422, bad
    assert client.get("/api/admin/models/404", headers=auth(admin)).status_code == 404
    assert client.get("/api/admin/models/x", headers=auth(admin)).status_code == 422
    assert client.get("/api/admin/studies/nope/models", headers=auth(admin)).status_code == 404
    assert client.post("/api/admin/models/404/evaluation-study", json={"slug": "ev"},
                       headers=auth(admin)).status_code == 404

    # A fit that has not run yet (the worker is held back) cannot be downloaded or deployed.
    monkeypatch.setattr(fits.FitWorker, "submit", lambda self, job: None)
    add_simulated_participants(client, "s1", n=2, model=paper_params())
    model = client.post("/api/admin/studies/s1/fits", json={"restarts": 1}, headers=auth(admin)).json()
    document = client.get(f"/api/admin/models/{model['id']}/document", headers=auth(admin))
    assert document.status_code == 409 and "still being fitted" in document.json()["detail"]
    deploy = client.post(f"/api/admin/models/{model['id']}/evaluation-study", json={"slug": "ev"}, headers=auth(admin))
    assert deploy.status_code == 409
    bad_template = client.post(f"/api/admin/models/{model['id']}/evaluation-study",
                               json={"slug": "ev", "template": "model-estimation"}, headers=auth(admin))
    assert bad_template.status_code == 422


def test_running_fits_of_a_stopped_server_fail_at_start(app_client, database_url, monkeypatch):
    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    add_simulated_participants(client, "s1", n=2, model=paper_params())
    with monkeypatch.context() as patch:
        patch.setattr(fits.FitWorker, "submit", lambda self, job: None)  # the server "dies" before fitting
        stale = client.post("/api/admin/studies/s1/fits", json={"restarts": 1}, headers=auth(admin)).json()
    # A worker other than the primary of a group (server.workers) runs no fits: its start leaves fits alone.
    with TestClient(create_app(Settings(database_url=database_url, world_loop=False, worker_index=1))) as other:
        assert other.get(f"/api/admin/models/{stale['id']}", headers=auth(admin)).json()["status"] == "running"
    with TestClient(create_app(Settings(database_url=database_url, world_loop=False))) as restarted:
        model = restarted.get(f"/api/admin/models/{stale['id']}", headers=auth(admin)).json()
    assert model["status"] == "failed" and model["error"] == fits.INTERRUPTED
    retried = client.post("/api/admin/studies/s1/fits", json={"restarts": 1}, headers=auth(admin))
    assert retried.status_code == 202 and retried.json()["id"] != stale["id"]
    assert wait_for_fit(client, admin, retried.json()["id"])["status"] == "done"


def test_stopping_the_server_interrupts_a_running_fit(app_client, monkeypatch):
    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    add_simulated_participants(client, "s1", n=2, model=paper_params())
    started = threading.Event()

    def endless(*args, progress, **kwargs):
        started.set()
        while True:
            progress(1, fits.MAX_ITERATIONS)
            time.sleep(0.01)

    monkeypatch.setattr(fits, "fit_bundle", endless)
    model = client.post("/api/admin/studies/s1/fits", json={"restarts": 1}, headers=auth(admin)).json()
    assert started.wait(60)
    client.app.state.services.fits.stop()  # what the server's shutdown does
    stopped = client.get(f"/api/admin/models/{model['id']}", headers=auth(admin)).json()
    assert stopped["status"] == "failed" and stopped["error"] == fits.INTERRUPTED
    assert stopped["progress"]["iterations_done"] == 1


def test_a_failing_fit_records_why(app_client, monkeypatch):
    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    add_simulated_participants(client, "s1", n=2, model=paper_params())

    def broken(*args, **kwargs):
        raise RuntimeError("numerical trouble")

    monkeypatch.setattr(fits, "fit_bundle", broken)
    started = client.post("/api/admin/studies/s1/fits", json={"restarts": 1}, headers=auth(admin)).json()
    model = wait_for_fit(client, admin, started["id"])
    assert model["status"] == "failed" and model["error"] == "RuntimeError: numerical trouble"
    document = client.get(f"/api/admin/models/{started['id']}/document", headers=auth(admin))
    assert document.status_code == 409 and "numerical trouble" in document.json()["detail"]


def test_data_without_autonomous_attempts_has_no_baseline_to_deploy(app_client):
    """A robot that always asks: the model is stored, but the policy and the baseline say why they are missing."""
    client, admin = app_client
    config = estimation_config()
    block = config.blocks[0].model_copy(update={"policy": AlwaysAskSpec()})
    make_study(client, admin, config=config.model_copy(update={"blocks": [block]}), slug="asks")
    add_simulated_participants(client, "asks", n=2, model=paper_params())
    started = client.post("/api/admin/studies/asks/fits", json={"restarts": 1}, headers=auth(admin)).json()
    model = wait_for_fit(client, admin, started["id"])
    assert model["status"] == "done"
    assert "no autonomous attempts in low or high complexity" in model["agnostic"]["error"]
    assert model["agnostic"]["action"] is None and model["policy"]["error"]
    # the read model says why before anyone asks, in the words the refusal uses
    assert model["evaluation_blocked"].startswith("there is no trust-agnostic baseline: no autonomous attempts")
    deploy = client.post(f"/api/admin/models/{started['id']}/evaluation-study", json={"slug": "ev"},
                         headers=auth(admin))
    assert deploy.status_code == 409 and "no trust-agnostic baseline" in deploy.json()["detail"]
    assert deploy.json()["detail"].endswith(model["evaluation_blocked"])
    listed = client.get("/api/admin/studies/asks/models", headers=auth(admin)).json()
    assert [m["evaluation_blocked"] for m in listed] == [model["evaluation_blocked"]]


def test_a_policy_that_cannot_be_solved_blocks_the_evaluation_study_before_the_click(app_client):
    """A robot that never asks: the baseline has its rates, but the trust-aware policy needs what follows an ask,
    which the data never showed. The read model says so (evaluation_blocked), and the deployment refuses with it."""
    client, admin = app_client
    config = estimation_config()
    block = config.blocks[0].model_copy(update={"policy": AlwaysAutoSpec()})
    make_study(client, admin, config=config.model_copy(update={"blocks": [block]}), slug="never-asks")
    add_simulated_participants(client, "never-asks", n=3, model=paper_params())
    started = client.post("/api/admin/studies/never-asks/fits", json={"restarts": 1}, headers=auth(admin)).json()
    assert started["evaluation_blocked"] and "still being fitted" in started["evaluation_blocked"]
    model = wait_for_fit(client, admin, started["id"])
    assert model["status"] == "done" and model["agnostic"]["error"] is None and model["policy"]["error"]
    assert model["evaluation_blocked"] == f"the trust-aware policy cannot be solved: {model['policy']['error']}"
    deploy = client.post(f"/api/admin/models/{started['id']}/evaluation-study", json={"slug": "ev"},
                         headers=auth(admin))
    assert deploy.status_code == 409
    assert deploy.json()["detail"] == (f"cannot make an evaluation study of model {model['id']}: "
                                       f"{model['evaluation_blocked']}")
    assert client.get("/api/admin/studies/ev", headers=auth(admin)).status_code == 404
