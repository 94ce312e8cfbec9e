"""Self-reported trust as a second observation (issue 40): the beta-binomial rating emission, its place in the
K-state EM, the data, and what it adds to the held-out reliance."""

import itertools
import math

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.stats import betabinom

from experiment.records import DataError
from experiment.trust_ratings import (
    NO_RATING,
    RatingEmission,
    Ratings,
    beta_binomial_update,
    rating_scale_of,
    ratings_at_shelf_ends,
    sample_ratings,
)
from experiment.trust_states import illustrative_three_state_model, sample_sequences_k
from experiment.trust_states_em import EMSettings, Layout, PaddedData, e_step, fit_k_states, m_step, start_vectors
from tests.experiment.test_trust_states import path_weight, random_params, random_sequence


def test_the_emission_is_scipys_beta_binomial():
    emission = RatingEmission(np.array([0.7, 3.0, 9.0]), np.array([2.0, 3.0, 1.5]))
    expected = np.stack([betabinom.pmf(np.arange(11), 10, a, b) for a, b in zip(emission.alpha, emission.beta,
                                                                                 strict=True)], axis=1)
    np.testing.assert_allclose(emission.pmf(), expected, rtol=1e-12)
    np.testing.assert_allclose(emission.mean_rating(), 10 * emission.alpha / (emission.alpha + emission.beta))


@pytest.mark.parametrize("k", [2, 3])
def test_the_likelihood_with_ratings_equals_brute_force_enumeration(k):
    rng = np.random.default_rng(10 + k)
    emission = RatingEmission(rng.uniform(0.5, 8.0, k), rng.uniform(0.5, 8.0, k))
    pmf = emission.pmf()
    for length in (1, 3, 5):
        params, seq = random_params(k, rng), random_sequence(length, rng)
        levels = np.where(rng.random(length) < 0.5, rng.integers(0, 11, length), NO_RATING)
        brute = 0.0
        for path in itertools.product(range(k), repeat=length + 1):
            weight = path_weight(params, seq, path)
            for t in range(length):
                weight *= pmf[levels[t], path[t]] if levels[t] >= 0 else 1.0
            brute += weight
        layout = Layout(k, (0, 10))
        data = PaddedData([seq], Ratings((levels,)))
        assert e_step(layout, layout.pack(params, emission)[None], data).loglik[0] == pytest.approx(
            math.log(brute), abs=1e-12)


def test_the_rating_update_reaches_the_weighted_maximum():
    rng = np.random.default_rng(3)
    counts = rng.gamma(1.0, 3.0, size=(4, 11, 2))  # (restarts, levels, states): expected counts are fractional
    alpha, beta = np.full((4, 2), 2.0), np.full((4, 2), 2.0)
    for _ in range(20):
        alpha, beta = beta_binomial_update(counts, alpha, beta, 10)
    for r, j in itertools.product(range(4), range(2)):
        def minus(log_ab, n=counts[r, :, j]):
            return -(n * betabinom.logpmf(np.arange(11), 10, *np.exp(log_ab))).sum()
        best = minimize(minus, np.log([alpha[r, j], beta[r, j]]) + 0.3, method="Nelder-Mead",
                        options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 4000})
        assert -minus(np.log([alpha[r, j], beta[r, j]])) >= -best.fun - 1e-8


def test_an_em_step_with_ratings_never_lowers_the_likelihood():
    rng = np.random.default_rng(5)
    model = illustrative_three_state_model()
    sequences, states = sample_sequences_k(model, 40, 30, rng)
    ratings = sample_ratings(RatingEmission(np.array([2.0, 5.0, 8.0]), np.array([8.0, 5.0, 2.0])), states, 10, rng)
    data = PaddedData(sequences, ratings)
    layout = Layout(3, (0, 10))
    theta = start_vectors(layout, 6, rng)
    previous = e_step(layout, theta, data)
    for _ in range(15):
        theta = m_step(layout, theta, previous)
        stats = e_step(layout, theta, data)
        assert (stats.loglik >= previous.loglik - 1e-9).all()
        previous = stats


@pytest.fixture(scope="module")
def rated_study():
    """300 participants of the illustrative three-state model, a rating every 10 trials that tells the states
    apart (means 2, 5 and 8 of 10)."""
    rng = np.random.default_rng(11)
    truth = RatingEmission(np.array([4.0, 10.0, 16.0]), np.array([16.0, 10.0, 4.0]))
    sequences, states = sample_sequences_k(illustrative_three_state_model(), 300, 40, rng)
    return sequences, sample_ratings(truth, states, 10, rng), truth


def test_em_with_ratings_recovers_the_rating_emission(rated_study):
    sequences, ratings, truth = rated_study
    fit = fit_k_states(PaddedData(sequences, ratings), 3, seed=0, settings=EMSettings(restarts=6, keep=2))
    assert fit.ratings is not None and fit.n_ratings == ratings.count == 1200
    np.testing.assert_allclose(fit.ratings.mean_rating(), truth.mean_rating(), atol=0.35)
    np.testing.assert_allclose(fit.params.p_rely, illustrative_three_state_model().p_rely, atol=0.08)
    assert fit.n_free == fit_k_states(PaddedData(sequences), 3, settings=EMSettings(restarts=1, max_iter=1)).n_free \
        + 6


def test_ratings_sit_at_the_last_scored_trial_of_their_shelf():
    shelves = {"p1": [(1, 1), (1, 1), (1, 2), (2, 1), (2, 1)], "p2": [(1, 1)]}
    answers = [
        {"participant_id": "p1", "context": "shelf:1:1", "item": "trust", "value": "7"},
        {"participant_id": "p1", "context": "shelf:1:1", "item": "reliance", "value": "3"},  # another item
        {"participant_id": "p1", "context": "shelf:2:1", "item": "trust", "value": "10"},
        {"participant_id": "p1", "context": "end", "item": "trust", "value": "1"},  # not a shelf
        {"participant_id": "p1", "context": "shelf:3:1", "item": "trust", "value": "4"},  # no scored trials there
        {"participant_id": "gone", "context": "shelf:1:1", "item": "trust", "value": "4"},  # excluded participant
    ]
    ratings = ratings_at_shelf_ends(["p1", "p2"], shelves, answers)
    np.testing.assert_array_equal(ratings.levels_by_participant[0], [-1, 7, -1, -1, 10])
    np.testing.assert_array_equal(ratings.levels_by_participant[1], [-1])
    assert ratings.count == 2


@pytest.mark.parametrize("value", ["11", "-1", "6.5", "", "x"])
def test_a_rating_off_the_scale_is_refused_with_its_line(value):
    with pytest.raises(DataError, match=r"surveys.csv:2: "):
        ratings_at_shelf_ends(["p1"], {"p1": [(1, 1)]}, [
            {"participant_id": "p1", "context": "shelf:1:1", "item": "trust", "value": value}], where="surveys.csv")


def test_the_rating_sd_is_the_beta_binomials():
    emission = RatingEmission(np.array([0.7, 3.0, 5000.0]), np.array([2.0, 3.0, 5000.0]))
    expected = [betabinom.std(10, a, b) for a, b in zip(emission.alpha, emission.beta, strict=True)]
    np.testing.assert_allclose(emission.sd_rating(), expected, rtol=1e-12)


def test_the_rating_scale_is_the_shelf_questionnaires():
    from experiment.templates import template

    config = template("model-estimation")
    assert rating_scale_of(config) == (0, 10)
    assert rating_scale_of(config.model_copy(update={"shelf_questionnaire": None})) is None
