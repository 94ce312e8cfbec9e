import itertools
import math

import numpy as np
import pytest

from experiment.fit import fit_iohmm, log_likelihood
from experiment.iohmm import IOHMMParams, ModelError, filter_beliefs, paper_params
from experiment.sequences import Sequence, sample_random_assist_sequences
from experiment.trust_states import (
    KStateParams,
    filter_beliefs_k,
    from_iohmm,
    log_likelihood_k,
    order_states,
    sample_sequences_k,
    sequence_log_likelihood,
    to_iohmm,
)
from experiment.trust_states_em import (
    EMSettings,
    Layout,
    PaddedData,
    batch_log_likelihood,
    e_step,
    fit_k_states,
    gradient,
    m_step,
    start_vectors,
)


def random_params(k: int, rng: np.random.Generator) -> KStateParams:
    """Interior probabilities (no brute-force underflow, no ruled-out observations)."""
    return KStateParams(rng.dirichlet(np.ones(k)), rng.dirichlet(np.ones(k) * 2, size=(2, 2, 2, k)),
                        rng.uniform(0.05, 0.95, size=(2, k)))


def random_sequence(length: int, rng: np.random.Generator) -> Sequence:
    rows = rng.integers(0, 2, size=(4, length))
    rows[2] = np.where(rows[1] == 1, 1, rows[2])  # asked -> intervene
    return Sequence(*rows)


def path_weight(params: KStateParams, seq: Sequence, path: tuple[int, ...]) -> float:
    """P(o_1..t, T_1..T_{t+1} = path) for a path of t + 1 states, straight from the model definition."""
    weight = params.initial[path[0]]
    for t, state in enumerate(path[:-1]):
        c, a, o, e = (int(x[t]) for x in (seq.complexity, seq.robot_action, seq.human_action, seq.experience))
        rely = params.p_rely[c, state]
        weight *= 1.0 if a == 1 else (rely if o == 0 else 1.0 - rely)
        weight *= params.transition[c, a, e, state, path[t + 1]]
    return float(weight)


def brute_force(params: KStateParams, seq: Sequence) -> tuple[float, np.ndarray]:
    """Log-likelihood and (T + 1, K) filtered beliefs by summing over all trust paths."""
    k, n = params.n_states, len(seq)
    beliefs = []
    for t in range(n + 1):
        belief = np.zeros(k)
        for path in itertools.product(range(k), repeat=t + 1):
            belief[path[-1]] += path_weight(params, seq, path)
        beliefs.append(belief / belief.sum())
    # the likelihood sums the paths of T + 1 states: the last transition's row sums to 1
    likelihood = sum(path_weight(params, seq, path) for path in itertools.product(range(k), repeat=n + 1))
    return math.log(likelihood), np.array(beliefs)


@pytest.mark.parametrize("k", [2, 3])
def test_filter_and_likelihood_equal_brute_force_enumeration(k):
    rng = np.random.default_rng(k)
    for length in (1, 3, 6):
        for _ in range(3):
            params, seq = random_params(k, rng), random_sequence(length, rng)
            loglik, beliefs = brute_force(params, seq)
            assert sequence_log_likelihood(params, seq) == pytest.approx(loglik, abs=1e-12)
            np.testing.assert_allclose(filter_beliefs_k(params, seq), beliefs, atol=1e-12)


@pytest.fixture(scope="module")
def paper_data():
    sequences, _ = sample_random_assist_sequences(paper_params(), 40, 40, np.random.default_rng(11))
    return sequences


def test_two_states_are_todays_model(paper_data):
    paper = paper_params()
    params = from_iohmm(paper)
    assert log_likelihood_k(params, paper_data) == pytest.approx(log_likelihood(paper, paper_data), abs=1e-9)
    assert batch_log_likelihood(params, PaddedData(paper_data)) == pytest.approx(log_likelihood(paper, paper_data),
                                                                                abs=1e-9)
    for seq in paper_data:
        np.testing.assert_allclose(filter_beliefs_k(params, seq)[:, 1], filter_beliefs(paper, seq.trials()),
                                   atol=1e-9, rtol=0)
    np.testing.assert_array_equal(to_iohmm(params).to_vector(), paper.to_vector())  # NaN slots kept
    assert order_states(params).p_rely.tolist() == params.p_rely.tolist()  # low trust relies less


def test_two_states_equal_todays_model_on_other_parameters(paper_data):
    vector = np.random.default_rng(5).uniform(0.05, 0.95, size=paper_params().to_vector().shape)
    other = IOHMMParams.from_vector(vector)
    assert log_likelihood_k(from_iohmm(other), paper_data) == pytest.approx(log_likelihood(other, paper_data),
                                                                             abs=1e-9)
    np.testing.assert_allclose(filter_beliefs_k(from_iohmm(other), paper_data[0])[:, 1],
                               filter_beliefs(other, paper_data[0].trials()), atol=1e-9, rtol=0)


def test_only_two_states_have_the_papers_form():
    with pytest.raises(ModelError, match="2-state"):
        to_iohmm(random_params(3, np.random.default_rng(0)))
    with pytest.raises(ModelError, match="number of trust states"):
        KStateParams(np.ones(5) / 5, np.full((2, 2, 2, 5, 5), 0.2), np.full((2, 5), 0.5))


def test_state_order_is_stable_under_relabelling():
    params = order_states(random_params(3, np.random.default_rng(2)))
    assert (np.diff(params.p_rely[1]) > 0).all()
    seq = random_sequence(6, np.random.default_rng(3))
    for perm in itertools.permutations(range(3)):
        relabelled = params.permuted(np.array(perm))
        assert sequence_log_likelihood(relabelled, seq) == pytest.approx(sequence_log_likelihood(params, seq))
        ordered = order_states(relabelled)
        for name in ("initial", "transition", "p_rely"):
            np.testing.assert_array_equal(getattr(ordered, name), getattr(params, name))


def three_state_model() -> KStateParams:
    """Well separated in P(rely | high complexity); persistent, up after positive experience, down after negative."""
    transition = np.zeros((2, 2, 2, 3, 3))
    for e, i in itertools.product(range(2), range(3)):
        row = np.full(3, 0.05)
        row[i] += 0.65
        row[min(i + 1, 2) if e else max(i - 1, 0)] += 0.2
        transition[:, :, e, i] = row / row.sum()
    return KStateParams(np.array([0.2, 0.3, 0.5]), transition, np.array([[0.6, 0.95, 0.99], [0.05, 0.5, 0.95]]))


def test_em_recovers_a_three_state_models_likelihood():
    truth = three_state_model()
    train, _ = sample_sequences_k(truth, 60, 40, np.random.default_rng(3))
    held_out, _ = sample_sequences_k(truth, 100, 40, np.random.default_rng(4))
    fit = fit_k_states(train, 3, seed=0, settings=EMSettings(restarts=3, max_iter=300, tol=1e-6))
    gain = fit.loglik - log_likelihood_k(truth, train)
    # the maximum is at least the truth's; twice the excess is asymptotically chi² with n_free degrees of freedom
    assert 0.0 <= gain <= fit.n_free
    assert fit.loglik == pytest.approx(log_likelihood_k(fit.params, train), abs=1e-9)
    assert fit.loglik == fit.restart_logliks.max()
    n_held_out = sum(len(s) for s in held_out)
    assert (log_likelihood_k(fit.params, held_out) - log_likelihood_k(truth, held_out)) / n_held_out > -0.02
    assert (np.diff(fit.params.p_rely[1]) >= 0).all()  # ordered


def test_two_state_em_reaches_todays_fit(paper_data):
    fit = fit_k_states(paper_data, 2, seed=0, settings=EMSettings(restarts=3))
    best = fit_iohmm(paper_data, restarts=10, seed=0).loglik  # EM + polish: the maximum
    assert best - 0.01 <= fit.loglik <= best + 1e-6  # EM without the polish stops a little short of the maximum
    assert fit.converged and fit.loglik == pytest.approx(log_likelihood_k(fit.params, paper_data), abs=1e-9)


def test_em_never_decreases_the_likelihood(paper_data):
    data, layout = PaddedData(paper_data), Layout(3)
    theta = start_vectors(layout, 4, np.random.default_rng(1))
    trace = []
    for _ in range(30):
        stats = e_step(layout, theta, data)
        trace.append(stats.loglik)
        theta = m_step(layout, theta, stats)
    assert np.isfinite(trace).all() and (np.diff(trace, axis=0) >= -1e-9).all()


@pytest.mark.parametrize("k", [2, 3, 4])
def test_the_gradient_is_the_likelihoods_derivative(k):
    """Fisher's identity (expected count / θ) against central differences, every entry a free variable."""
    rng = np.random.default_rng(k)
    data, layout = PaddedData([random_sequence(8, rng) for _ in range(5)]), Layout(k)
    theta = start_vectors(layout, 3, rng)[1:2]  # a random interior point
    grad = gradient(layout, theta, e_step(layout, theta, data))[0]
    eps = 1e-6
    for j in range(layout.size):
        step = np.zeros_like(theta)
        step[0, j] = eps
        ahead, back = (e_step(layout, theta + d, data).loglik[0] for d in (step, -step))
        assert grad[j] == pytest.approx((ahead - back) / (2 * eps), rel=1e-5, abs=1e-6)


@pytest.mark.parametrize("k", [2, 3])
def test_the_path_entropy_equals_brute_force_enumeration(k):
    """ICL's penalty: the entropy of the posterior over trust paths, summed over sequences."""
    rng = np.random.default_rng(10 + k)
    params, seqs = random_params(k, rng), [random_sequence(length, rng) for length in (1, 4, 5)]
    expected = 0.0
    for seq in seqs:  # P(path of len(seq) states | o): the transition after the last trial sums out
        weights = np.array([sum(path_weight(params, seq, path + (last,)) for last in range(k))
                            for path in itertools.product(range(k), repeat=len(seq))])
        posterior = weights / weights.sum()
        expected -= float((posterior * np.log(posterior)).sum())
    layout = Layout(k)
    stats = e_step(layout, layout.pack(params)[None], PaddedData(seqs), entropy=True)
    assert stats.entropy[0] == pytest.approx(expected, abs=1e-10)
    assert stats.loglik[0] == pytest.approx(log_likelihood_k(params, seqs), abs=1e-12)


def test_an_input_the_model_has_no_estimate_for_is_an_error():
    seq = Sequence([0], [1], [1], [1])  # asked in low complexity, positive: cannot occur (paper §4.2), NaN row
    with pytest.raises(ModelError, match="no transition estimate"):
        filter_beliefs_k(from_iohmm(paper_params()), seq)
    with pytest.raises(ModelError, match="no transition estimate"):
        filter_beliefs(paper_params(), seq.trials())
    two_trials = Sequence([0, 0], [1, 0], [1, 0], [1, 1])
    with pytest.raises(ModelError, match="no transition estimate"):
        batch_log_likelihood(from_iohmm(paper_params()), PaddedData([two_trials]))
    with pytest.raises(ModelError, match="no transition estimate"):
        log_likelihood_k(from_iohmm(paper_params()), [two_trials])
