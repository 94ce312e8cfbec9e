"""EM for the K-state trust IOHMM (issue 40): scaled forward–backward over padded sequences, seeded restarts.

A straightforward numpy implementation (clarity over speed): the time loop runs in Python over (N, K) rows of all
N sequences at once; restarts run one after another. Shapes: N sequences padded to T trials, K states. Padding and
the step after a sequence's last trial use probability-1 emissions and the identity transition, so they change
nothing. The fast K = 2 fit (``experiment.fit``) stays the production path; ``trust_states`` describes the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from experiment.iohmm import ModelError
from experiment.sequences import Sequence
from experiment.trust_states import MAX_STATES, MIN_STATES, N_INPUTS, KStateParams, order_states


@dataclass(frozen=True)
class EMSettings:
    """Numbers of the method (move to ``experiment.defaults`` with model selection)."""

    restarts: int = 10  # EM finds local maxima; the K = 2 fit uses 20, fewer here as each K ≥ 3 restart is slower
    max_iter: int = 1000  # cap per restart: EM is slow near flat optima; a capped restart is reported, not hidden
    tol: float = 1e-7  # converged: log-likelihood gain per iteration ≤ tol × number of trials (scale-free stop)
    start_spread: float = 0.8  # restart 0: P(rely | state) spread evenly over [0.1, 0.9] (the data's range)
    start_stay: float = 0.8  # restart 0: P(stay in the same state), trust is persistent (paper §4.2)


@dataclass(frozen=True)
class KStateFit:
    params: KStateParams  # ordered by ``order_states``
    loglik: float
    restart_logliks: np.ndarray = field(repr=False)  # (R,) final log-likelihood of each restart
    iterations: np.ndarray = field(repr=False)  # (R,) EM iterations of each restart
    converged: np.ndarray = field(repr=False)  # (R,) bool: stopped by ``tol``, not by ``max_iter``
    n_trials: int = 0
    n_free: int = 0  # free parameters the data can inform (BIC's count)


class PaddedData:
    """Sequences as (N, T) code arrays; ``valid`` marks real trials, ``trans`` the input code (N_INPUTS: none)."""

    def __init__(self, sequences: list[Sequence]) -> None:
        seqs = [s for s in sequences if len(s)]
        if not seqs:
            raise ValueError("no trials to fit")
        n, t = len(seqs), max(len(s) for s in seqs)
        self.lengths = np.array([len(s) for s in seqs])
        self.valid = np.arange(t)[None, :] < self.lengths[:, None]  # (N, T)
        codes = np.zeros((4, n, t), dtype=int)
        for i, s in enumerate(seqs):
            codes[:, i, :len(s)] = (s.complexity, s.robot_action, s.human_action, s.experience)
        self.complexity, self.robot_action, self.human_action, experience = codes
        has_next = np.arange(t)[None, :] < self.lengths[:, None] - 1
        self.trans = np.where(has_next, (self.complexity * 2 + self.robot_action) * 2 + experience, N_INPUTS)
        self.auto = self.valid & (self.robot_action == 0)
        self.n_trials = int(self.lengths.sum())
        self.inputs_used = np.bincount(self.trans.ravel(), minlength=N_INPUTS + 1)[:N_INPUTS] > 0  # (8,)
        self.complexities_used = np.array([self.auto[self.complexity == c].any() for c in (0, 1)])  # (2,)


def _tables(params: KStateParams, data: PaddedData) -> tuple[np.ndarray, np.ndarray]:
    """(N, T, K) emission probabilities and (N, T, K, K) transitions; NaN rows of unused inputs become uniform."""
    k = params.n_states
    if np.isnan(params.transition.reshape(N_INPUTS, k, k))[data.inputs_used].any():
        raise ModelError("the model has no transition estimate for an input combination in the data")
    rely = params.p_rely[data.complexity]  # (N, T, K)
    emit = np.where((data.human_action == 0)[..., None], rely, 1.0 - rely)
    emit = np.where(data.auto[..., None], emit, 1.0)
    table = np.concatenate([params.transition.reshape(N_INPUTS, k, k), np.eye(k)[None]])
    table = np.where(np.isnan(table).any(axis=-1, keepdims=True), 1.0 / k, table)
    return emit, table[data.trans]


def _forward(initial: np.ndarray, emit: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scaled forward pass: (N, T, K) filtered P(T_t | o_1..t) and (N, T) scales P(o_t | o_1..t−1)."""
    n, t, k = emit.shape
    alpha, scale = np.zeros((n, t, k)), np.zeros((n, t))
    predicted = np.broadcast_to(initial, (n, k))
    for step in range(t):
        joint = predicted * emit[:, step]
        scale[:, step] = joint.sum(axis=1)
        alpha[:, step] = joint / np.maximum(scale[:, step], np.finfo(float).tiny)[:, None]
        predicted = np.einsum("ni,nij->nj", alpha[:, step], trans[:, step])
    return alpha, scale


def _backward(emit: np.ndarray, trans: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(N, T, K) scaled backward variables: P(o_t+1..T | T_t) / P(o_t+1..T | o_1..t)."""
    n, t, k = emit.shape
    beta = np.ones((n, t, k))
    for step in range(t - 2, -1, -1):
        ahead = emit[:, step + 1] * beta[:, step + 1] / np.maximum(scale[:, step + 1], np.finfo(float).tiny)[:, None]
        beta[:, step] = np.einsum("nij,nj->ni", trans[:, step], ahead)
    return beta


def batch_log_likelihood(params: KStateParams, data: PaddedData) -> float:
    """Total log-likelihood of the padded sequences (−inf if the model rules an observation out)."""
    emit, trans = _tables(params, data)
    _, scale = _forward(params.initial, emit, trans)
    return float(np.log(scale).sum()) if (scale > 0).all() else -math.inf


def _em_step(params: KStateParams, data: PaddedData) -> tuple[KStateParams, float]:
    """One EM iteration: the new parameters and the log-likelihood of the old ones."""
    k = params.n_states
    emit, trans = _tables(params, data)
    alpha, scale = _forward(params.initial, emit, trans)
    beta = _backward(emit, trans, scale)
    gamma = alpha * beta  # (N, T, K) P(T_t | all o); padding rows are the last real trial's, masked below
    ahead = emit[:, 1:] * beta[:, 1:] / np.maximum(scale[:, 1:], np.finfo(float).tiny)[..., None]
    xi = alpha[:, :-1, :, None] * trans[:, :-1] * ahead[:, :, None, :]  # (N, T−1, K, K)
    counts = np.zeros((N_INPUTS + 1, k, k))
    np.add.at(counts, data.trans[:, :-1], xi)
    rely, total = np.zeros((2, k)), np.zeros((2, k))
    np.add.at(rely, data.complexity[data.auto & (data.human_action == 0)], gamma[data.auto & (data.human_action == 0)])
    np.add.at(total, data.complexity[data.auto], gamma[data.auto])
    rows = counts[:N_INPUTS].sum(axis=-1, keepdims=True)
    old = params.transition.reshape(N_INPUTS, k, k)
    transition = np.where(rows > 0, counts[:N_INPUTS] / np.maximum(rows, np.finfo(float).tiny), old)
    transition[~data.inputs_used] = np.nan
    p_rely = np.where(total > 0, rely / np.maximum(total, np.finfo(float).tiny), params.p_rely)
    initial = gamma[:, 0].sum(axis=0) / gamma[:, 0].sum()
    loglik = float(np.log(scale).sum()) if (scale > 0).all() else -math.inf
    return KStateParams(initial, transition.reshape(2, 2, 2, k, k), np.clip(p_rely, 0.0, 1.0)), loglik


def start_params(k: int, restart: int, rng: np.random.Generator, settings: EMSettings = EMSettings()) -> KStateParams:
    """Restart 0: evenly spread, persistent states; others: uniform Dirichlet rows and uniform P(rely)."""
    if restart == 0:
        spread = 0.5 + settings.start_spread * (np.arange(k) / (k - 1) - 0.5)
        stay = np.full((k, k), (1.0 - settings.start_stay) / (k - 1)) + np.eye(k) * (
            settings.start_stay - (1.0 - settings.start_stay) / (k - 1))
        return KStateParams(np.full(k, 1.0 / k), np.broadcast_to(stay, (2, 2, 2, k, k)), np.stack([spread, spread]))
    return KStateParams(rng.dirichlet(np.ones(k)), rng.dirichlet(np.ones(k), size=(2, 2, 2, k)),
                        rng.uniform(0.0, 1.0, size=(2, k)))


def n_free_parameters(k: int, data: PaddedData) -> int:
    """Free parameters the data inform: K − 1 initial, K(K − 1) per input seen, K per complexity with auto trials."""
    return (k - 1) + int(data.inputs_used.sum()) * k * (k - 1) + int(data.complexities_used.sum()) * k


def _run(params: KStateParams, data: PaddedData, settings: EMSettings) -> tuple[KStateParams, float, int, bool]:
    previous = -math.inf
    for iteration in range(1, settings.max_iter + 1):
        new, loglik = _em_step(params, data)
        if loglik - previous <= settings.tol * data.n_trials:
            return params, loglik, iteration, True
        params, previous = new, loglik
    return params, batch_log_likelihood(params, data), settings.max_iter, False


def fit_k_states(sequences: list[Sequence], k: int, rng: np.random.Generator,
                 settings: EMSettings = EMSettings()) -> KStateFit:
    """Maximum-likelihood K-state IOHMM by EM from ``settings.restarts`` seeded starts; the best, ordered."""
    if not MIN_STATES <= k <= MAX_STATES:
        raise ValueError(f"the number of trust states must be {MIN_STATES}…{MAX_STATES}, got {k}")
    data = PaddedData(sequences)
    runs = [_run(start_params(k, r, rng, settings), data, settings) for r in range(settings.restarts)]
    logliks = np.array([run[1] for run in runs])
    best = runs[int(np.argmax(logliks))]
    return KStateFit(order_states(best[0]), best[1], logliks, np.array([run[2] for run in runs]),
                     np.array([run[3] for run in runs]), data.n_trials, n_free_parameters(k, data))
