import functools
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiment import defaults
from experiment.belief_mdp import myopic_threshold, solve_belief_mdp
from experiment.iohmm import IOHMMParams, ModelError, paper_params, update_belief
from experiment.task import Complexity as C
from experiment.task import Experience as E
from experiment.task import ExperienceRule, RewardTable, TaskParams, expected_reward_given_action, p_positive_experience
from experiment.task import HumanAction as O
from experiment.task import RobotAction as A

STUDY1 = defaults.STUDY1_TRIALS_HIGH / (defaults.STUDY1_TRIALS_LOW + defaults.STUDY1_TRIALS_HIGH)  # 30/71
STUDY2 = 0.5
#: Our thresholds in high complexity, paper_params(), gamma = 0.99, grid 1001 (see the module docstring).
EXPECTED_HIGH = {("bayes", STUDY1): 0.70481, ("bayes", STUDY2): 0.69053,
                 ("paper", STUDY1): 0.69911, ("paper", STUDY2): 0.69325}
CASES = list(EXPECTED_HIGH)


@functools.cache
def paper_solution(method, p_high, grid=1001):
    return solve_belief_mdp(paper_params(), p_high=p_high, grid=grid, belief_update=method)


@pytest.mark.parametrize(("method", "p_high"), CASES)
def test_paper_policy_never_asks_in_low_and_has_a_threshold_in_high(method, p_high):
    solution = paper_solution(method, p_high)
    assert solution.thresholds[C.LOW] is None and solution.constant_action[C.LOW] == A.AUTO
    assert (solution.policy[:, C.LOW.code] == A.AUTO.code).all()
    assert solution.threshold_shaped[C.HIGH] and solution.constant_action[C.HIGH] is None
    threshold = solution.thresholds[C.HIGH]
    assert 0.6 <= threshold <= myopic_threshold(paper_params(), complexity=C.HIGH)
    assert threshold == pytest.approx(EXPECTED_HIGH[method, p_high], abs=1e-4)
    high = solution.policy[0, C.HIGH.code]
    assert (high[solution.beliefs < threshold] == A.ASK.code).all()
    assert (high[solution.beliefs > threshold] == A.AUTO.code).all()
    assert solution.action(threshold - 1e-3, C.HIGH) == A.ASK and solution.action(threshold + 1e-3, C.HIGH) == A.AUTO
    assert solution.action(0.0, C.LOW) == A.AUTO


@pytest.mark.parametrize(("method", "p_high"), CASES)
def test_threshold_converges_as_the_grid_is_refined(method, p_high):
    thresholds = [paper_solution(method, p_high, grid).thresholds[C.HIGH] for grid in (201, 1001, 4001)]
    assert max(thresholds) - min(thresholds) < 1e-3


def test_myopic_threshold_is_the_discount_zero_solution():
    params = paper_params()
    assert myopic_threshold(params, complexity=C.HIGH) == pytest.approx(0.7255, abs=1e-4)
    assert myopic_threshold(params, complexity=C.LOW) is None  # acting always pays in low complexity
    for method in ("bayes", "paper"):
        solution = solve_belief_mdp(params, p_high=STUDY2, grid=101, discount=0.0, belief_update=method)
        assert solution.thresholds[C.HIGH] == pytest.approx(myopic_threshold(params, complexity=C.HIGH), abs=1e-12)
        assert solution.constant_action[C.LOW] == A.AUTO and solution.iterations == 1


def test_policy_does_not_depend_on_experience():
    solution = paper_solution("bayes", STUDY2)
    assert solution.depends_on_experience is False
    assert np.array_equal(solution.q[0], solution.q[1]) and np.array_equal(solution.policy[0], solution.policy[1])
    for b in np.linspace(0, 1, 23):
        assert solution.action(b, C.HIGH, E.POSITIVE) == solution.action(b, C.HIGH, E.NEGATIVE)


def test_json_output_contract():
    doc = json.loads(json.dumps(paper_solution("bayes", STUDY2).to_dict()))
    assert doc["threshold"]["low"] is None and doc["action"]["low"] == "auto"
    assert doc["threshold"]["high"] == pytest.approx(EXPECTED_HIGH["bayes", STUDY2], abs=1e-4)
    assert doc["action"]["high"] is None
    assert (doc["p_high"], doc["grid"], doc["discount"], doc["belief_update"]) == (0.5, 1001, 0.99, "bayes")
    assert doc["iterations"] > 0 and doc["residual"] < doc["tolerance"] and doc["depends_on_experience"] is False


def test_ties_go_to_ask():
    flat = TaskParams(rewards=RewardTable(auto_rely_success=1.0, auto_rely_failure=1.0, auto_intervene=1.0, ask=1.0))
    solution = solve_belief_mdp(paper_params(), flat, p_high=STUDY2, grid=51, discount=0.0)
    assert solution.constant_action == {C.LOW: A.ASK, C.HIGH: A.ASK}
    assert solution.action(0.5, C.LOW) == A.ASK


def test_needed_missing_estimate_is_a_model_error():
    vector = paper_params().to_vector()
    vector[1 + 8 + 2] = np.nan  # transitions.high.auto.positive.from_low
    with pytest.raises(ModelError, match=r"transitions\.high\.auto\.positive\.from_low"):
        solve_belief_mdp(IOHMMParams.from_vector(vector), p_high=STUDY2, grid=51)
    vector = paper_params().to_vector()
    vector[-2] = np.nan  # emissions.high.auto.p_rely_low
    with pytest.raises(ModelError, match=r"emissions\.high\.auto\.p_rely_low"):
        solve_belief_mdp(IOHMMParams.from_vector(vector), p_high=STUDY2, grid=51)
    # An experience rule under which asking in high complexity is a negative experience
    # reaches (high, ask, negative), which the paper could not estimate.
    task = TaskParams(experience_rule=ExperienceRule(ask_high=E.NEGATIVE))
    with pytest.raises(ModelError, match=r"transitions\.high\.ask\.negative\.from_(low|high)"):
        solve_belief_mdp(paper_params(), task, p_high=STUDY2, grid=51)


@pytest.mark.parametrize("kwargs", [{"p_high": 1.5}, {"p_high": 0.5, "grid": 1}, {"p_high": 0.5, "discount": 1.0},
                                    {"p_high": 0.5, "belief_update": "kalman"}, {"p_high": 0.5, "tol": 0.0}])
def test_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        solve_belief_mdp(paper_params(), **kwargs)


# -- properties on random models ------------------------------------------------

def _reference_q(params, task, solution, c):
    """Q(b, c, a) on the grid, (N, 2 A), by one Bellman backup of solution.values with iohmm.update_belief."""
    after = (1 - solution.p_high) * solution.values[:, 0] + solution.p_high * solution.values[:, 1]  # (E', N)
    q = np.zeros((solution.grid, 2))
    for i, b in enumerate(solution.beliefs):
        prior = np.array([1 - b, b])
        for a in A:
            for o in O:
                p_o = float(prior @ params.p_observation(c, a, o))
                q[i, a.code] += p_o * expected_reward_given_action(c, a, o, task)
                p_positive = p_positive_experience(c, a, o, task)
                for e, p_e in ((E.NEGATIVE, 1 - p_positive), (E.POSITIVE, p_positive)):
                    if p_o * p_e > 0:
                        nxt = update_belief(params, b, c, a, o, e, solution.belief_update)
                        q[i, a.code] += solution.discount * p_o * p_e * np.interp(nxt, solution.beliefs, after[e.code])
    return q


probability = st.floats(0.0, 1.0)
interior = st.floats(0.01, 0.99)


@st.composite
def models(draw):
    """Random IOHMMs; the two ask slots the default experience rule never reaches may be NaN."""
    p_high_next = np.array(draw(st.lists(interior, min_size=16, max_size=16))).reshape(2, 2, 2, 2)
    for c, e in ((C.LOW, E.POSITIVE), (C.HIGH, E.NEGATIVE)):
        if draw(st.booleans()):
            p_high_next[c.code, A.ASK.code, e.code] = np.nan
    p_rely = np.array(draw(st.lists(probability, min_size=4, max_size=4))).reshape(2, 2)
    return IOHMMParams(0.5, p_high_next, p_rely)


@settings(max_examples=40, deadline=None)
@given(params=models(), p_high=probability, discount=st.sampled_from([0.0, 0.5, 0.9, 0.99]),
       method=st.sampled_from(["bayes", "paper"]))
def test_solution_properties_on_random_models(params, p_high, discount, method):
    task = TaskParams()
    solution = solve_belief_mdp(params, task, p_high=p_high, grid=41, discount=discount, belief_update=method)
    assert np.isfinite(solution.q).all() and not solution.depends_on_experience
    rewards = [expected_reward_given_action(c, a, o, task) for c in C for a in A for o in O]
    scale = 1.0 / (1.0 - discount)
    assert (solution.values >= min(rewards) * scale - 1e-6).all()
    assert (solution.values <= max(rewards) * scale + 1e-6).all()
    for c in C:
        # The solver's vectorised transitions agree with update_belief, and V is a fixed point to within tol.
        assert np.abs(_reference_q(params, task, solution, c) - solution.q[0, c.code]).max() <= solution.tolerance
        if method == "bayes":  # the exact belief MDP has a convex value function
            assert (np.diff(solution.values[0, c.code], 2) >= -1e-6).all()
        _check_policy_summary(solution, c)
    json.dumps(solution.to_dict())


def _check_policy_summary(solution, c):
    policy = solution.policy[0, c.code]
    if solution.constant_action[c] is not None:
        assert solution.thresholds[c] is None and (policy == solution.constant_action[c].code).all()
    elif solution.thresholds[c] is not None:
        assert solution.threshold_shaped[c]
        assert (policy[solution.beliefs < solution.thresholds[c]] == A.ASK.code).all()
        assert (policy[solution.beliefs > solution.thresholds[c]] == A.AUTO.code).all()
    else:
        assert not solution.threshold_shaped[c] and solution.switches[c]
    assert all(0.0 <= s <= 1.0 for s in solution.switches[c])
