import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from experiment import defaults
from experiment.agnostic import AgnosticPolicy, intervention_rates, trust_agnostic_policy
from experiment.sequences import Sequence
from experiment.task import Complexity as C
from experiment.task import HumanAction as O
from experiment.task import RewardTable, TaskParams
from experiment.task import RobotAction as A

PAPER_RATES = {C.LOW: defaults.PAPER_INTERVENTION_RATE_LOW, C.HIGH: defaults.PAPER_INTERVENTION_RATE_HIGH}


def test_paper_rates_give_never_ask():
    policy = trust_agnostic_policy(PAPER_RATES)
    assert policy.expected_reward_auto[C.LOW] == pytest.approx(2.77326, abs=1e-5)  # paper prints 2.79 (SPEC §11)
    assert policy.expected_reward_auto[C.HIGH] == pytest.approx(1.019, abs=1e-9)  # paper prints 1.02
    assert policy.expected_reward_ask == {C.LOW: 1.0, C.HIGH: 1.0}
    assert policy.action == {C.LOW: A.AUTO, C.HIGH: A.AUTO} and policy.act(C.HIGH) == A.AUTO


def test_paper_low_value_is_the_formula_without_interventions():
    policy = trust_agnostic_policy({C.LOW: 0.0, C.HIGH: 0.0})
    assert policy.expected_reward_auto[C.LOW] == pytest.approx(defaults.PAPER_EXPECTED_REWARD_AUTO_LOW)


def test_high_intervention_rate_flips_to_ask():
    policy = trust_agnostic_policy({C.LOW: 0.006, C.HIGH: 0.3})  # 0.7 * 1.25 = 0.875 < 1
    assert policy.action == {C.LOW: A.AUTO, C.HIGH: A.ASK}


def test_ties_go_to_ask():
    flat = TaskParams(rewards=RewardTable(auto_rely_success=1.0, auto_rely_failure=1.0, auto_intervene=1.0, ask=1.0))
    assert trust_agnostic_policy(PAPER_RATES, flat).action == {C.LOW: A.ASK, C.HIGH: A.ASK}


def test_json_output():
    doc = json.loads(json.dumps(trust_agnostic_policy(PAPER_RATES).to_dict()))
    assert doc["action"] == {"low": "auto", "high": "auto"}
    assert doc["intervention_rate"] == {"low": 0.006, "high": 0.1848}
    assert doc["expected_reward"]["ask"] == {"low": 1.0, "high": 1.0}
    assert doc["expected_reward"]["auto"]["high"] == pytest.approx(1.019)


@pytest.mark.parametrize("rates", [{C.LOW: 0.1, C.HIGH: None}, {C.LOW: 0.1}, {C.LOW: 0.1, C.HIGH: 1.5},
                                   {C.LOW: 0.1, C.HIGH: float("nan")}])
def test_missing_or_bad_rate_is_an_error(rates):
    with pytest.raises(ValueError, match="high complexity"):
        trust_agnostic_policy(rates)


def test_rates_from_sequences():
    #            complexity    robot action  human action  experience
    first = Sequence([0, 0, 0, 1, 1, 1], [0, 0, 1, 0, 0, 1], [1, 0, 1, 1, 1, 1], [0, 1, 0, 0, 0, 1])
    second = Sequence([1, 1, 0], [0, 1, 0], [0, 1, 0], [1, 1, 1])
    rates = intervention_rates([first, second])
    assert rates.auto_trials == {C.LOW: 3, C.HIGH: 3}  # asks are not counted
    assert rates.interventions == {C.LOW: 1, C.HIGH: 2}
    assert rates.rates == {C.LOW: pytest.approx(1 / 3), C.HIGH: pytest.approx(2 / 3)}
    assert json.loads(json.dumps(rates.to_dict()))["high"] == {"rate": 2 / 3, "interventions": 2, "auto_trials": 3}


def test_no_auto_trials_gives_no_rate():
    rates = intervention_rates([Sequence([1, 1], [1, 1], [1, 1], [1, 1])])
    assert rates.rates == {C.LOW: None, C.HIGH: None} and rates.auto_trials == {C.LOW: 0, C.HIGH: 0}
    assert intervention_rates([]).rates == {C.LOW: None, C.HIGH: None}


trials = st.tuples(st.sampled_from(list(C)), st.sampled_from(list(A)), st.sampled_from(list(O))).filter(
    lambda t: not (t[1] == A.ASK and t[2] == O.RELY))


@given(st.lists(st.lists(trials, max_size=20), max_size=5))
def test_rates_match_a_direct_count(participants):
    sequences = [Sequence(*(np.array([[t[0].code, t[1].code, t[2].code, 0] for t in p], dtype=int).reshape(-1, 4).T))
                 for p in participants]
    rates = intervention_rates(sequences)
    every = [t for p in participants for t in p]
    for c in C:
        auto = [t for t in every if t[0] == c and t[1] == A.AUTO]
        assert rates.auto_trials[c] == len(auto)
        assert rates.interventions[c] == sum(t[2] == O.INTERVENE for t in auto)
        assert rates.rates[c] == (rates.interventions[c] / len(auto) if auto else None)


def test_explicit_actions():
    policy = AgnosticPolicy.explicit({C.LOW: A.AUTO, C.HIGH: "ask"})
    assert policy.action == {C.LOW: A.AUTO, C.HIGH: A.ASK}
    assert policy.expected_reward_auto == {C.LOW: None, C.HIGH: None}
    assert json.loads(json.dumps(policy.to_dict()))["action"] == {"low": "auto", "high": "ask"}
    with pytest.raises(ValueError, match="missing high"):
        policy.explicit({C.LOW: A.AUTO})
