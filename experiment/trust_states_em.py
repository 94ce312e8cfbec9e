"""Maximum-likelihood fit of the K-state trust IOHMM (issue 40): batched EM with SQUAREM and restarts.

As the two-state fit (``experiment.fit``), the restarts run side by side: every array carries a restart axis R,
so one pass of the Python time loop serves all of them. Shapes: T trials (time-major, sequences padded to the
longest), R restarts, N sequences, K states, P = K + 8·K² + 2·K entries of the parameter vector (``Layout``).
Padding and the step after a sequence's last trial use probability-1 emissions and the identity transition, so
they change nothing. Simplex rows (initial, transition) are renormalised after every extrapolation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.special import xlogy

from experiment import defaults
from experiment.fit import distinct_best
from experiment.iohmm import ModelError
from experiment.sequences import Sequence
from experiment.trust_ratings import RatingEmission, Ratings, beta_binomial_update, log_pmf
from experiment.trust_states import MAX_STATES, MIN_STATES, N_INPUTS, KStateParams, state_order

_NONE = N_INPUTS  # transition code of "no transition" (after the last trial, padding): the identity
_N_EMIT = 4  # emission code c·2 + o of an autonomous trial
_TINY = np.finfo(float).tiny
_MAX_CELLS = 8_000_000  # T·N·R·K² cells per E-step batch: bounds the (T, R, K, K, N) table at 64 MB


@dataclass(frozen=True)
class EMSettings:
    """Numbers of the method; their reasons are in ``experiment.defaults``."""

    restarts: int = defaults.STATES_RESTARTS
    keep: int = defaults.STATES_KEEP
    max_iter: int = defaults.STATES_MAX_ITER
    tol: float = defaults.STATES_TOL


class Layout:
    """Where each part of the model sits in a parameter vector of K states; with a rating scale (minimum,
    maximum), the rating emission's α (K) and β (K) follow ``p_rely``."""

    def __init__(self, k: int, rating_scale: tuple[int, int] | None = None) -> None:
        self.k = k
        self.initial = slice(0, k)
        self.transition = slice(k, k + N_INPUTS * k * k)
        self.p_rely = slice(self.transition.stop, self.transition.stop + 2 * k)
        self.rating_scale = rating_scale
        self.rating = slice(self.p_rely.stop, self.p_rely.stop + (2 * k if rating_scale else 0))
        self.size = self.rating.stop
        #: (rows, K) indices of the simplex rows: the initial distribution, then transition rows by (input, from)
        self.simplex_rows = np.concatenate([np.arange(k)[None], k + np.arange(N_INPUTS * k * k).reshape(-1, k)])

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """theta (R, P) → initial (R, K), transition (R, 8, K, K), p_rely (R, 2, K)."""
        r, k = len(theta), self.k
        return (theta[:, self.initial], theta[:, self.transition].reshape(r, N_INPUTS, k, k),
                theta[:, self.p_rely].reshape(r, 2, k))

    def ratings(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """theta (R, P) → the rating emission's α (R, K) and β (R, K)."""
        part = theta[:, self.rating].reshape(len(theta), 2, self.k)
        return part[:, 0], part[:, 1]

    def join(self, initial: np.ndarray, transition: np.ndarray, p_rely: np.ndarray,
             ratings: np.ndarray | None = None) -> np.ndarray:
        """The parts as (R, P); ``ratings`` (R, 2, K): α and β, with a rating scale only."""
        r = len(initial)
        parts = [initial, transition.reshape(r, -1), p_rely.reshape(r, -1)]
        if self.rating_scale is not None:
            if ratings is None:
                raise ValueError("a layout with ratings needs the rating emission")
            parts.append(ratings.reshape(r, -1))
        return np.concatenate(parts, axis=1)

    def pack(self, params: KStateParams, ratings: RatingEmission | None = None) -> np.ndarray:
        """(P,) vector of a model; rows the model leaves NaN (inputs it has no estimate for) become uniform."""
        transition = params.transition.reshape(N_INPUTS, self.k, self.k)
        transition = np.where(np.isnan(transition).any(axis=-1, keepdims=True), 1.0 / self.k, transition)
        rating = None if ratings is None else np.stack([ratings.alpha, ratings.beta])[None]
        return self.join(params.initial[None], transition[None], params.p_rely[None], rating)[0]

    def unpack_ratings(self, theta: np.ndarray) -> RatingEmission | None:
        """The rating emission of a (P,) vector (None without a rating scale)."""
        if self.rating_scale is None:
            return None
        alpha, beta = (part[0] for part in self.ratings(theta[None]))
        return RatingEmission(alpha.copy(), beta.copy(), *self.rating_scale)

    def unpack(self, theta: np.ndarray, data: PaddedData) -> KStateParams:
        """The model of a (P,) vector, NaN in the transition rows of inputs the data never show."""
        initial, transition, p_rely = (part[0] for part in self.split(theta[None]))
        transition = np.where(data.inputs_used[:, None, None], transition, np.nan)
        return KStateParams(initial / initial.sum(), transition.reshape(2, 2, 2, self.k, self.k),
                            np.clip(p_rely, 0.0, 1.0))

    def project(self, theta: np.ndarray) -> np.ndarray:
        """theta (R, P) moved onto the model's domain: simplex rows clipped at 0 and renormalised, p_rely in [0, 1]."""
        out = np.clip(theta, 0.0, None)
        rows = out[:, self.simplex_rows]
        out[:, self.simplex_rows] = rows / np.maximum(rows.sum(axis=-1, keepdims=True), _TINY)
        out[:, self.p_rely] = np.clip(out[:, self.p_rely], 0.0, 1.0)
        out[:, self.rating] = np.clip(theta[:, self.rating], *defaults.RATING_CONCENTRATION_RANGE)
        return out


class PaddedData:
    """Sequences as time-major (T, N) codes: ``trans`` the input after each trial (8: none), ``emit`` c·2 + o of an
    autonomous trial (4: none, the robot asked or padding); with ratings, ``rating`` the level rated at the trial
    (levels + 1: none)."""

    def __init__(self, sequences: list[Sequence], ratings: Ratings | None = None) -> None:
        if ratings is not None and len(ratings.levels_by_participant) != len(sequences):
            raise ValueError(f"{len(ratings.levels_by_participant)} participants' ratings for {len(sequences)} "
                             "sequences")
        kept = [i for i, s in enumerate(sequences) if len(s)]
        seqs = [sequences[i] for i in kept]
        if not seqs:
            raise ValueError("no trials to fit")
        n, t = len(seqs), max(len(s) for s in seqs)
        self.n_sequences = n
        self.lengths = np.array([len(s) for s in seqs])
        codes = np.zeros((4, t, n), dtype=np.intp)
        for i, s in enumerate(seqs):
            codes[:, :len(s), i] = (s.complexity, s.robot_action, s.human_action, s.experience)
        complexity, robot_action, human_action, experience = codes
        steps = np.arange(t)[:, None]
        auto = (steps < self.lengths[None]) & (robot_action == 0)
        self.trans = np.where(steps < self.lengths[None] - 1, (complexity * 2 + robot_action) * 2 + experience, _NONE)
        self.emit = np.where(auto, complexity * 2 + human_action, _N_EMIT)
        self.rating_scale = None if ratings is None else (ratings.minimum, ratings.maximum)
        self.rating = np.zeros((t, n), dtype=np.intp)
        if ratings is not None:
            self.rating[:] = ratings.levels + 1
            for column, i in enumerate(kept):
                levels = ratings.levels_by_participant[i]
                if len(levels) != len(sequences[i]):
                    raise ValueError(f"participant {i}: {len(levels)} rating slots for {len(sequences[i])} trials")
                self.rating[:len(levels), column] = np.where(levels >= 0, levels, ratings.levels + 1)
        self._derive()

    def _derive(self) -> None:
        """What the E-step reads, from ``trans``, ``emit`` and ``lengths``."""
        t, n = self.emit.shape
        self.trans_onehot = np.eye(N_INPUTS + 1)[self.trans[:-1], :N_INPUTS]  # (T − 1, N, 8)
        self.emit_onehot = np.eye(_N_EMIT + 1)[self.emit, :_N_EMIT]  # (T, N, 4)
        codes = self.trans[:-1].reshape(-1)  # the (t, n) cells grouped by input: the E-step's counts by input
        self.trans_order = np.argsort(codes, kind="stable")
        self.trans_bounds = np.searchsorted(codes[self.trans_order], np.arange(N_INPUTS + 1))
        self.n_trials = int(self.lengths.sum())
        self.inputs_used = np.asarray(self.trans_onehot.any(axis=(0, 1)))  # (8,)
        self.complexities_used = np.asarray(self.emit_onehot.reshape(t, n, 2, 2).any(axis=(0, 1, 3)))  # (2,)
        levels = 0 if self.rating_scale is None else self.rating_scale[1] - self.rating_scale[0] + 1
        self.rating_onehot = np.eye(levels + 1)[self.rating, :levels]  # (T, N, levels + 1)
        self.n_ratings = int(self.rating_onehot.sum())

    def subset(self, sequences: np.ndarray) -> PaddedData:
        """The same data restricted to some sequences (indices), keeping the padded length."""
        copy = object.__new__(PaddedData)
        copy.__dict__.update(self.__dict__)
        copy.n_sequences, copy.lengths = len(sequences), self.lengths[sequences]
        copy.trans, copy.emit = self.trans[:, sequences], self.emit[:, sequences]
        copy.rating = self.rating[:, sequences]
        copy._derive()
        return copy


class EStep(NamedTuple):
    """Expected counts under the posterior, per restart: the EM statistics and the exact gradient's parts."""

    loglik: np.ndarray  # (R,)
    initial: np.ndarray  # (R, K) expected first states
    transition: np.ndarray  # (R, 8, K, K) expected transitions by input
    rely: np.ndarray  # (R, 2, K) expected "rely" among autonomous trials, by complexity
    intervene: np.ndarray  # (R, 2, K) expected "intervene"
    entropy: np.ndarray  # (R,) entropy of the posterior over state paths (ICL's penalty); NaN unless asked
    sequence_loglik: np.ndarray  # (R, N) log-likelihood of each sequence (−inf where ruled out)
    ratings: np.ndarray  # (R, levels + 1, K) expected states at the trials rated at each level; (R, 0, K) without


def _e_step_batch(layout: Layout, theta: np.ndarray, data: PaddedData, entropy: bool) -> EStep:
    # sequences on the last axis: each step's arithmetic runs over N contiguous numbers
    initial, transition, p_rely = layout.split(theta)
    r, k = len(theta), layout.k
    table = np.concatenate([transition, np.broadcast_to(np.eye(k), (r, 1, k, k))], axis=1)  # (R, 9, K, K)
    trans = np.ascontiguousarray(np.moveaxis(table.transpose(0, 2, 3, 1)[..., data.trans], 3, 0))  # (T, R, K, K, N)
    emission = np.stack([p_rely[:, 0], 1.0 - p_rely[:, 0], p_rely[:, 1], 1.0 - p_rely[:, 1], np.ones((r, k))],
                        axis=2)  # (R, K, 5) by emission code
    emit = np.ascontiguousarray(np.moveaxis(emission[..., data.emit], 2, 0))  # (T, R, K, N)
    if layout.rating_scale != data.rating_scale:
        raise ValueError("the layout's rating scale is not the data's")
    if layout.rating_scale is not None:
        alpha, beta = layout.ratings(theta)
        rating = np.concatenate([np.exp(log_pmf(alpha, beta, layout.rating_scale[1] - layout.rating_scale[0])),
                                 np.ones((r, k, 1))], axis=2)  # (R, K, levels + 2) by rating code
        emit *= np.moveaxis(rating[..., data.rating], 2, 0)
    t_len, n = data.emit.shape
    alpha, scale = np.empty((t_len, r, k, n)), np.empty((t_len, r, n))
    predicted = np.broadcast_to(initial[:, :, None], (r, k, n))
    for t in range(t_len):
        joint = predicted * emit[t]
        scale[t] = joint.sum(axis=1)
        alpha[t] = joint / np.where(scale[t] > 0, scale[t], 1.0)[:, None]
        if t + 1 < t_len:
            predicted = (alpha[t][:, :, None] * trans[t]).sum(axis=1)
    inverse_scale = np.divide(1.0, scale, out=np.zeros_like(scale), where=scale > 0)  # a ruled-out observation: 0
    ahead = emit[1:] * inverse_scale[1:, :, None]  # P(o_t+1 | T_t+1) β_t+1 / scale_t+1, once β_t+1 is in
    beta = np.ones((t_len, r, k, n))
    for t in range(t_len - 2, -1, -1):
        ahead[t] *= beta[t + 1]
        beta[t] = (trans[t] * ahead[t][:, None]).sum(axis=2)
    gamma = alpha * beta
    # ξ_t(i, j) = α_t(i) P(j | i, input_t) ahead_t(j): the matrix is the same for every (t, n) of one input, so the
    # counts by input are Σ α_t(i) ahead_t(j) over that input's cells, times the matrix
    a = alpha[:-1].transpose(1, 2, 0, 3).reshape(r, k, -1)[..., data.trans_order]
    b = ahead.transpose(1, 2, 0, 3).reshape(r, k, -1)[..., data.trans_order]
    outer = np.stack([np.matmul(a[..., lo:hi], b[..., lo:hi].transpose(0, 2, 1))
                      for lo, hi in zip(data.trans_bounds[:-1], data.trans_bounds[1:], strict=True)], axis=1)
    counts = outer * transition  # (R, 8, K, K)
    by_code = np.einsum("tne,trjn->rej", data.emit_onehot, gamma, optimize=True)  # (R, 4, K)
    by_sequence = np.where((scale > 0).all(axis=0), np.log(np.where(scale > 0, scale, 1.0)).sum(axis=0), -math.inf)
    loglik = by_sequence.sum(axis=1)
    path_entropy = np.full(r, np.nan)
    if entropy:  # H(Z | O) = −Σ γ_1 log γ_1 − Σ_t Σ_ij ξ_t(i, j) log P(T_t+1 = j | T_t = i, O)
        xi = alpha[:-1, :, :, None] * trans[:-1] * ahead[:, :, None]  # (T − 1, R, K, K, N)
        conditional = xi / np.maximum(gamma[:-1, :, :, None], _TINY)
        path_entropy = -(xlogy(gamma[0], gamma[0]).sum(axis=(1, 2)) + xlogy(xi, conditional).sum(axis=(0, 2, 3, 4)))
    by_rating = np.einsum("tnl,trjn->rlj", data.rating_onehot, gamma, optimize=True)  # (R, levels + 1, K)
    return EStep(loglik, gamma[0].sum(axis=2), counts, by_code[:, 0::2], by_code[:, 1::2], path_entropy,
                 by_sequence, by_rating)


def e_step(layout: Layout, theta: np.ndarray, data: PaddedData, *, entropy: bool = False) -> EStep:
    """The E-step of every parameter vector of theta (R, P), in batches that bound the memory."""
    per_vector = data.trans.size * layout.k * layout.k
    size = max(1, _MAX_CELLS // per_vector)
    parts = [_e_step_batch(layout, theta[i:i + size], data, entropy) for i in range(0, len(theta), size)]
    return EStep(*(np.concatenate(arrays) for arrays in zip(*parts, strict=True)))


def m_step(layout: Layout, theta: np.ndarray, stats: EStep) -> np.ndarray:
    """The EM update of theta (R, P); rows without expected uses keep their value."""
    initial, transition, p_rely = layout.split(theta)
    new_initial = stats.initial / np.maximum(stats.initial.sum(axis=-1, keepdims=True), _TINY)
    rows = stats.transition.sum(axis=-1, keepdims=True)
    new_transition = np.where(rows > 0, stats.transition / np.maximum(rows, _TINY), transition)
    total = stats.rely + stats.intervene
    new_rely = np.where(total > 0, stats.rely / np.maximum(total, _TINY), p_rely)
    ratings = None
    if layout.rating_scale is not None:
        alpha, beta = layout.ratings(theta)
        ratings = np.stack(beta_binomial_update(stats.ratings, alpha, beta,
                                                layout.rating_scale[1] - layout.rating_scale[0]), axis=1)
    return layout.join(new_initial, new_transition, np.clip(new_rely, 0.0, 1.0), ratings)


def gradient(layout: Layout, theta: np.ndarray, stats: EStep) -> np.ndarray:
    """(R, P) ∂L/∂θ with every entry taken as a free variable (Fisher's identity: expected count / θ).

    Entries at 0 get 0 (they carry no expected count); the Laplace step only uses interior entries. The rating
    emission's entries get 0: standard errors are conditional on it (``trust_states_uncertainty``).
    """
    def ratio(count: np.ndarray, value: np.ndarray) -> np.ndarray:
        return np.divide(count, value, out=np.zeros_like(count), where=value > 0)

    initial, transition, p_rely = layout.split(theta)
    return layout.join(ratio(stats.initial, initial), ratio(stats.transition, transition),
                       ratio(stats.rely, p_rely) - ratio(stats.intervene, 1.0 - p_rely),
                       None if layout.rating_scale is None else np.zeros((len(theta), 2, layout.k)))


# -- SQUAREM over restarts side by side ------------------------------------------

def _squarem(layout: Layout, data: PaddedData, theta: np.ndarray, n_iter: int, tol: float,
             tick: Callable[[], None]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """At most n_iter SQUAREM iterations (Varadhan & Roland 2008, S3) of theta (R, P), side by side.

    θ1 = F(θ0), θ2 = F(θ1) (F: the EM map); the extrapolation θ' = θ0 − 2αr + α²v, r = θ1 − θ0,
    v = θ2 − 2θ1 + θ0, α = min(−‖r‖/‖v‖, −1), projected onto the domain, is kept only if L(θ') ≥ L(θ1), else θ1:
    the likelihood never decreases. A restart stops when an iteration gains ≤ tol·(1 + |L|) (converged), or when
    even its present gain for the iterations left would not bring it up to the best restart's likelihood.
    Returns theta, loglik (R,), iterations (R,) and converged (R,).
    """
    theta = theta.copy()
    stats = e_step(layout, theta, data)
    loglik, following = stats.loglik.copy(), m_step(layout, theta, stats)
    iterations, active = np.zeros(len(theta), dtype=int), np.isfinite(loglik)
    converged = np.zeros(len(theta), dtype=bool)
    for step in range(n_iter):
        rows = np.flatnonzero(active)
        if not rows.size:
            break
        th0, th1 = theta[rows], following[rows]
        s1 = e_step(layout, th1, data)
        th2 = m_step(layout, th1, s1)
        r, v = th1 - th0, th2 - 2.0 * th1 + th0
        rr, vv = (r * r).sum(axis=1), (v * v).sum(axis=1)
        alpha = np.minimum(np.where(vv > 0, -np.sqrt(rr / np.where(vv > 0, vv, 1.0)), -1.0), -1.0)[:, None]
        th_x = layout.project(th0 - 2.0 * alpha * r + alpha * alpha * v)
        sx = e_step(layout, th_x, data)
        ok = np.isfinite(sx.loglik) & (sx.loglik >= s1.loglik)
        new_ll = np.where(ok, sx.loglik, s1.loglik)
        gain = new_ll - loglik[rows]
        theta[rows] = np.where(ok[:, None], th_x, th1)
        following[rows] = np.where(ok[:, None], m_step(layout, th_x, sx), th2)
        loglik[rows] = new_ll
        iterations[rows] += 1
        converged[rows[gain <= tol * (1.0 + np.abs(new_ll))]] = True
        # EM's gains shrink: a restart that would stay below the best even at its present gain is left behind
        behind = rows[new_ll + gain * (n_iter - 1 - step) < loglik.max()]
        active[rows[converged[rows]]] = active[behind] = False
        tick()
    return theta, loglik, iterations, converged


# -- restarts --------------------------------------------------------------------

def start_vectors(layout: Layout, restarts: int, rng: np.random.Generator) -> np.ndarray:
    """(restarts, P) starts: restart 0 evenly spread, persistent states; the others uniform on the domain.

    Restart 0 spreads P(rely | state) over [0.1, 0.9] and stays in a state with probability 0.8 (trust is
    persistent, paper §4.2); the others draw every simplex row from a flat Dirichlet and P(rely) from U(0, 1).
    """
    k = layout.k
    spread = 0.5 + defaults.STATES_START_SPREAD * (np.arange(k) / (k - 1) - 0.5)
    stay = np.full((k, k), (1.0 - defaults.STATES_START_STAY) / (k - 1))
    np.fill_diagonal(stay, defaults.STATES_START_STAY)
    with_ratings = layout.rating_scale is not None

    def ratings(mean: np.ndarray, concentration: np.ndarray) -> np.ndarray | None:
        """(R, 2, K) α, β of a rating mean and concentration: trust ratings rise with reliance."""
        return np.stack([mean * concentration, (1.0 - mean) * concentration], axis=1) if with_ratings else None

    first = layout.join(np.full((1, k), 1.0 / k), np.broadcast_to(stay, (1, N_INPUTS, k, k)),
                        np.stack([spread, spread])[None],
                        ratings(spread[None], np.full((1, k), defaults.RATING_START_CONCENTRATION)))
    if restarts == 1:
        return first
    # the rating draws come after the others, so that a fit without ratings starts as it always did
    initial, transition = rng.dirichlet(np.ones(k), size=restarts - 1), rng.dirichlet(np.ones(k), size=(
        restarts - 1, N_INPUTS, k))
    p_rely = rng.uniform(0.0, 1.0, size=(restarts - 1, 2, k))
    low, high = np.log(defaults.RATING_START_CONCENTRATION_RANGE)
    shape = (restarts - 1, k)
    rating = None if not with_ratings else ratings(rng.uniform(*defaults.RATING_START_MEAN_RANGE, size=shape),
                                                   np.exp(rng.uniform(low, high, shape)))
    return np.concatenate([first, layout.join(initial, transition, p_rely, rating)])


def ordered(layout: Layout, theta: np.ndarray, data: PaddedData) -> tuple[KStateParams, RatingEmission | None]:
    """The model of a (P,) vector with its states in ``state_order``, and its rating emission likewise."""
    params, ratings = layout.unpack(theta, data), layout.unpack_ratings(theta)
    order = state_order(params)
    return params.permuted(order), None if ratings is None else ratings.permuted(order)


def _distinct_best(layout: Layout, data: PaddedData, theta: np.ndarray, loglik: np.ndarray, keep: int) -> np.ndarray:
    """Indices of up to ``keep`` restarts, best first, whose state-ordered parameters differ by > 1e-3."""
    return distinct_best(np.array([layout.pack(*ordered(layout, th, data)) for th in theta]), loglik, keep)


@dataclass(frozen=True)
class KStateFit:
    params: KStateParams  # ordered by ``order_states``; NaN rows for inputs the data never show
    loglik: float
    n_states: int
    restart_logliks: np.ndarray = field(repr=False)  # (R,) log-likelihood each restart reached
    iterations: int = 0  # SQUAREM iterations of the returned restart
    converged: bool = False  # stopped by the tolerance, not by the iteration cap
    n_sequences: int = 0
    n_trials: int = 0
    n_free: int = 0  # free parameters the data can inform (BIC's count)
    path_entropy: float = 0.0  # entropy of the posterior over state paths at the estimate (ICL's penalty)
    ratings: RatingEmission | None = None  # the rating emission, when fitted with ratings (states as ``params``)
    n_ratings: int = 0


def n_free_parameters(k: int, data: PaddedData) -> int:
    """Free parameters the data inform: K − 1 initial, K(K − 1) per input seen, K per complexity with auto trials,
    and with ratings 2K (α, β per state)."""
    ratings = 2 * k if data.rating_scale is not None and data.n_ratings else 0
    return (k - 1) + int(data.inputs_used.sum()) * k * (k - 1) + int(data.complexities_used.sum()) * k + ratings


def fit_k_states(sequences: list[Sequence] | PaddedData, k: int, *, seed: int = 0,
                 settings: EMSettings = EMSettings(), progress: Callable[[int, int], None] | None = None,
                 init: KStateParams | None = None, init_ratings: RatingEmission | None = None) -> KStateFit:
    """Maximum-likelihood K-state IOHMM from ``settings.restarts`` seeded starts, side by side.

    Successive halving: every ``defaults.STATES_STAGE_ITER`` iterations the worse half of the distinct restarts is
    dropped until ``settings.keep`` finalists are left, which run until they gain ≤ tol·(1 + |L|) per iteration
    or ``settings.max_iter`` iterations in all. ``progress(done, max_iter)`` is called after each iteration (it
    may raise to cancel the fit). ``init`` (a model of K states), if given, replaces restart 0 (with
    ``init_ratings`` its rating emission, for data with ratings). Data with ratings (``PaddedData(sequences,
    ratings)``) fit the rating emission too. Same arguments ⇒ bit-identical result.
    """
    if init is not None and init.n_states != k:
        raise ValueError(f"the starting model has {init.n_states} states, not {k}")
    if not MIN_STATES <= k <= MAX_STATES:
        raise ValueError(f"the number of trust states must be {MIN_STATES}…{MAX_STATES}, got {k}")
    if settings.restarts < 1 or settings.max_iter < 1 or settings.keep < 1:
        raise ValueError("restarts, keep and max_iter must be at least 1")
    data = sequences if isinstance(sequences, PaddedData) else PaddedData(sequences)
    layout = Layout(k, data.rating_scale)
    theta = start_vectors(layout, settings.restarts, np.random.default_rng(seed))
    if init is not None:  # without init_ratings, restart 0 keeps its starting rating emission
        theta[0, :layout.p_rely.stop] = Layout(k).pack(init)
        if init_ratings is not None and layout.rating_scale is not None:
            theta[0] = layout.pack(init, init_ratings)
    loglik, iterations = np.full(len(theta), -np.inf), np.zeros(len(theta), dtype=int)
    converged = np.zeros(len(theta), dtype=bool)
    rows, used = np.arange(len(theta)), 0

    def tick() -> None:
        if progress is not None:
            progress(min(used + 1, settings.max_iter), settings.max_iter)

    while True:
        final = len(rows) <= settings.keep
        run = rows[~converged[rows]]
        if run.size:
            n_iter = settings.max_iter - used if final else min(defaults.STATES_STAGE_ITER, settings.max_iter - used)
            th, ll, its, done = _squarem(layout, data, theta[run], n_iter, settings.tol, tick)
            theta[run], loglik[run], converged[run], iterations[run] = th, ll, done, iterations[run] + its
            used += int(its.max())
        if final or used >= settings.max_iter:
            break
        rows = rows[_distinct_best(layout, data, theta[rows], loglik[rows], max(settings.keep, (len(rows) + 1) // 2))]
    best = int(rows[np.argmax(loglik[rows])])
    params, ratings = ordered(layout, theta[best], data)
    stats = e_step(layout, layout.pack(params, ratings)[None], data, entropy=True)
    if progress is not None:
        progress(settings.max_iter, settings.max_iter)
    return KStateFit(params, float(stats.loglik[0]), k, loglik, int(iterations[best]), bool(converged[best]),
                     data.n_sequences, data.n_trials, n_free_parameters(k, data), float(stats.entropy[0]),
                     ratings, data.n_ratings)


def batch_log_likelihood(params: KStateParams, data: PaddedData) -> float:
    """Total log-likelihood of the padded sequences (−inf if the model rules an observation out)."""
    k = params.n_states
    if np.isnan(params.transition.reshape(N_INPUTS, k, k))[data.inputs_used].any():
        raise ModelError("the model has no transition estimate for an input combination in the data")
    layout = Layout(k)
    return float(e_step(layout, layout.pack(params)[None], data).loglik[0])
