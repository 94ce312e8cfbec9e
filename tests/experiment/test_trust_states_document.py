"""Issue 40: the model JSON of a K-state model, and a study that plans and keeps its belief with one."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from experiment.belief_mdp import BeliefMDPSolution
from experiment.config import StudyConfig, TrustAwareSpec
from experiment.engine import StudyRuntime, simplex_resolution
from experiment.evaluation import evaluation_config
from experiment.iohmm import IOHMMParams, ModelError, model_document, paper_params, params_from_document
from experiment.policies import PolicyKind, TrustAware
from experiment.records import TrialRecord
from experiment.sequences import Sequence
from experiment.simulate import simulate_study
from experiment.task import Complexity, RobotAction
from experiment.templates import template
from experiment.trust_belief import p_highest, update_belief_k
from experiment.trust_states import KStateParams, filter_beliefs_k, from_iohmm, illustrative_three_state_model
from experiment.trust_states_document import (
    K_FORMAT,
    k_state_document,
    k_state_params_from_document,
    load_trust_model_document,
    parameter_names,
    trust_model_from_document,
)
from experiment.trust_states_policy import KPolicySolution
from tests.experiment.test_trust_states import three_state_model

RATES = {Complexity.LOW: 0.1, Complexity.HIGH: 0.6}


def four_state_model() -> KStateParams:
    rng = np.random.default_rng(4)
    transition = rng.dirichlet(np.ones(4), size=(2, 2, 2, 4))
    transition[1, 1, 1, 2] = np.nan  # an input the data never exercised
    p_rely = np.sort(rng.uniform(size=(2, 4)), axis=1)
    return KStateParams(rng.dirichlet(np.ones(4)), transition, p_rely)


def assert_same_params(a: KStateParams, b: KStateParams) -> None:
    for name in ("initial", "transition", "p_rely"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


# -- the document ---------------------------------------------------------------

@pytest.mark.parametrize("make", [three_state_model, four_state_model])
def test_round_trip_through_json_keeps_every_number_and_the_extra_keys(make):
    params = make()
    document = k_state_document(params, fitted_on={"participants": ["p1"]}, fit={"converged": True})
    assert document["format"] == K_FORMAT and document["version"] == 1
    assert document["n_states"] == params.n_states
    assert document["states"] == [f"state_{j}" for j in range(params.n_states)]
    assert document["fitted_on"] == {"participants": ["p1"]} and document["fit"] == {"converged": True}
    assert set(document["params"]) == {"initial", "transitions", "emissions"}
    assert document["params"]["emissions"]["high"]["auto"]["p_rely_state_0"] == params.p_rely[1, 0]
    read = k_state_params_from_document(json.loads(json.dumps(document)))
    assert_same_params(read, params)
    assert trust_model_from_document(document).n_states == params.n_states  # type: ignore[union-attr]


def test_unseen_transition_rows_are_null():
    document = k_state_document(four_state_model())
    row = document["params"]["transitions"]["high"]["ask"]["positive"]["from_state_2"]
    assert row == {f"to_state_{j}": None for j in range(4)}


def test_a_two_state_model_is_todays_document_exactly():
    paper = paper_params()
    assert k_state_document(from_iohmm(paper), note="x") == model_document(paper, note="x")
    read = trust_model_from_document(model_document(paper))
    assert isinstance(read, IOHMMParams)
    np.testing.assert_array_equal(read.to_vector(), paper.to_vector())
    assert_same_params(k_state_params_from_document(model_document(paper)), from_iohmm(paper))


def test_states_are_written_lowest_trust_first():
    params = three_state_model()
    relabelled = params.permuted(np.array([2, 0, 1]))
    assert_same_params(k_state_params_from_document(k_state_document(relabelled)), params)


def _set(document: dict, dotted: str, value) -> dict:
    changed = copy.deepcopy(document)
    *path, leaf = dotted.split(".")
    node = changed
    for key in path:
        node = node[key]
    node[leaf] = value
    return changed


def _bad_documents():
    good = k_state_document(three_state_model())
    row = "params.transitions.low.auto.negative.from_state_0"
    unordered = copy.deepcopy(good)
    unordered["params"]["emissions"]["high"]["auto"]["p_rely_state_0"] = 0.99
    extra_parameter = copy.deepcopy(good)
    extra_parameter["params"]["initial"]["state_3"] = 0.0
    missing = copy.deepcopy(good)
    del missing["params"]["emissions"]["low"]
    return [
        ([1, 2], "a JSON object"),
        (good | {"format": "other"}, "not a trustlab model document"),
        (good | {"version": 2}, "unsupported trustlab-iohmm-k version"),
        (good | {"n_states": 5}, "n_states"),
        (good | {"n_states": 2, "states": ["state_0", "state_1"]}, "trustlab-iohmm"),
        (good | {"n_states": 3.0}, "n_states"),
        (good | {"n_states": True}, "n_states"),
        (good | {"states": ["low", "mid", "high"]}, "states must be"),
        (good | {"params": []}, "no \"params\" object"),
        (missing, "'emissions.low.auto.p_rely_state_0' is missing"),
        (extra_parameter, "unknown model parameter 'initial.state_3'"),
        (_set(good, "params.initial.state_0", 0.5), "initial must sum to 1"),
        (_set(good, "params.initial.state_0", -0.1), "probability in [0, 1]"),
        (_set(good, "params.initial.state_0", float("nan")), "probability in [0, 1]"),
        (_set(good, "params.initial.state_0", float("inf")), "probability in [0, 1]"),
        (_set(good, "params.initial.state_0", "0.2"), "must be a number"),
        (_set(good, "params.initial.state_0", True), "must be a number"),
        (_set(good, "params.initial.state_0", None), "only a whole transition row may be null"),
        (_set(good, f"{row}.to_state_1", None), "only a whole transition row may be null"),
        (_set(good, f"{row}.to_state_1", 0.5), "transitions.low.auto.negative.from_state_0 must sum to 1"),
        (_set(good, "params.emissions.low.auto.p_rely_state_1", 1.5), "probability in [0, 1]"),
        (unordered, "lowest trust to the highest"),
    ]


@pytest.mark.parametrize(("document", "reason"), _bad_documents())
def test_a_bad_document_is_a_model_error_that_says_why(document, reason):
    with pytest.raises(ModelError, match=reason.replace("[", r"\[").replace("(", r"\(")):
        k_state_params_from_document(document)


def test_a_bad_document_is_a_config_error_too():
    document = _set(k_state_document(three_state_model()), "params.initial.state_0", 0.5)
    with pytest.raises(ValueError, match="initial must sum to 1"):
        TrustAwareSpec(model=document)


def test_a_model_file_of_either_format_loads(tmp_path):
    path = tmp_path / "model.json"
    document = k_state_document(three_state_model(), fitted_on={"x": 1})
    path.write_text(json.dumps(document))
    assert load_trust_model_document(str(path)) == document
    assert load_trust_model_document("paper") == model_document(paper_params())
    path.write_text("{")
    with pytest.raises(ModelError, match="not valid JSON"):
        load_trust_model_document(str(path))


def test_parameter_names_count():
    assert len(parameter_names(3)) == 3 + 8 * 9 + 2 * 3


# -- the belief ------------------------------------------------------------------

@pytest.mark.parametrize("make", [three_state_model, four_state_model])
def test_one_step_update_is_the_filters_step(make):
    params = make()
    rng = np.random.default_rng(0)
    robot = rng.integers(0, 2, 40)
    human = np.where(robot == 1, 1, rng.integers(0, 2, 40))
    complexity, experience = rng.integers(0, 2, 40), rng.integers(0, 2, 40)
    if params.n_states == 4:  # avoid the input without an estimate
        experience[(complexity == 1) & (robot == 1)] = 0
    seq = Sequence(complexity, robot, human, experience)
    expected = filter_beliefs_k(params, seq)
    belief = params.initial
    for t, (c, a, o, e) in enumerate(seq.trials()):
        belief = update_belief_k(params, belief, c, a, o, e)
        np.testing.assert_array_equal(belief, expected[t + 1])


def test_p_highest():
    assert p_highest(0.25) == 0.25 and p_highest([0.1, 0.2, 0.7]) == 0.7


def test_simplex_resolution_is_a_budget_of_grid_points():
    assert simplex_resolution(2, 1001) == 1000
    assert simplex_resolution(3, 1001) == 43  # C(45, 2) = 990 ≤ 1001 < C(46, 2)
    assert simplex_resolution(4, 1001) == 16  # C(19, 3) = 969 ≤ 1001 < C(20, 3)


# -- a study of a K-state model --------------------------------------------------

def _sequence(records: list[TrialRecord]) -> Sequence:
    return Sequence([r.complexity.code for r in records], [r.robot_action.code for r in records],
                    [r.human_action.code for r in records], [r.experience.code for r in records])


def assert_decisions_follow_the_k_state_filter(config: StudyConfig, params: KStateParams, block_name: str,
                                               records: list[TrialRecord], *, study_belief: bool) -> int:
    """Every trust-aware trial's action is ``KPolicySolution.action`` on the K-state filter's belief of the trials
    before it; returns how many trust-aware trials there were."""
    runtime = StudyRuntime(config)
    policy = runtime.policies[block_name]
    assert isinstance(policy, TrustAware) and isinstance(policy.solution, KPolicySolution)
    scored = [r for r in records if not r.practice]
    beliefs = filter_beliefs_k(params, _sequence(scored))
    aware = 0
    for t, record in enumerate(scored):
        if record.block_name == block_name:
            aware += 1
            assert record.policy == PolicyKind.TRUST_AWARE
            assert record.robot_action == policy.solution.action(beliefs[t], record.complexity)
            assert record.policy_belief == pytest.approx(beliefs[t][-1], abs=1e-12)
        if study_belief:
            assert record.belief_before == pytest.approx(beliefs[t][-1], abs=1e-12)
            assert record.belief_after == pytest.approx(beliefs[t + 1][-1], abs=1e-12)
    return aware


def test_an_evaluation_study_of_a_three_state_model_plans_and_keeps_a_belief_vector():
    params = three_state_model()
    document = k_state_document(params)
    config = evaluation_config(document, RATES, template_name="demo-fast")
    config = StudyConfig.model_validate(json.loads(config.model_dump_json()))  # as stored and read back
    runtime = StudyRuntime(config)
    assert runtime.initial_beliefs() == {"": [0.2, 0.3, 0.5]}  # the block's model is the study's: one belief
    aware = next(b.name for b in config.blocks if b.policy.kind == "trust_aware")
    simulation = simulate_study(config, paper_params(), 3, seed=2)
    actions = set()
    for participant in simulation.participants:
        n = assert_decisions_follow_the_k_state_filter(config, params, aware, participant.records, study_belief=True)
        assert n == config.block(aware).schedule.n_trials
        actions |= {r.robot_action for r in participant.records if r.block_name == aware}
    assert actions == {RobotAction.AUTO, RobotAction.ASK}  # the belief decides, not a constant


def test_a_block_with_its_own_three_state_model_in_a_study_of_the_papers_model():
    params = three_state_model()
    base = template("demo-fast")
    data = base.model_dump(mode="json")
    aware = next(b for b in data["blocks"] if b["policy"]["kind"] == "trust_aware")
    aware["policy"]["model"] = k_state_document(params)
    config = StudyConfig.model_validate(data)
    runtime = StudyRuntime(config)
    beliefs = runtime.initial_beliefs()
    assert beliefs[""] == paper_params().initial_high and beliefs[aware["name"]] == [0.2, 0.3, 0.5]
    for participant in simulate_study(config, paper_params(), 2, seed=5).participants:
        assert_decisions_follow_the_k_state_filter(config, params, aware["name"], participant.records,
                                                   study_belief=False)


def test_a_two_state_study_is_as_before():
    config = evaluation_config(model_document(paper_params()), RATES, template_name="demo-fast")
    runtime = StudyRuntime(config)
    assert runtime.initial_beliefs() == {"": paper_params().initial_high}
    policy = next(p for p in runtime.policies.values() if isinstance(p, TrustAware))
    assert isinstance(policy.solution, BeliefMDPSolution) and isinstance(policy.belief_model, IOHMMParams)
    assert policy.solution.grid == 1001
    for record in simulate_study(config, paper_params(), 1, seed=1).records():
        assert isinstance(record.belief_before, float)


def test_a_reader_of_the_two_state_model_names_a_model_of_more_states_as_such():
    document = k_state_document(illustrative_three_state_model())
    with pytest.raises(ModelError, match="a model of 3 trust states; here only the paper's two-state model"):
        params_from_document(document)
