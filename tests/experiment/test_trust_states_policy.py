import functools
from math import comb

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiment import defaults
from experiment.belief_mdp import solve_belief_mdp
from experiment.iohmm import ModelError, paper_params
from experiment.task import Complexity as C
from experiment.task import RobotAction as A
from experiment.trust_states import KStateParams, from_iohmm
from experiment.trust_states_policy import (
    ask_share,
    interpolation,
    mean_belief_where,
    simplex_grid,
    solve_k_state_policy,
)

STUDY1 = defaults.STUDY1_TRIALS_HIGH / (defaults.STUDY1_TRIALS_LOW + defaults.STUDY1_TRIALS_HIGH)  # 30/71
STUDY2 = 0.5


@functools.cache
def todays(method, p_high, grid=1001):
    return solve_belief_mdp(paper_params(), p_high=p_high, grid=grid, belief_update=method)


def threshold(beliefs, gain):
    """The single belief where gain = Q(auto) - Q(ask) turns positive, interpolated as belief_mdp does."""
    i = int(np.flatnonzero((gain[1:] > 0) != (gain[:-1] > 0))[0])
    return beliefs[i] + (beliefs[i + 1] - beliefs[i]) * gain[i] / (gain[i] - gain[i + 1])


def duplicated_high(params: KStateParams) -> KStateParams:
    """A 3-state model whose states 1 and 2 are both copies of the 2-state model's state 1 (high trust)."""
    split = np.array([[1.0, 0.0, 0.0], [0.0, 0.5, 0.5]])  # (2, 3): old state -> new states
    transition = params.transition[..., [0, 1, 1], :] @ split  # (2, 2, 2, 3, 3)
    return KStateParams(params.initial @ split, transition, params.p_rely[:, [0, 1, 1]])


@pytest.mark.parametrize("method", ["bayes", "paper"])
@pytest.mark.parametrize("p_high", [STUDY1, STUDY2])
def test_two_states_is_todays_policy(method, p_high):
    old = todays(method, p_high)
    new = solve_k_state_policy(from_iohmm(paper_params()), p_high=p_high, resolution=1000, belief_update=method)
    np.testing.assert_allclose(new.beliefs[:, 1], old.beliefs, atol=1e-15)  # the same grid, in the same order
    assert np.array_equal(new.policy, old.policy[0])  # the same action at every grid point and complexity
    np.testing.assert_allclose(new.q, old.q[0], atol=1e-9)
    assert new.iterations == old.iterations
    gain = new.q[C.HIGH.code, :, A.AUTO.code] - new.q[C.HIGH.code, :, A.ASK.code]
    assert threshold(new.beliefs[:, 1], gain) == pytest.approx(old.thresholds[C.HIGH], abs=1e-9)
    assert ask_share(new)[C.LOW] == 0.0


def test_paper_threshold_at_two_states():
    new = solve_k_state_policy(from_iohmm(paper_params()), p_high=STUDY2, resolution=1000)
    gain = new.q[C.HIGH.code, :, A.AUTO.code] - new.q[C.HIGH.code, :, A.ASK.code]
    assert round(threshold(new.beliefs[:, 1], gain), 4) == 0.6905
    ask = new.beliefs[new.policy[C.HIGH.code] == A.ASK.code, 1]
    assert ask.max() < 0.6905 < new.beliefs[new.policy[C.HIGH.code] == A.AUTO.code, 1].min()
    for b in (0.69, 0.691):
        assert new.action(np.array([1 - b, b]), C.HIGH) == todays("bayes", STUDY2).action(b, C.HIGH)


@pytest.mark.parametrize("method", ["bayes", "paper"])
def test_a_duplicated_state_changes_nothing(method):
    """Three states, two of them the same high trust: the policy is the 2-state policy of P(low) alone."""
    two = from_iohmm(paper_params())
    n = 60
    k2 = solve_k_state_policy(two, p_high=STUDY2, resolution=n, belief_update=method)
    k3 = solve_k_state_policy(duplicated_high(two), p_high=STUDY2, resolution=n, belief_update=method)
    assert len(k3.counts) == comb(n + 2, 2)
    high = k3.counts[:, 1] + k3.counts[:, 2]  # index of the 2-state grid point with the same P(high)
    assert np.array_equal(k3.policy, k2.policy[:, high])
    np.testing.assert_allclose(k3.values, k2.values[:, high], atol=1e-9)
    assert 0.0 < ask_share(k3)[C.HIGH] < 1.0


def three_state_model() -> KStateParams:
    """Low, middle and high trust from the paper's model: the middle state is halfway in every parameter."""
    two = from_iohmm(paper_params())
    up = two.transition[..., 1]  # (2, 2, 2, 2): P(high next | state)
    mid_up = up.mean(axis=-1, keepdims=True)
    rows = np.concatenate([up[..., :1], mid_up, up[..., 1:]], axis=-1)  # (2, 2, 2, 3): P(up) per state
    # from each state: to high w.p. up, to middle w.p. (1 - up) / 2, to low the rest
    transition = np.stack([(1 - rows) / 2, (1 - rows) / 2, rows], axis=-1)
    p_rely = np.stack([two.p_rely[:, 0], two.p_rely.mean(axis=1), two.p_rely[:, 1]], axis=1)
    return KStateParams(np.array([0.3, 0.3, 0.4]), np.nan_to_num(transition, nan=1 / 3), p_rely)


def test_three_states_ask_where_low_trust_is_likely():
    solution = solve_k_state_policy(three_state_model(), p_high=STUDY2, resolution=40)
    share = ask_share(solution)
    assert share[C.LOW] == 0.0 and 0.0 < share[C.HIGH] < 1.0
    ask, auto = mean_belief_where(solution, A.ASK)[C.HIGH], mean_belief_where(solution, A.AUTO)[C.HIGH]
    assert ask is not None and auto is not None
    assert ask[0] > auto[0] and ask[2] < auto[2]
    # monotone: moving belief mass from high to low trust never turns asking into acting
    index = {tuple(x): m for m, x in enumerate(solution.counts)}
    asks = solution.policy[C.HIGH.code] == A.ASK.code
    for m, (x0, x1, x2) in enumerate(solution.counts):
        for lower in ((x0 + 1, x1, x2 - 1), (x0 + 1, x1 - 1, x2), (x0, x1 + 1, x2 - 1)):
            if asks[m] and min(lower) >= 0:
                assert asks[index[lower]]


@settings(max_examples=50, deadline=None)
@given(k=st.integers(2, 4), n=st.integers(1, 12), seed=st.integers(0, 2**32 - 1))
def test_interpolation_is_barycentric_on_the_grid(k, n, seed):
    rng = np.random.default_rng(seed)
    counts = simplex_grid(k, n)
    assert len(counts) == comb(n + k - 1, k - 1) and (counts.sum(axis=1) == n).all() and (counts >= 0).all()
    assert len(np.unique(counts, axis=0)) == len(counts)
    beliefs = np.concatenate([rng.dirichlet(np.full(k, 0.5), 20), counts / n, np.eye(k)])
    index, weights = interpolation(counts, n, beliefs)
    assert (weights >= -1e-12).all()
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("bk,bkj->bj", weights, counts[index] / n), beliefs, atol=1e-12)


def test_missing_transition_that_is_reached_is_a_model_error():
    model = three_state_model()
    transition = model.transition.copy()
    transition[C.HIGH.code, A.AUTO.code, 0, 1] = np.nan  # negative experience after auto, from the middle state
    with pytest.raises(ModelError):
        solve_k_state_policy(KStateParams(model.initial, transition, model.p_rely), p_high=STUDY2, resolution=10)


@pytest.mark.parametrize("kwargs", [{"p_high": 1.5}, {"p_high": 0.5, "resolution": 0},
                                    {"p_high": 0.5, "discount": 1.0}, {"p_high": 0.5, "belief_update": "x"},
                                    {"p_high": 0.5, "tol": 0.0}])
def test_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        solve_k_state_policy(three_state_model(), **kwargs)


def test_action_at_grid_points_is_the_policy():
    solution = solve_k_state_policy(three_state_model(), p_high=STUDY1, resolution=12)
    for c in C:
        for m in range(0, len(solution.counts), 7):
            assert solution.action(solution.beliefs[m], c).code == solution.policy[c.code, m]
    with pytest.raises(ValueError):
        solution.action(np.array([0.5, 0.5]), C.HIGH)


def test_four_states_solve():
    model = three_state_model()
    four = KStateParams(np.full(4, 0.25), np.full((2, 2, 2, 4, 4), 0.25),
                        np.concatenate([model.p_rely, model.p_rely[:, 2:]], axis=1))
    solution = solve_k_state_policy(four, p_high=STUDY2, resolution=10)
    assert solution.policy.shape == (2, comb(13, 3))
    assert ask_share(solution)[C.LOW] == 0.0
