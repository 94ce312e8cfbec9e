"""``trustlab deploy`` (the evaluation study of a model, by the admin API's code path) and ``simulate --sweep``."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from experiment.agnostic import intervention_rates
from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.evaluation import evaluation_config
from experiment.provenance import content_hash
from experiment.records import read_sequences
from server.cli import app
from server.models import Trial
from server.services.completion_codes import with_private_codes
from server.services.studies import config_hash
from tests.server.factories import auth, join, make_client

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A trials.csv of simulated study-1 participants and the model ``trustlab fit`` makes of it."""
    folder = tmp_path_factory.mktemp("fitted")
    assert run("simulate", "paper", "--design", "model-estimation", "--participants", 12, "--seed", 3,
               "--out", folder).exit_code == 0
    fit = run("fit", folder / "trials.csv", "--out", folder / "model.json", "--restarts", 2, "--json")
    assert fit.exit_code == 0, fit.output
    return folder / "trials.csv", folder / "model.json"


def test_deploy_creates_the_evaluation_study_once(fitted, database_url, tmp_path):
    trials, model = fitted
    document = json.loads(model.read_text())
    args = ["deploy", model, "--trials", trials, "--slug", "next", "--template", "demo-fast", "--database-url",
            database_url, "--json"]
    first = run(*args)
    assert first.exit_code == 0, first.output
    payload = json.loads(first.stdout)
    assert payload["created"] is True and payload["model_hash"] == content_hash(document)
    assert payload["status"] == "draft"  # participants wait until the experimenter opens it
    drafted = run(*args[:-1])
    assert "the study is a draft" in drafted.output and "/api/admin/studies/next/open" in drafted.output
    again = json.loads(run(*args, "--open").stdout)  # the same deploy with --open opens the draft it made
    assert again["created"] is False and again["config_hash"] == payload["config_hash"] and again["status"] == "open"
    other = run("deploy", model, "--trials", trials, "--slug", "next", "--database-url", database_url)
    assert other.exit_code == 2 and "already exists with another configuration" in other.output

    # The config is the admin route's: the model inline, the baseline from the trials' intervention rates.
    _, sequences = read_sequences(trials)
    expected = evaluation_config(document, intervention_rates(sequences).rates, template_name="demo-fast")
    client, admin = make_client(database_url=database_url)
    study = client.get("/api/admin/studies/next", headers=auth(admin)).json()
    # (the study's random completion codes in place of the public defaults: server.services.completion_codes)
    assert study["config_hash"] == payload["config_hash"] == config_hash(with_private_codes(expected, study["config"]))
    written = tmp_path / "config.json"
    out = run("deploy", model, "--trials", trials, "--out", written, "--template", "demo-fast")
    assert out.exit_code == 0, out.output
    written_config = StudyConfig.model_validate_json(written.read_text())  # with the public codes: no study has it yet
    assert config_hash(with_private_codes(written_config, study["config"])) == payload["config_hash"]

    # A trial started in the deployed study records the model and the policy it runs under.
    token = join(client, "next", PROLIFIC_PID="cli")["token"]
    for step, body in (("consent", {"agree": True}), ("instructions/done", None),
                       ("trials/start", {"practice": True, "block": 0, "trial": 1})):
        assert client.post(f"/api/p/{token}/{step}", json=body).status_code == 200, step
    with client.app.state.services.sessionmaker() as session:
        row = session.scalars(select(Trial)).one()
    provenance = StudyRuntime(expected).practice_provenance
    assert (row.model_hash, row.policy_hash, row.seed) == (payload["model_hash"], provenance.policy_hash, 0)


@pytest.mark.parametrize(("extra", "message"), [
    ([], "give --slug"),
    (["--slug", "a", "--out", "c.json"], "give --slug"),
    (["--slug", "a", "--template", "model-estimation"], "unknown evaluation design"),
    (["--slug", "Not A Slug"], "study slug"),
])
def test_deploy_refuses_bad_arguments(fitted, tmp_path, extra, message):
    trials, model = fitted
    result = run("deploy", model, "--trials", trials, "--database-url", f"sqlite:///{tmp_path / 'x.db'}", *extra)
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output


def test_deploy_needs_readable_inputs(fitted, tmp_path):
    trials, model = fitted
    assert "model file not found" in run("deploy", tmp_path / "none.json", "--trials", trials, "--out",
                                         tmp_path / "c").output
    assert "not found" in run("deploy", model, "--trials", tmp_path / "none.csv", "--out", tmp_path / "c").output


def test_simulate_sweep_reports_power_per_n_and_the_paper_comparison():
    result = run("simulate", "paper", "--design", "demo", "--sweep", "6,3", "--replications", 4, "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert [row["participants"] for row in payload["sweep"]] == [3, 6]
    for row in payload["sweep"]:
        assert 0 <= row["power"] <= 1 and row["effect_size"] is not None
        assert {b: r["n"] for b, r in row["rewards"].items()} == {"trust_aware": 4 * row["participants"],
                                                                  "trust_agnostic": 4 * row["participants"]}
        low, high = row["difference_95"]
        assert low <= row["mean_difference"] <= high
    reached = [row["participants"] for row in payload["sweep"] if row["power"] >= 0.8]
    assert payload["participants_needed"] == (reached[0] if reached else None)
    paper = payload["paper"]
    assert paper["measured_median"] == {"trust_aware": 84, "trust_agnostic": 69}
    assert "the paper measured" in paper["message"]

    human = run("simulate", "paper", "--design", "demo", "--sweep", "3,4", "--replications", 2)
    assert human.exit_code == 0, human.output
    assert "power" in human.stdout and ("Smallest N tried" in human.stdout or "No N tried reached" in human.stdout)
    assert "Model prediction" in human.stdout and "N = 4: [" in human.stderr


@pytest.mark.parametrize(("args", "message"), [
    (["--sweep", "3,5"], "--replications R ≥ 2"),
    (["--sweep", "3,x", "--replications", "3"], "whole numbers"),
    (["--sweep", "1,5", "--replications", "3"], "between 2 and"),
    (["--sweep", "3,5", "--replications", "3", "--participants", "4"], "without --participants"),
    (["--replications", "3"], "give --participants"),
])
def test_simulate_sweep_bad_input(args, message):
    result = run("simulate", "paper", "--design", "demo", *args)
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output


def test_sweep_needs_two_blocks():
    result = run("simulate", "paper", "--design", "model-estimation", "--sweep", "3", "--replications", 2)
    assert result.exit_code == 2 and "compares two blocks" in result.output
