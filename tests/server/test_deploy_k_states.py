"""Issue 40: deploying a model of three trust states by ``trustlab deploy`` and the admin API, and running it."""

from __future__ import annotations

import csv
import io
import json
from contextlib import nullcontext

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from typer.testing import CliRunner

from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.evaluation import evaluation_config
from experiment.iohmm import model_document, paper_params
from experiment.policies import TrustAware
from experiment.provenance import content_hash
from experiment.sequences import Sequence
from experiment.task import Complexity, Experience, HumanAction, RobotAction
from experiment.trust_states import filter_beliefs_k
from experiment.trust_states_document import k_state_document, k_state_params_from_document
from experiment.trust_states_policy import KPolicySolution
from server.cli import app
from server.harness.crowd import run_bots
from server.main import create_app
from server.models import Participant
from server.settings import Settings
from tests.experiment.test_trust_states_document import three_state_model
from tests.server.factories import auth, fast_config, make_client

#: The PostgreSQL runs add nothing here (tests/conftest.py): the belief over three trust states and its policy;
#: deploying and storing a model are tested on both databases in test_fits.py and test_fit_states.py.
STORAGE_INCIDENTAL = True

runner = CliRunner()
RATES = {Complexity.LOW: 0.1, Complexity.HIGH: 0.6}


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def trials_csv(tmp_path_factory):
    """A trials.csv whose intervention rates make the trust-agnostic baseline."""
    folder = tmp_path_factory.mktemp("trials")
    result = run("simulate", "paper", "--design", "model-estimation", "--participants", 4, "--seed", 3,
                 "--out", folder)
    assert result.exit_code == 0, result.output
    return folder / "trials.csv"


def test_deploy_a_three_state_model_from_the_command_line(trials_csv, database_url, tmp_path):
    document = k_state_document(three_state_model(), fitted_on={"note": "by hand"})
    model = tmp_path / "k3.json"
    model.write_text(json.dumps(document))
    written = tmp_path / "config.json"
    out = run("deploy", model, "--trials", trials_csv, "--out", written, "--template", "demo-fast")
    assert out.exit_code == 0, out.output
    config = StudyConfig.model_validate_json(written.read_text())
    aware = next(b.policy for b in config.blocks if b.policy.kind == "trust_aware")
    assert config.model == aware.model == document
    policy = StudyRuntime(config).policies[next(b.name for b in config.blocks if b.policy.kind == "trust_aware")]
    assert isinstance(policy, TrustAware) and isinstance(policy.solution, KPolicySolution)

    # `trustlab simulate` runs the deployed design: its trust-aware block acts on the 3-state filter's belief.
    folder = tmp_path / "simulated"
    simulated = run("simulate", "paper", "--design", written, "--participants", 2, "--seed", 1, "--out", folder)
    assert simulated.exit_code == 0, simulated.output
    rows = list(csv.DictReader(io.StringIO((folder / "trials.csv").read_text())))
    assert_trust_aware_trials_follow_the_filter(config, rows)

    created = run("deploy", model, "--trials", trials_csv, "--slug", "k3", "--template", "demo-fast",
                  "--database-url", database_url, "--json")
    assert created.exit_code == 0, created.output
    payload = json.loads(created.stdout)
    assert payload["created"] is True and payload["model_hash"] == content_hash(document)


def test_a_bad_model_file_is_refused_with_the_reason(trials_csv, tmp_path):
    document = k_state_document(three_state_model())
    document["params"]["initial"]["state_0"] = 0.5
    model = tmp_path / "bad.json"
    model.write_text(json.dumps(document))
    result = run("deploy", model, "--trials", trials_csv, "--out", tmp_path / "config.json")
    assert result.exit_code == 2 and "initial must sum to 1" in result.output


def k_state_evaluation(document: dict) -> StudyConfig:
    return fast_config(evaluation_config(document, RATES, template_name="demo-fast"))


def test_the_admin_api_refuses_a_bad_model_with_a_reason(database_url):
    client, admin = make_client(database_url=database_url)
    config = k_state_evaluation(k_state_document(three_state_model())).model_dump(mode="json")
    config["model"]["params"]["emissions"]["high"]["auto"]["p_rely_state_1"] = 1.5
    response = client.post("/api/admin/studies", json={"slug": "bad", "config": config}, headers=auth(admin))
    assert response.status_code == 422
    assert "emissions.high.auto.p_rely_state_1" in response.text and "probability in [0, 1]" in response.text
    config["model"] = {"format": "trustlab-iohmm-k", "version": 1, "n_states": 7}
    response = client.post("/api/admin/studies", json={"slug": "bad", "config": config}, headers=auth(admin))
    assert response.status_code == 422 and "n_states" in response.text


def _scored_rows(rows: list[dict[str, str]]) -> dict[str, list[dict[str, str]]]:
    """The scored trials.csv rows per participant, in order."""
    by_participant: dict[str, list[dict[str, str]]] = {}
    scored = [r for r in rows if r["practice"] == "0"]
    for row in sorted(scored, key=lambda r: (r["participant_id"], int(r["trial_overall"]))):
        by_participant.setdefault(row["participant_id"], []).append(row)
    return by_participant


def assert_trust_aware_trials_follow_the_filter(config: StudyConfig, rows: list[dict[str, str]]) -> np.ndarray:
    """Every trust-aware decision is ``KPolicySolution.action`` on the K-state filter's belief of the trials before
    it, and the belief columns are P(the highest state) of that filter; returns the last participant's beliefs."""
    params = k_state_params_from_document(config.model)
    runtime = StudyRuntime(config)
    aware = next(b.name for b in config.blocks if b.policy.kind == "trust_aware")
    policy = runtime.policies[aware]
    assert isinstance(policy, TrustAware) and isinstance(policy.solution, KPolicySolution)
    participants = _scored_rows(rows)
    assert participants
    for trials in participants.values():
        beliefs = filter_beliefs_k(params, _sequence(trials))
        decisions = 0
        for t, row in enumerate(trials):
            assert float(row["belief_before"]) == pytest.approx(beliefs[t][-1], abs=1e-9)  # 10 decimals in the CSV
            assert float(row["belief_after"]) == pytest.approx(beliefs[t + 1][-1], abs=1e-9)
            if row["block_name"] == aware:
                decisions += 1
                complexity = Complexity(row["complexity"])
                assert RobotAction(row["robot_action"]) == policy.solution.action(beliefs[t], complexity)
                assert float(row["policy_belief"]) == pytest.approx(beliefs[t][-1], abs=1e-9)
        assert decisions == config.block(aware).schedule.n_trials
    return beliefs


def _sequence(rows: list[dict[str, str]]) -> Sequence:
    return Sequence([Complexity(r["complexity"]).code for r in rows],
                    [RobotAction(r["robot_action"]).code for r in rows],
                    [HumanAction(r["human_action"]).code for r in rows],
                    [Experience(r["experience"]).code for r in rows])


def test_a_three_state_study_made_by_the_admin_api_runs_by_its_belief_vector(database_url):
    params = three_state_model()
    document = k_state_document(params)
    client, admin = make_client(database_url=database_url)
    config = k_state_evaluation(document)
    response = client.post("/api/admin/studies", json={"slug": "k3", "status": "open",
                                                       "config": config.model_dump(mode="json")}, headers=auth(admin))
    assert response.status_code == 201, response.text
    stored = StudyConfig.model_validate(response.json()["config"])
    assert stored.model == document
    # The designer's check and the study's summary take the model too (the policy in words names its states).
    checked = client.post("/api/admin/study-config/check", json={"config": config.model_dump(mode="json")},
                          headers=auth(admin)).json()
    assert checked["valid"] is True and checked["problems"] == []
    policies = [b["policy"] for b in client.get("/api/admin/studies/k3/summary", headers=auth(admin)).json()["blocks"]]
    assert any("3 trust states" in words for words in policies)

    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "k3", paper_params(), participants=1,
                       concurrency=1)
    assert summary.errors == [] and summary.completed == 1

    # Every trust-aware decision is KPolicySolution.action on the 3-state filter's belief of the trials before it.
    content = client.get("/api/admin/studies/k3/export/trials.csv", headers=auth(admin)).content
    rows = list(csv.DictReader(io.StringIO(content.decode("utf-8"))))
    beliefs = assert_trust_aware_trials_follow_the_filter(stored, rows)
    (participant_id,) = _scored_rows(rows)

    # The server keeps the vector in the participant's row, so a restarted server has it (and shows P(highest)).
    with client.app.state.services.sessionmaker() as session:
        kept = session.scalars(select(Participant).where(Participant.public_id == participant_id)).one().beliefs
    np.testing.assert_allclose(kept[""], beliefs[-1], rtol=0, atol=1e-12)
    restarted = TestClient(create_app(Settings(database_url=database_url, world_loop=False, planner_processes=0)))
    listed = restarted.get("/api/admin/studies/k3/participants", headers=auth(admin)).json()
    assert [p["belief"] for p in listed] == [pytest.approx(beliefs[-1][-1], abs=1e-12)]


def test_a_two_state_document_deploys_as_before(trials_csv, tmp_path):
    model = tmp_path / "paper.json"
    model.write_text(json.dumps(model_document(paper_params())))
    written = tmp_path / "config.json"
    assert run("deploy", model, "--trials", trials_csv, "--out", written, "--template", "demo-fast").exit_code == 0
    from_file = StudyConfig.model_validate_json(written.read_text())
    assert run("deploy", "paper", "--trials", trials_csv, "--out", written, "--template", "demo-fast").exit_code == 0
    assert StudyConfig.model_validate_json(written.read_text()) == from_file
    assert StudyRuntime(from_file).initial_beliefs() == {"": paper_params().initial_high}
