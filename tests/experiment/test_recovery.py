import json
import math
from dataclasses import replace

import numpy as np
import pytest

from experiment.iohmm import PARAMETER_NAMES, ModelError, paper_params
from experiment.participants.reliance import KStateHuman, simulated_human
from experiment.recovery import recover, sequence_of, summarise, verdict
from experiment.simulate import simulate_study
from experiment.task import Complexity, Experience, HumanAction, RobotAction
from experiment.templates import template
from experiment.trust_states import KStateParams, illustrative_three_state_model


def test_the_figures_of_one_parameter():
    estimates, stderrs = np.array([0.5, 0.7, 0.62, 0.0]), np.array([0.1, 0.05, 0.02, math.nan])
    figures = summarise("p", 0.6, estimates, stderrs, ["estimated", "estimated", "estimated", "boundary"], 4)
    errors = estimates - 0.6
    assert figures.bias == pytest.approx(errors.mean()) and figures.rmse == pytest.approx(np.sqrt((errors ** 2).mean()))
    # 0.5 ± 0.196 holds 0.6; 0.7 ± 0.098 does not; 0.62 ± 0.039 does
    assert figures.coverage == pytest.approx(2 / 3) and figures.mean_stderr == pytest.approx(np.mean([0.1, 0.05, 0.02]))
    assert (figures.n_exercised, figures.n_estimated, figures.n_boundary) == (4, 3, 1)
    assert figures.verdict == "intervals off" and figures.identified  # intervals in most studies, but off


def test_the_verdicts():
    assert verdict(19, 1, 0.95, 20) == "recovered"
    assert verdict(19, 1, 0.80, 20) == "intervals off"
    assert verdict(3, 17, math.nan, 20) == "at a bound"
    assert verdict(3, 2, 0.9, 20) == "not identified"


def test_a_sequence_leaves_the_practice_trials_out():
    sim = simulate_study(template("demo-fast"), paper_params(), 1, seed=0)
    [participant] = sim.participants
    records = [replace(r, practice=True) if i < 2 else r for i, r in enumerate(participant.records)]
    seq = sequence_of(records)
    assert len(seq) == len(records) - 2
    assert seq.human_action.tolist() == [r.human_action.code for r in records[2:]]


def test_a_recovery_run_of_the_paper_model_repeats_and_flags_what_sits_at_a_bound():
    config = template("model-estimation")
    result = recover(config, paper_params(), 8, 3, seed=1, restarts=3)
    true = paper_params().to_vector()
    assert [p.name for p in result.parameters] == [n for n, v in zip(PARAMETER_NAMES, true, strict=True)
                                                   if not math.isnan(v)]
    by_name = {p.name: p for p in result.parameters}
    # the paper's P(rely | high trust, low complexity) is 1: its estimates sit at the bound, no interval
    assert by_name["emissions.low.auto.p_rely_high"].verdict == "at a bound"
    assert "emissions.low.auto.p_rely_high" in result.not_identified()
    for p in result.parameters:
        assert p.n_exercised <= 3 and p.n_estimated + p.n_boundary + p.n_unidentified <= 3
        assert math.isnan(p.coverage) or 0.0 <= p.coverage <= 1.0
    again = recover(config, paper_params(), 8, 3, seed=1, restarts=3)
    assert json.dumps(again.to_dict()) == json.dumps(result.to_dict())
    with pytest.raises(ValueError, match="2 replications"):
        recover(config, paper_params(), 8, 1)


def test_a_three_state_model_is_recovered_with_three_states():
    truth = illustrative_three_state_model()
    result = recover(template("model-estimation"), truth, 10, 2, seed=0, restarts=3)
    names = [p.name for p in result.parameters]
    assert names[:3] == ["initial.state_0", "initial.state_1", "initial.state_2"]
    assert names[-1] == "emissions.high.auto.p_rely_state_2" and len(names) == 3 + 8 * 9 + 6
    by_name = {p.name: p for p in result.parameters}
    assert by_name["emissions.high.auto.p_rely_state_2"].true == pytest.approx(0.95)
    assert by_name["emissions.high.auto.p_rely_state_2"].n_exercised == 2


def test_a_three_state_participant_draws_from_its_model():
    truth = illustrative_three_state_model()
    rng = np.random.default_rng(3)
    people = [simulated_human(truth, rng) for _ in range(4000)]
    assert all(isinstance(p, KStateHuman) for p in people)
    np.testing.assert_allclose(np.bincount([p.state for p in people], minlength=3) / 4000, truth.initial, atol=0.03)
    stuck = KStateParams(np.array([0.0, 1.0, 0.0]), np.broadcast_to(np.eye(3), (2, 2, 2, 3, 3)).copy(),
                         np.array([[0.9, 0.8, 0.7], [0.1, 0.3, 0.9]]))
    person = KStateHuman(stuck, rng)
    answers = [person.respond(Complexity.HIGH, RobotAction.AUTO) for _ in range(4000)]
    assert answers.count(HumanAction.RELY) / 4000 == pytest.approx(0.3, abs=0.03)
    assert person.respond(Complexity.HIGH, RobotAction.ASK) == HumanAction.INTERVENE
    person.update(Complexity.LOW, RobotAction.AUTO, Experience.POSITIVE)
    assert person.state == 1  # the identity row keeps the state
    transition = np.array(stuck.transition)
    transition[0, 1, 1] = np.nan  # asked in low complexity, positive: never seen
    no_estimate = KStateParams(stuck.initial, transition, stuck.p_rely)
    with pytest.raises(ModelError, match="no transition estimate"):
        KStateHuman(no_estimate, rng).update(Complexity.LOW, RobotAction.ASK, Experience.POSITIVE)
