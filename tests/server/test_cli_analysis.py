"""The analysis commands of the CLI, as a user runs them (SPEC §9)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from experiment.iohmm import IOHMMParams, paper_params, params_from_document
from experiment.templates import demo_fast
from experiment.trust_states import illustrative_three_state_model
from experiment.trust_states_document import k_state_document, k_state_params_from_document, trust_model_from_document
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


def test_fit_compares_numbers_of_trust_states_and_writes_the_chosen_one(tmp_path):
    assert run("simulate", "paper", "--design", "model-estimation", "--participants", "30", "--seed", "2",
               "--out", tmp_path).exit_code == 0
    model = tmp_path / "model.json"
    result = run("fit", tmp_path / "trials.csv", "--out", model, "--states", "3,2", "--cv", "3", "--restarts", "4")
    assert result.exit_code == 0, result.output
    assert "held-out per trial" in result.stdout and "BIC counts trials as its sample size" in result.stdout
    document = json.loads(model.read_text())
    selection = document["selection"]
    assert [c["n_states"] for c in selection["candidates"]] == [2, 3]
    assert selection["folds"] == 3 and selection["seed"] == 0 and selection["n_participants"] == 30
    assert selection["chosen"] in (2, 3) and selection["reason"].startswith(f"{selection['chosen']} states")
    assert f"Fitted {selection['chosen']} trust states" in result.stdout
    model_of_chosen = trust_model_from_document(document)  # the chosen model, readable as any model JSON
    assert (selection["chosen"] == 2) == isinstance(model_of_chosen, IOHMMParams)


def test_fit_of_three_states_writes_standard_errors_and_statuses(tmp_path):
    assert run("simulate", "paper", "--design", "model-estimation", "--participants", "20", "--seed", "5",
               "--out", tmp_path).exit_code == 0
    model = tmp_path / "model.json"
    result = run("fit", tmp_path / "trials.csv", "--out", model, "--states", "3", "--restarts", "3", "--json")
    assert result.exit_code == 0, result.output
    document = json.loads(model.read_text())
    assert json.loads(result.stdout) == document and "selection" not in document
    assert document["format"] == "trustlab-iohmm-k" and document["n_states"] == 3
    params = k_state_params_from_document(document)
    assert set(document["params"]["emissions"]["high"]["auto"]) == {f"p_rely_state_{j}" for j in range(3)}
    statuses = document["status"]["emissions"]["high"]["auto"]
    assert set(statuses.values()) <= {"estimated", "boundary", "unidentified", "not_exercised"}
    for j in range(3):
        se = document["stderr"]["emissions"]["high"]["auto"][f"p_rely_state_{j}"]
        assert (se is not None and se > 0) == (statuses[f"p_rely_state_{j}"] == "estimated")
    assert document["fit"]["restarts"] == 3 and document["loglik"] < 0
    assert np.all(np.diff(params.p_rely[1]) >= 0)  # ordered: the last state is the highest trust
    recovered = run("simulate", model, "--design", "demo", "--participants", "3", "--replications", "2", "--recover",
                    "--json")
    assert recovered.exit_code == 0, recovered.output  # simulated people of three trust states, refitted with three
    names = {p["name"] for p in json.loads(recovered.stdout)["parameters"]}
    assert "emissions.high.auto.p_rely_state_2" in names and "initial.state_0" in names
    solved = run("policy", model, "--grid", "100")
    assert solved.exit_code == 0 and "Trust-aware policy of 3 trust states" in solved.stdout


@pytest.mark.parametrize(("states", "message"), [("2,5", "must be 2…4"), ("two", "separated by commas"),
                                                 (",", "must be 2…4")])
def test_fit_refuses_numbers_of_states_it_cannot_fit(tmp_path, states, message):
    assert run("simulate", "paper", "--design", "demo", "--participants", "3", "--out", tmp_path).exit_code == 0
    result = run("fit", tmp_path / "trials.csv", "--out", tmp_path / "m.json", "--states", states)
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output


def test_fit_refuses_more_folds_than_participants(tmp_path):
    assert run("simulate", "paper", "--design", "demo", "--participants", "3", "--out", tmp_path).exit_code == 0
    result = run("fit", tmp_path / "trials.csv", "--out", tmp_path / "m.json", "--states", "2,3", "--cv", "5")
    assert result.exit_code == 2 and "at least 5 participants" in result.output


def test_simulate_recover_reports_bias_rmse_and_coverage_per_parameter():
    result = run("simulate", "paper", "--design", "model-estimation", "--participants", "6", "--replications", "2",
                 "--recover")
    assert result.exit_code == 0, result.output
    assert "2 simulated studies of 6 participants" in result.stdout
    assert "emissions.high.auto.p_rely_high" in result.stdout and "coverage" in result.stdout
    payload = json.loads(run("simulate", "paper", "--design", "model-estimation", "--participants", "6",
                             "--replications", "2", "--recover", "--json").stdout)
    assert payload["participants"] == 6 and payload["replications"] == 2 and len(payload["parameters"]) == 17
    assert {p["verdict"] for p in payload["parameters"]} <= {"recovered", "intervals off", "at a bound",
                                                             "not identified"}
    refused = run("simulate", "paper", "--design", "model-estimation", "--participants", "6", "--recover")
    assert refused.exit_code == 2 and "--replications R ≥ 2" in refused.output


def test_policy_of_three_states_says_where_on_the_simplex_the_robot_asks_and_plots_it(tmp_path):
    model = tmp_path / "three.json"
    model.write_text(json.dumps(k_state_document(illustrative_three_state_model())))
    plot = tmp_path / "policy.png"
    result = run("policy", model, "--grid", "300", "--plot", plot)
    assert result.exit_code == 0, result.output
    assert "Trust-aware policy of 3 trust states" in result.stdout and "belief simplex" in result.stdout
    assert plot.read_bytes().startswith(b"\x89PNG")
    payload = json.loads(run("policy", model, "--grid", "300", "--json").stdout)
    assert payload["n_states"] == 3 and payload["grid_points"] <= 300
    high = payload["ask_share"]["high"]
    assert 0.0 < high < 1.0  # asks where low trust is likely, acts alone where high trust is
    assert payload["mean_belief_where_ask"]["high"][0] > payload["mean_belief_where_auto"]["high"][0]
    refused = run("policy", "paper", "--plot", plot)
    assert refused.exit_code == 2 and "3 or 4 trust states" in refused.output


def write_rated_export(folder, participants: int, seed: int) -> None:
    """trials.csv (shelves of 10 trials) and surveys.csv (a trust rating after each shelf) of the illustrative
    three-state model, whose states rate their trust 2, 5 and 8 of 10 on average."""
    import csv

    from experiment.task import Complexity, Experience, HumanAction, RobotAction
    from experiment.trust_ratings import RatingEmission, sample_ratings
    from experiment.trust_states import sample_sequences_k

    rng = np.random.default_rng(seed)
    sequences, states = sample_sequences_k(illustrative_three_state_model(), participants, 40, rng)
    ratings = sample_ratings(RatingEmission(np.array([4.0, 10.0, 16.0]), np.array([16.0, 10.0, 4.0])), states, 10,
                             rng)
    with (folder / "trials.csv").open("w", newline="") as trials, (folder / "surveys.csv").open("w", newline="") as s:
        rows = csv.writer(trials)
        rows.writerow(["participant_id", "block", "trial", "complexity", "robot_action", "human_action", "outcome",
                       "experience", "practice", "excluded", "shelf"])
        answers = csv.writer(s)
        answers.writerow(["participant_id", "context", "questionnaire", "item", "value"])
        for i, (seq, levels) in enumerate(zip(sequences, ratings.levels_by_participant, strict=True)):
            pid = f"p{i}"
            for t in range(len(seq)):
                rows.writerow([pid, 1, t + 1, Complexity.from_code(seq.complexity[t]),
                               RobotAction.from_code(seq.robot_action[t]), HumanAction.from_code(seq.human_action[t]),
                               "none", Experience.from_code(seq.experience[t]), 0, 0, t // 10 + 1])
                if levels[t] >= 0:
                    answers.writerow([pid, f"shelf:1:{t // 10 + 1}", "shelf_trust_reliance", "trust", levels[t]])
                    answers.writerow([pid, f"shelf:1:{t // 10 + 1}", "shelf_trust_reliance", "reliance", 0])


def test_fit_with_ratings_compares_on_held_out_reliance_and_writes_the_rating_emission(tmp_path):
    write_rated_export(tmp_path, participants=40, seed=4)
    model = tmp_path / "model.json"
    result = run("fit", tmp_path / "trials.csv", "--out", model, "--states", "2,3", "--cv", "3", "--restarts", "4",
                 "--with-ratings")
    assert result.exit_code == 0, result.output
    document = json.loads(model.read_text())
    assert "160 trust ratings" in result.stdout and "Mean trust rating by state" in result.stdout
    comparison, selection, ratings = document["ratings_comparison"], document["selection"], document["ratings"]
    assert selection["with_ratings"] and selection["n_ratings"] == 160 == ratings["n_ratings"]
    assert comparison["n_states"] == selection["chosen"] == document.get("n_states", 2)
    assert comparison["verdict"].startswith("the ratings ") and comparison["verdict"] in result.stdout
    scores_with, scores_without = (np.array(comparison[f"participant_scores_{w}"]) for w in ("with", "without"))
    assert comparison["difference_per_trial"] == pytest.approx((scores_with - scores_without).sum() / 1600)
    assert len(ratings["alpha"]) == comparison["n_states"] and ratings["scale"] == [0, 10]
    assert ratings["mean_rating"] == sorted(ratings["mean_rating"])  # the states rate as they rely: low to high
    model_of_chosen = trust_model_from_document(document)  # deployable as any model JSON
    assert (comparison["n_states"] == 2) == isinstance(model_of_chosen, IOHMMParams)


def test_fit_with_ratings_of_two_states_writes_the_papers_names_with_standard_errors(tmp_path):
    write_rated_export(tmp_path, participants=12, seed=6)
    model = tmp_path / "model.json"
    result = run("fit", tmp_path / "trials.csv", "--out", model, "--cv", "3", "--restarts", "2", "--with-ratings",
                 "--json")
    assert result.exit_code == 0, result.output
    document = json.loads(model.read_text())
    params_from_document(document)  # the two-state format, readable as today's
    assert "selection" not in document and document["ratings_comparison"]["n_states"] == 2  # one number: no choice
    assert set(document["stderr"]) == set(document["params"]) and "conditional" in document["fit"]["stderr_method"]
    assert document["status"]["initial"]["p_high"] in ("estimated", "boundary", "unidentified")


def test_fit_with_ratings_needs_the_surveys_file(tmp_path):
    write_rated_export(tmp_path, participants=6, seed=1)
    (tmp_path / "surveys.csv").unlink()
    result = run("fit", tmp_path / "trials.csv", "--out", tmp_path / "m.json", "--with-ratings")
    assert result.exit_code == 2 and "surveys.csv" in result.output and "Traceback" not in result.output


def rated_model_document() -> dict:
    from experiment.trust_ratings import RatingEmission

    document = k_state_document(illustrative_three_state_model())
    document["ratings"] = RatingEmission(np.array([4.0, 10.0, 16.0]), np.array([16.0, 10.0, 4.0])).to_document()
    return document


def test_simulated_people_of_a_rated_model_rate_each_shelf_and_the_fit_reads_them_back(tmp_path):
    (tmp_path / "rated.json").write_text(json.dumps(rated_model_document()))
    (tmp_path / "plain.json").write_text(json.dumps(k_state_document(illustrative_three_state_model())))
    for name in ("rated", "plain"):
        result = run("simulate", tmp_path / f"{name}.json", "--design", "model-estimation", "--participants", "8",
                     "--out", tmp_path / name)
        assert result.exit_code == 0, result.output
    # the ratings come from a random stream of their own: the same trials with and without them
    assert (tmp_path / "rated" / "trials.csv").read_text() == (tmp_path / "plain" / "trials.csv").read_text()
    assert not (tmp_path / "plain" / "surveys.csv").exists()
    import csv
    with (tmp_path / "rated" / "trials.csv").open() as handle:
        shelves = {(row["participant_id"], row["block"], row["shelf"]) for row in csv.DictReader(handle)}
    with (tmp_path / "rated" / "surveys.csv").open() as handle:
        answers = list(csv.DictReader(handle))
    assert {(a["participant_id"], a["block"], a["shelf"]) for a in answers} == shelves  # one rating per shelf
    assert len(answers) == len(shelves) and {a["item"] for a in answers} == {"trust"}
    assert all(0 <= int(a["value"]) <= 10 and a["context"] == f"shelf:{a['block']}:{a['shelf']}" for a in answers)
    fitted = run("fit", tmp_path / "rated" / "trials.csv", "--out", tmp_path / "m.json", "--states", "3", "--cv", "2",
                 "--restarts", "2", "--with-ratings")
    assert fitted.exit_code == 0, fitted.output
    assert f"{len(answers)} trust ratings" in fitted.stdout


def test_a_malformed_rating_section_is_refused_in_one_line(tmp_path):
    document = rated_model_document()
    document["ratings"]["alpha"] = [1.0, -2.0, 3.0]
    (tmp_path / "bad.json").write_text(json.dumps(document))
    result = run("simulate", tmp_path / "bad.json", "--design", "model-estimation", "--participants", "2")
    assert result.exit_code == 2 and "rating alpha and beta must be positive" in result.output


def test_recovery_of_a_rated_model_refits_with_the_ratings_and_reports_the_mean_ratings(tmp_path):
    (tmp_path / "rated.json").write_text(json.dumps(rated_model_document()))
    result = run("simulate", tmp_path / "rated.json", "--design", "model-estimation", "--participants", "20",
                 "--replications", "2", "--recover", "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert [r["state"] for r in payload["ratings"]] == [0, 1, 2]
    assert [round(r["true"], 6) for r in payload["ratings"]] == [2.0, 5.0, 8.0]
    assert all(r["rmse"] >= abs(r["bias"]) for r in payload["ratings"])
    assert {p["name"] for p in payload["parameters"]} >= {"emissions.high.auto.p_rely_state_2"}


@pytest.mark.parametrize(("scale", "message"), [("0,5", "must be a whole number 0…5"), ("ten", "MIN,MAX"),
                                                ("3,3", "must exceed MIN")])
def test_fit_with_ratings_on_another_scale_reads_it_or_refuses(tmp_path, scale, message):
    write_rated_export(tmp_path, participants=6, seed=1)
    result = run("fit", tmp_path / "trials.csv", "--out", tmp_path / "m.json", "--with-ratings", "--rating-scale",
                 scale)
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output
