from collections import Counter

import numpy as np
import pytest

from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.iohmm import filter_beliefs, paper_params, update_belief
from experiment.simulate import compare_blocks, power_analysis, simulate_study
from experiment.task import Complexity, HumanAction, RobotAction, resolve_trial
from experiment.templates import TEMPLATES, demo, model_estimation, policy_evaluation


@pytest.mark.parametrize("name", sorted(TEMPLATES))
def test_templates_validate_and_round_trip(name):
    config = TEMPLATES[name]()
    assert StudyConfig.model_validate_json(config.model_dump_json()) == config


def test_paper_designs():
    study1 = model_estimation()
    assert [b.schedule.n_trials for b in study1.blocks] == [71]
    study2 = policy_evaluation()
    assert [b.schedule.n_trials for b in study2.blocks] == [40, 40]
    assert [b.policy.kind for b in study2.blocks] == ["trust_aware", "trust_agnostic"]


def test_plan_follows_schedule_and_is_reproducible():
    runtime = StudyRuntime(policy_evaluation())
    plan = runtime.plan("p-1", ["trust_agnostic", "trust_aware"])
    assert len(plan) == 80 and plan[0].block_name == "trust_agnostic" and plan[40].block == 2
    for block in (1, 2):
        counts = Counter(t.complexity for t in plan if t.block == block)
        assert counts == {Complexity.LOW: 20, Complexity.HIGH: 20}
    assert plan == runtime.plan("p-1", ["trust_agnostic", "trust_aware"])
    assert [t.complexity for t in plan] != [t.complexity
                                            for t in runtime.plan("p-2", ["trust_agnostic", "trust_aware"])]
    assert sum(t.shelf_end for t in plan) == 10  # 5 shelves of 8 per block


def test_simulated_records_are_consistent():
    config = policy_evaluation()
    sim = simulate_study(config, paper_params(), 20, seed=3)
    records = sim.records()
    assert len(records) == 20 * 80
    assert Counter(p.block_order for p in sim.participants) == {("trust_aware", "trust_agnostic"): 10,
                                                                 ("trust_agnostic", "trust_aware"): 10}
    for p in sim.participants:
        beliefs = filter_beliefs(paper_params(), [(r.complexity, r.robot_action, r.human_action, r.experience)
                                                  for r in p.records])
        assert np.allclose([r.belief_before for r in p.records], beliefs[:-1])
        assert np.allclose([r.belief_after for r in p.records], beliefs[1:])
        assert p.records[-1].score == pytest.approx(sum(r.reward for r in p.records))
        for r in p.records:
            success = r.outcome.value == "success"
            again = resolve_trial(r.complexity, r.robot_action, r.human_action, success, config.task)
            assert (again.experience, again.reward) == (r.experience, r.reward)
            if r.robot_action == RobotAction.ASK:
                assert r.human_action == HumanAction.INTERVENE
            if r.policy == "trust_agnostic":
                assert r.robot_action == RobotAction.AUTO  # paper: never ask
            if r.policy == "trust_aware" and r.complexity == Complexity.LOW:
                assert r.robot_action == RobotAction.AUTO


def test_trust_aware_acts_on_threshold():
    config = policy_evaluation()
    runtime = StudyRuntime(config)
    threshold = runtime.policies["trust_aware"].solution.thresholds[Complexity.HIGH]
    sim = simulate_study(config, paper_params(), 10, seed=1, runtime=runtime)
    high = [r for r in sim.records() if r.policy == "trust_aware" and r.complexity == Complexity.HIGH]
    assert high and all((r.robot_action == RobotAction.AUTO) == (r.policy_belief > threshold) for r in high
                        if abs(r.policy_belief - threshold) > 1e-6)


def test_same_seed_same_study():
    a = simulate_study(demo(), paper_params(), 6, seed=9).records()
    b = simulate_study(demo(), paper_params(), 6, seed=9).records()
    c = simulate_study(demo(), paper_params(), 6, seed=10).records()
    assert a == b and a != c


def test_power_analysis_runs_and_reports_a_fraction():
    config = demo()
    result = power_analysis(config, paper_params(), 8, 5, block_a="trust_aware", block_b="trust_agnostic", seed=2)
    assert 0.0 <= result.power <= 1.0 and result.p_values.shape == (5,)
    sim = simulate_study(config, paper_params(), 8, seed=2)
    assert compare_blocks(sim, "trust_aware", "trust_agnostic").test.df == 14


def test_study_belief_matches_update_rule():
    p = paper_params()
    config = demo()
    sim = simulate_study(config, p, 2, seed=0)
    r = sim.records()[0]
    assert r.belief_after == pytest.approx(update_belief(p, r.belief_before, r.complexity, r.robot_action,
                                                         r.human_action, r.experience, config.belief_update))
