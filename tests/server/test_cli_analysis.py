"""The analysis commands of the CLI, as a user runs them (SPEC §9)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from experiment.iohmm import paper_params, params_from_document
from experiment.templates import demo_fast
from server.cli import app

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_policy_paper_json_gives_thresholds():
    result = run("policy", "paper", "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["threshold"]["low"] is None and payload["action"]["low"] == "auto"
    assert 0.65 < payload["threshold"]["high"] < 0.7255
    assert payload["myopic_threshold"]["high"] == pytest.approx(0.7255, abs=1e-4)


def test_policy_human_output():
    result = run("policy", "paper", "--p-high", "0.4225", "--belief-update", "paper")
    assert result.exit_code == 0 and "ask below belief" in result.stdout


def test_agnostic_from_simulated_study(tmp_path):
    assert run("simulate", "paper", "--design", "model-estimation", "--participants", "10", "--out",
               tmp_path).exit_code == 0
    result = run("agnostic", tmp_path / "trials.csv", "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert set(payload["action"]) == {"low", "high"}


def test_simulate_then_fit_recovers_the_model(tmp_path):
    sim = run("simulate", "paper", "--design", "model-estimation", "--participants", "200", "--seed", "4",
              "--out", tmp_path, "--json")
    assert sim.exit_code == 0, sim.output
    assert json.loads(sim.stdout)["trials_written"] == 200 * 71
    model = tmp_path / "model.json"
    result = run("fit", tmp_path / "trials.csv", "--out", model, "--restarts", "5", "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert {"loglik", "params", "stderr"} <= payload.keys()
    fitted = params_from_document(json.loads(model.read_text()))
    true = paper_params()
    for c in (0, 1):  # emission probabilities are well identified
        assert np.allclose(fitted.p_rely[c], true.p_rely[c], atol=0.06)
    # the fitted model feeds the policy solver
    assert run("policy", model, "--json").exit_code == 0


def test_simulate_power_json():
    result = run("simulate", "paper", "--design", "demo", "--participants", "6", "--replications", "3", "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert 0 <= payload["power"]["power"] <= 1 and payload["test"]["df"] == 10


@pytest.mark.parametrize(("args", "message"), [
    (["fit", "missing.csv", "--out", "m.json"], "not found"),
    (["policy", "missing.json"], "model file not found"),
    (["simulate", "paper", "--design", "nope", "--participants", "2"], "unknown design"),
    (["policy", "paper", "--belief-update", "magic"], "bayes"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    result = run(*args)
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


def test_fit_rejects_malformed_csv(tmp_path):
    bad = tmp_path / "trials.csv"
    bad.write_text("participant_id,block\np,1\n")
    result = run("fit", bad, "--out", tmp_path / "m.json")
    assert result.exit_code == 2 and "missing column" in result.output and "Traceback" not in result.output


def test_a_design_file_is_checked_as_the_designer_checks_it(tmp_path):
    """Every problem of the file, placed as the designer's check places it (union tags left out), as strictly as the
    schema reads ("4" is not a number); a valid file runs."""
    config = demo_fast().model_dump(mode="json")
    good = tmp_path / "good.json"
    good.write_text(json.dumps(config))
    assert run("simulate", "paper", "--design", good, "--participants", "2", "--json").exit_code == 0
    config["blocks"][1]["schedule"]["n_low"] = -1
    config["timing"]["decision_window_s"] = "4"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(config))
    result = run("simulate", "paper", "--design", bad, "--participants", "2")
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "2 problem(s)" in result.output
    assert "blocks[1].schedule.n_low:" in result.output and "timing.decision_window_s:" in result.output
    (tmp_path / "broken.json").write_text("{")
    assert "not a JSON document" in run("simulate", "paper", "--design", tmp_path / "broken.json").output
