"""Closing the loop without a server: hashes, trial provenance, the fit bundle, the evaluation config, power sweeps."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest

from experiment.agnostic import baseline_from_rates, intervention_rates
from experiment.belief_mdp import solve_belief_mdp
from experiment.engine import StudyRuntime
from experiment.evaluation import EVALUATION_TEMPLATES, design_p_high, evaluation_config, fit_bundle, rates_of
from experiment.fit import fit_iohmm
from experiment.iohmm import ModelError, model_document, paper_params
from experiment.provenance import canonical_json, content_hash, data_hash, model_hash, study_provenance
from experiment.records import read_model_trials, read_sequences, write_trials_csv
from experiment.simulate import PowerResult, PowerSweep, power_sweep, simulate_study
from experiment.task import Complexity, TaskParams
from experiment.templates import demo, model_estimation, policy_evaluation

PAPER_RATES = {Complexity.LOW: 0.006, Complexity.HIGH: 0.1848}


def test_content_hash_is_of_the_canonical_json():
    assert content_hash({"b": 1, "a": [1.5, None]}) == content_hash({"a": [1.5, None], "b": 1})
    assert content_hash({"a": 1}) != content_hash({"a": 1.0000001})
    assert canonical_json({"b": 1, "a": "é"}) == '{"a":"é","b":1}'
    with pytest.raises(ValueError):
        content_hash({"a": math.nan})
    assert model_hash("paper") == content_hash(model_document(paper_params()))


def test_trial_provenance_per_block():
    document = model_document(paper_params())
    config = evaluation_config(document, PAPER_RATES, template_name="demo")
    blocks, practice = study_provenance(config)
    assert {b.model_hash for b in blocks.values()} == {practice.model_hash} == {content_hash(document)}
    assert len({blocks["trust_aware"].policy_hash, blocks["trust_agnostic"].policy_hash, practice.policy_hash}) == 3
    assert {b.seed for b in blocks.values()} == {config.seed}
    # The policy hash follows what the policy does: another p_high or other rates change only their block.
    other_p = study_provenance(evaluation_config(document, PAPER_RATES, template_name="demo", p_high=0.3))[0]
    assert other_p["trust_aware"].policy_hash != blocks["trust_aware"].policy_hash
    assert other_p["trust_agnostic"] == blocks["trust_agnostic"]
    other_rates = study_provenance(evaluation_config(document, {**PAPER_RATES, Complexity.HIGH: 0.5},
                                                     template_name="demo"))[0]
    assert other_rates["trust_agnostic"].policy_hash != blocks["trust_agnostic"].policy_hash
    # p_high left open resolves to the schedule's fraction: the same policy as giving it.
    assert study_provenance(evaluation_config(document, PAPER_RATES, template_name="demo", p_high=0.5))[0] == blocks
    # A trust-aware block with its own model records that model; other blocks the study's.
    own = document | {"params": {**document["params"], "initial": {"p_high": 0.5}}}
    mixed = config.model_copy(update={"model": "paper", "blocks": [
        b.model_copy(update={"policy": b.policy.model_copy(update={"model": own})}) if b.policy.kind == "trust_aware"
        else b for b in config.blocks]})
    mixed_blocks = study_provenance(mixed)[0]
    assert mixed_blocks["trust_aware"].model_hash == content_hash(own)
    assert mixed_blocks["trust_agnostic"].model_hash == model_hash("paper")


def test_simulated_records_carry_provenance_and_readers_ignore_it(tmp_path):
    config = policy_evaluation()
    runtime = StudyRuntime(config)
    sim = simulate_study(config, paper_params(), 2, seed=5)
    for record in sim.records():
        expected = runtime.block_provenance[record.block_name]
        assert (record.model_hash, record.policy_hash, record.seed) == (expected.model_hash, expected.policy_hash, 0)
    buffer = io.StringIO()
    write_trials_csv(sim.records(), buffer)
    rows = list(csv.DictReader(io.StringIO(buffer.getvalue())))
    assert [(r["model_hash"], r["policy_hash"], r["seed"]) for r in rows] == \
        [(r.model_hash, r.policy_hash, str(r.seed)) for r in sim.records()]
    path = tmp_path / "trials.csv"
    path.write_text(buffer.getvalue(), encoding="utf-8")
    ids, sequences = read_sequences(path)
    assert ids == ["sim-0001", "sim-0002"] and [len(s) for s in sequences] == [80, 80]


def test_fit_bundle_is_the_fit_its_policy_and_the_baseline_of_the_same_data(tmp_path):
    sim = simulate_study(model_estimation(), paper_params(), 12, seed=2)
    buffer = io.StringIO()
    write_trials_csv(sim.records(), buffer)
    (tmp_path / "trials.csv").write_text(buffer.getvalue(), encoding="utf-8")
    participants, sequences = read_sequences(tmp_path / "trials.csv")
    fitted_on = {"participants": participants, "data_hash": data_hash(read_model_trials(tmp_path / "trials.csv"))}
    bundle = fit_bundle(sequences, restarts=2, seed=3, p_high=0.5, fitted_on=fitted_on)
    direct = fit_iohmm(sequences, restarts=2, seed=3)
    assert bundle.document == direct.to_document(fitted_on=fitted_on)
    assert bundle.content_hash == content_hash(bundle.document)
    solution = solve_belief_mdp(direct.params, TaskParams(), p_high=0.5)
    assert bundle.policy["threshold"] == {c.value: solution.thresholds[c] for c in Complexity}
    assert bundle.policy["error"] is None and bundle.policy["p_high"] == 0.5
    assert bundle.agnostic == baseline_from_rates(intervention_rates(sequences))
    assert rates_of(bundle.agnostic) == intervention_rates(sequences).rates


def test_evaluation_config_deploys_the_model_against_the_baseline():
    document = model_document(paper_params())
    config = evaluation_config(document, PAPER_RATES, title="Next study")
    assert config.title == "Next study" and config.model == document and config.counterbalance == "all"
    aware = next(b for b in config.blocks if b.policy.kind == "trust_aware")
    agnostic = next(b for b in config.blocks if b.policy.kind == "trust_agnostic")
    assert aware.policy.model == document and aware.policy.p_high is None
    assert (agnostic.policy.intervention_rate_low, agnostic.policy.intervention_rate_high) == (0.006, 0.1848)
    assert [b.schedule for b in config.blocks] == [b.schedule for b in policy_evaluation().blocks]
    assert config.questionnaires_before == policy_evaluation().questionnaires_before
    evaluation = evaluation_config(document, PAPER_RATES, template_name="demo")
    assert evaluation.blocks[0].schedule == demo().blocks[0].schedule
    assert design_p_high() == 0.5 and set(EVALUATION_TEMPLATES) == {"policy-evaluation", "demo", "demo-fast"}


@pytest.mark.parametrize(("change", "message"), [
    ({"rates": {Complexity.LOW: None, Complexity.HIGH: 0.2}}, "intervention rate for low"),
    ({"template_name": "model-estimation"}, "unknown evaluation design"),
    ({"document": {"format": "something else"}}, "not a trustlab model document"),
])
def test_evaluation_config_refuses_what_cannot_run(change, message):
    arguments = {"document": model_document(paper_params()), "rates": PAPER_RATES} | change
    with pytest.raises((ValueError, ModelError), match=message):
        evaluation_config(arguments.pop("document"), arguments.pop("rates"), **arguments)


def _result(n: int, power: float) -> PowerResult:
    return PowerResult(n, 10, 0.05, power, 1.0, 0.5, np.zeros(10), np.zeros(10), {})


def test_participants_needed_is_the_smallest_n_reaching_the_target():
    assert PowerSweep([_result(10, 0.3), _result(20, 0.8), _result(40, 0.95)], 0.8).participants_needed() == 20
    assert PowerSweep([_result(10, 0.3), _result(20, 0.79)], 0.8).participants_needed() is None


def test_power_sweep_runs_each_n_with_progress():
    seen = []
    sweep = power_sweep(demo(), paper_params(), [6, 3], 3, block_a="trust_aware", block_b="trust_agnostic", seed=1,
                        progress=lambda n, done, total: seen.append((n, done, total)))
    assert [r.n_participants for r in sweep.results] == [3, 6]
    assert seen == [(3, 1, 3), (3, 2, 3), (3, 3, 3), (6, 1, 3), (6, 2, 3), (6, 3, 3)]
    for result in sweep.results:
        shape = (3, result.n_participants)
        assert result.rewards["trust_aware"].shape == result.rewards["trust_agnostic"].shape == shape
        assert result.mean_difference == pytest.approx(np.mean(result.differences))
        assert np.allclose(result.differences, result.rewards["trust_aware"].mean(axis=1)
                           - result.rewards["trust_agnostic"].mean(axis=1))
    with pytest.raises(ValueError, match="at least 2"):
        power_sweep(demo(), paper_params(), [1, 4], 3, block_a="trust_aware", block_b="trust_agnostic")
