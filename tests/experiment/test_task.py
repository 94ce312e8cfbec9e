import pytest

from experiment.task import Complexity as C
from experiment.task import Experience as E
from experiment.task import HumanAction as O
from experiment.task import Outcome, RewardTable, TaskParams, p_positive_experience, resolve_trial
from experiment.task import RobotAction as A


@pytest.mark.parametrize(("c", "a", "o", "success", "outcome", "experience", "reward"), [
    (C.LOW, A.AUTO, O.RELY, True, Outcome.SUCCESS, E.POSITIVE, 3.0),
    (C.HIGH, A.AUTO, O.RELY, False, Outcome.FAILURE, E.NEGATIVE, -4.0),
    (C.HIGH, A.AUTO, O.INTERVENE, True, Outcome.NONE, E.NEGATIVE, 0.0),
    (C.LOW, A.ASK, O.INTERVENE, True, Outcome.NONE, E.NEGATIVE, 1.0),
    (C.HIGH, A.ASK, O.INTERVENE, False, Outcome.NONE, E.POSITIVE, 1.0),
])
def test_experience_and_reward_follow_the_paper(c, a, o, success, outcome, experience, reward):
    result = resolve_trial(c, a, o, success)
    assert (result.outcome, result.experience, result.reward) == (outcome, experience, reward)


def test_ask_requires_assistance():
    with pytest.raises(ValueError, match="always assists"):
        resolve_trial(C.LOW, A.ASK, O.RELY, True)


def test_reward_table_is_configurable():
    params = TaskParams(rewards=RewardTable(ask=2.0))
    assert resolve_trial(C.LOW, A.ASK, O.INTERVENE, True, params).reward == 2.0


def test_p_positive_experience():
    assert p_positive_experience(C.HIGH, A.AUTO, O.RELY) == 0.75
    assert p_positive_experience(C.HIGH, A.AUTO, O.INTERVENE) == 0.0
    assert p_positive_experience(C.HIGH, A.ASK, O.INTERVENE) == 1.0
    assert p_positive_experience(C.LOW, A.ASK, O.INTERVENE) == 0.0


def test_codes_are_array_indices():
    assert [c.code for c in C] == [0, 1]
    assert A.from_code(1) is A.ASK
