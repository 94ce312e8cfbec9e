"""Laplace standard errors of the K-state trust IOHMM (experiment.trust_states_uncertainty)."""

import itertools

import numpy as np
import pytest

from experiment.fit import fit_iohmm
from experiment.iohmm import ModelError, paper_params
from experiment.sequences import sample_random_assist_sequences
from experiment.trust_states import KStateParams, from_iohmm, log_likelihood_k, sample_sequences_k
from experiment.trust_states_em import EMSettings, PaddedData, fit_k_states
from experiment.trust_states_uncertainty import k_state_uncertainty
from tests.experiment.test_trust_states import three_state_model

STATUSES = {"estimated", "boundary", "unidentified", "not_exercised"}


def _rows(part: np.ndarray, k: int) -> np.ndarray:
    return part.reshape(-1, k)


def _duplicated(params: KStateParams, state: int) -> KStateParams:
    """A K + 1 state model in which the new last state is a copy of ``state``: the same likelihood."""
    k = params.n_states
    initial = np.append(params.initial, params.initial[state] / 2)
    initial[state] /= 2
    transition = np.zeros((2, 2, 2, k + 1, k + 1))
    transition[..., :k, :k] = params.transition
    transition[..., k] = transition[..., state] / 2
    transition[..., state] /= 2
    transition[..., k, :] = transition[..., state, :]
    return KStateParams(initial, transition, np.concatenate([params.p_rely, params.p_rely[:, [state]]], axis=1))


def test_two_states_reproduce_the_two_state_fits_standard_errors():
    sequences, _ = sample_random_assist_sequences(paper_params(), 60, 40, np.random.default_rng(1))
    fit = fit_iohmm(sequences, restarts=3, seed=0)
    result = k_state_uncertainty(from_iohmm(fit.params), PaddedData(sequences))
    se, status = result.stderr, result.status
    # the two-state vector: initial.p_high, p_high_next (C, A, E, T), p_rely (C, T)
    mine = np.concatenate([[se.initial[1]], se.transition[..., 1].ravel(), se.p_rely.ravel()])
    mine_status = np.concatenate([[status.initial[1]], status.transition[..., 1].ravel(), status.p_rely.ravel()])
    assert mine_status.tolist() == fit.status
    assert {"estimated", "boundary", "not_exercised"} <= set(fit.status)  # the comparison covers each case
    estimated = np.array(fit.status) == "estimated"
    assert np.isnan(mine[~estimated]).all()
    np.testing.assert_allclose(mine[estimated], fit.stderr[estimated], rtol=1e-7)
    # a row [P(low), P(high)] has one free coordinate: both entries share its standard error and status
    np.testing.assert_array_equal(se.transition[..., 0], se.transition[..., 1])
    np.testing.assert_array_equal(status.transition[..., 0], status.transition[..., 1])
    assert se.initial[0] == se.initial[1] and status.initial[0] == status.initial[1]


def test_three_states_statuses_and_standard_errors():
    sequences, _ = sample_sequences_k(three_state_model(), 60, 40, np.random.default_rng(3))
    data = PaddedData(sequences)
    fit = fit_k_states(data, 3, seed=0, settings=EMSettings(restarts=3, max_iter=300, tol=1e-6))
    result = k_state_uncertainty(fit.params, data)
    params, se, status = fit.params, result.stderr, result.status
    for part in ("initial", "transition", "p_rely"):
        assert getattr(se, part).shape == getattr(params, part).shape == getattr(status, part).shape
        assert set(np.unique(getattr(status, part))) <= STATUSES
        estimated = getattr(status, part) == "estimated"
        assert np.isfinite(getattr(se, part)[estimated]).all() and (getattr(se, part)[estimated] > 0).all()
        assert np.isnan(getattr(se, part)[~estimated]).all()
    interior = (params.p_rely > 1e-6) & (params.p_rely < 1 - 1e-6)
    assert interior.sum() >= 4 and (status.p_rely[interior] == "estimated").all()
    assert (status.p_rely[~interior] == "boundary").all()
    assert (status.transition[np.isnan(params.transition)] == "not_exercised").all()
    assert np.isnan(params.transition).any()
    zero = params.transition == 0.0
    assert zero.any() and (status.transition[zero] == "boundary").all()
    # the dependent entry of a row (its largest interior one) has the SE of minus the sum of the others
    rows_se, rows_status = _rows(se.transition, 3), _rows(status.transition, 3)
    two_free = [i for i, row in enumerate(rows_status) if (row == "estimated").sum() == 2 and "boundary" in row]
    assert two_free
    for i in two_free:
        a, b = rows_se[i][rows_status[i] == "estimated"]
        assert a == pytest.approx(b, rel=1e-12)  # one free coordinate, moving against the other


def test_a_duplicated_state_is_unidentified_not_a_huge_standard_error():
    sequences, _ = sample_random_assist_sequences(paper_params(), 60, 40, np.random.default_rng(0))
    data = PaddedData(sequences)
    three = k_state_uncertainty(_duplicated(from_iohmm(paper_params()), 1), data)
    status, se = three.status, three.stderr
    # moving mass between the copies (columns 1 and 2 of any row) changes nothing: one of them is unidentified
    rows = np.concatenate([status.initial[None], _rows(status.transition, 3)])
    copies = rows[:, 1:]
    interior = (copies != "boundary").all(axis=1) & (copies != "not_exercised").all(axis=1)
    assert interior.sum() >= 8
    assert (copies[interior] == "unidentified").any(axis=1).all()
    # and no part of the model gets a huge, negative or non-finite standard error instead
    for part_se, part_status in zip(se, status, strict=True):
        estimated = part_status == "estimated"
        assert np.isfinite(part_se[estimated]).all() and (part_se[estimated] > 0).all()
        assert (part_se[estimated] < 1.0).all()
        assert np.isnan(part_se[~estimated]).all()


def test_a_missing_transition_estimate_for_an_input_in_the_data_is_an_error():
    sequences, _ = sample_random_assist_sequences(paper_params(), 10, 20, np.random.default_rng(0))
    data = PaddedData(sequences)
    model = from_iohmm(paper_params())
    transition = model.transition.copy().reshape(8, 2, 2)
    transition[int(np.flatnonzero(data.inputs_used)[0])] = np.nan
    with pytest.raises(ModelError, match="no transition estimate"):
        k_state_uncertainty(KStateParams(model.initial, transition.reshape(2, 2, 2, 2, 2), model.p_rely), data)


def test_every_entry_has_a_status_at_four_states():
    sequences, _ = sample_sequences_k(three_state_model(), 30, 30, np.random.default_rng(5))
    data = PaddedData(sequences)
    model = _duplicated(three_state_model(), 2)
    result = k_state_uncertainty(model, data)
    assert result.status.transition.shape == (2, 2, 2, 4, 4)
    for c, a, e in itertools.product(range(2), repeat=3):
        if not data.inputs_used[(c * 2 + a) * 2 + e]:
            assert (result.status.transition[c, a, e] == "not_exercised").all()
    assert "unidentified" in result.status.transition


def test_the_dependent_entry_gets_the_delta_method_standard_error():
    # states told apart by the emissions alone and never left: the initial distribution is a multinomial sample,
    # whose maximum-likelihood proportions have the standard errors sqrt(θ(1 − θ)/N), the dependent one included
    p_rely = np.array([[0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    stay = np.broadcast_to(np.eye(3), (2, 2, 2, 3, 3))
    truth = KStateParams(np.array([0.2, 0.3, 0.5]), stay, p_rely)
    sequences, states = sample_sequences_k(truth, 80, 30, np.random.default_rng(2))
    counts = np.bincount([path[0] for path in states], minlength=3)
    mle = KStateParams(counts / counts.sum(), stay, p_rely)
    data = PaddedData(sequences)
    assert log_likelihood_k(mle, sequences) == pytest.approx(float(counts @ np.log(mle.initial)), abs=1e-9)
    result = k_state_uncertainty(mle, data)
    assert (result.status.initial == "estimated").all()
    np.testing.assert_allclose(result.stderr.initial, np.sqrt(mle.initial * (1 - mle.initial) / counts.sum()),
                               rtol=1e-6)
    assert (result.status.p_rely == "boundary").all()
    assert "estimated" not in result.status.transition  # rows at 0 and 1, or without any expected use
