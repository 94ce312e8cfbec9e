"""Maximum-likelihood fitting of the trust IOHMM (paper §3–§4, SPEC §6).

Baum–Welch (EM) from several random restarts, run side by side and
accelerated with SQUAREM (Varadhan & Roland 2008); the best restarts are
polished with a bounded quasi-Newton step (L-BFGS-B on [0, 1]) using the
exact gradient, because maximum-likelihood optima of this model often lie on
the boundary where plain EM crawls. The E-step lives in
``experiment.fit_estep``; standard errors in ``experiment.fit_uncertainty``.
Shapes: R restarts, P = 21 parameters in the order of ``iohmm.PARAMETER_NAMES``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize

from experiment.fit_estep import Data, EStep, e_step, log_likelihood, log_likelihood_gradient
from experiment.fit_uncertainty import STDERR_METHOD, assess
from experiment.iohmm import (
    EMISSIONS_OF,
    INITIAL,
    N_PARAMETERS,
    PARAMETER_NAMES,
    IOHMMParams,
    model_document,
    nest,
    swap_states,
)
from experiment.sequences import Sequence
from experiment.task import Complexity

__all__ = ["FitResult", "fit_iohmm", "log_likelihood", "log_likelihood_gradient"]

_STAGE_ITER = 5  # iterations per screening stage
_KEEP = 4  # distinct restarts that run to convergence
_SWITCH_TOL = 1e-6  # with acceleration, EM hands over to the polish at this relative gain per iteration
_POLISH_WITHIN = 1.0  # polish every finalist within this loglik of the best
_KKT_TOL = 1e-6  # converged: |projected gradient| ≤ this × number of trials


# -- EM (SQUAREM-accelerated, vectorised over restarts) and the polish -----------

def _m_step(theta: np.ndarray, stats: EStep, free: np.ndarray) -> np.ndarray:
    """EM update n1 / (n1 + n0) of the free slots (R, P); slots without expected uses keep their value."""
    total = stats.n1 + stats.n0
    with np.errstate(all="ignore"):
        return np.clip(np.where((total > 0) & free, stats.n1 / total, theta), 0.0, 1.0)


def _squarem(data: Data, theta: np.ndarray, free: np.ndarray, n_iter: int, tol: float, accelerate: bool,
             tick: Callable[[], None]) -> tuple[np.ndarray, ...]:
    """At most n_iter iterations of (accelerated) EM on theta (R, P), side by side.

    One iteration: θ1 = F(θ0), θ2 = F(θ1) (F = EM map); SQUAREM (Varadhan &
    Roland 2008, S3) proposes θ' = θ0 − 2αr + α²v, r = θ1 − θ0,
    v = θ2 − 2θ1 + θ0, α = min(−‖r‖/‖v‖, −1), projected to [0, 1]; θ' is
    kept only if L(θ') ≥ L(θ1), else the plain EM point θ1, so L never
    decreases. A restart stops when an iteration gains ≤ tol·(1 + |L|).
    Returns theta (R, P), loglik (R,), iterations (R,), stopped (R,) and the
    trace (iterations + 1, R) of loglik (NaN once a restart stopped).
    """
    theta = theta.copy()
    stats = e_step(data, theta)
    ll, nxt = stats.loglik.copy(), _m_step(theta, stats, free)
    trace, its, active = [ll.copy()], np.zeros(len(theta), dtype=int), np.isfinite(ll)
    for _ in range(n_iter):
        rows = np.flatnonzero(active)
        if not rows.size:
            break
        th0, th1 = theta[rows], nxt[rows]
        s1 = e_step(data, th1)
        new_th, new_ll, new_nxt = th1, s1.loglik, _m_step(th1, s1, free)
        if accelerate:
            r, v = th1 - th0, new_nxt - 2.0 * th1 + th0
            rr, vv = (r * r).sum(axis=1), (v * v).sum(axis=1)
            alpha = np.minimum(np.where(vv > 0, -np.sqrt(rr / np.where(vv > 0, vv, 1.0)), -1.0), -1.0)[:, None]
            th_x = np.where(free, np.clip(th0 - 2.0 * alpha * r + alpha * alpha * v, 0.0, 1.0), th0)
            sx = e_step(data, th_x)
            ok = np.isfinite(sx.loglik) & (sx.loglik >= s1.loglik)
            new_th, new_ll = np.where(ok[:, None], th_x, th1), np.where(ok, sx.loglik, s1.loglik)
            new_nxt = np.where(ok[:, None], _m_step(th_x, sx, free), new_nxt)
        gain = new_ll - ll[rows]
        theta[rows], ll[rows], nxt[rows] = new_th, new_ll, new_nxt
        its[rows] += 1
        trace.append(np.full(len(theta), np.nan))
        trace[-1][rows] = new_ll
        active[rows[gain <= tol * (1.0 + np.abs(new_ll))]] = False
        tick()
    return theta, ll, its, ~active, np.array(trace)


def _polish(data: Data, theta: np.ndarray, free: np.ndarray) -> np.ndarray:
    """L-BFGS-B on [0, 1] from theta (P,) with the exact gradient; returns the new theta (P,).

    Variables are scaled by sqrt(n/(θ(1−θ))) (complete-data information at the start).
    """
    stats = e_step(data, theta[None])
    th0 = np.clip(theta[free], 1e-3, 1.0 - 1e-3)
    scale = np.sqrt((stats.n1 + stats.n0)[0, free] / (th0 * (1.0 - th0)) + 1.0)

    def objective(y: np.ndarray) -> tuple[float, np.ndarray]:
        th = theta.copy()
        th[free] = np.clip(y / scale, 0.0, 1.0)
        s = e_step(data, th[None])
        if not np.isfinite(s.loglik[0]):
            return 1e30, np.zeros_like(y)
        return -s.loglik[0] / data.n_trials, -s.grad[0, free] / scale / data.n_trials

    res = minimize(objective, theta[free] * scale, jac=True, method="L-BFGS-B",
                   bounds=list(zip(0 * scale, scale, strict=True)),
                   options={"maxiter": 1000, "ftol": 1e-15, "gtol": 1e-10})
    out = theta.copy()
    out[free] = np.clip(res.x / scale, 0.0, 1.0)
    return out


def _kkt(theta: np.ndarray, grad: np.ndarray, free: np.ndarray, n_trials: int) -> bool:
    """First-order optimality on [0, 1]: the projected gradient (P,) of the free slots is ~0."""
    projected = np.where(theta <= 0.0, np.maximum(grad, 0.0), np.where(theta >= 1.0, np.minimum(grad, 0.0), grad))
    return bool(np.abs(projected[free]).max() <= _KKT_TOL * n_trials)


# -- state labels and restarts ---------------------------------------------------

def _label(theta: np.ndarray, exercised: np.ndarray) -> np.ndarray:
    """Make "high" the state with the larger P(rely | high complexity, auto); ties: low complexity, then initial."""
    rely_low, rely_high = theta[EMISSIONS_OF[0]], theta[EMISSIONS_OF[1]]  # by complexity
    seen = exercised[EMISSIONS_OF[0]] & exercised[EMISSIONS_OF[1]]
    for c in (Complexity.HIGH.code, Complexity.LOW.code):
        if seen[c] and rely_low[c] != rely_high[c]:
            return swap_states(theta) if rely_low[c] > rely_high[c] else theta
    return swap_states(theta) if theta[INITIAL] < 0.5 else theta


def _distinct_best(theta: np.ndarray, loglik: np.ndarray, free: np.ndarray, keep: int) -> np.ndarray:
    """Indices of up to `keep` restarts, best first, whose labelled parameters differ by > 1e-3."""
    return distinct_best(np.array([_label(th, free) for th in theta])[:, free], loglik, keep)


def distinct_best(labelled: np.ndarray, loglik: np.ndarray, keep: int) -> np.ndarray:
    """Indices of up to `keep` restarts, best first, whose labelled parameter vectors (R, P) differ by > 1e-3."""
    chosen: list[int] = []
    for r in np.argsort(-loglik, kind="stable"):
        if np.isfinite(loglik[r]) and all(np.abs(labelled[r] - labelled[k]).max() > 1e-3 for k in chosen):
            chosen.append(int(r))
        if len(chosen) == keep:
            break
    return np.array(chosen or [int(np.argmax(loglik))])


def _run_restarts(data: Data, theta: np.ndarray, free: np.ndarray, max_iter: int, tol: float, accelerate: bool,
                  keep: int, tick: Callable[[], None]) -> tuple[Any, ...]:
    """EM on all starts theta (R, P) with successive halving.

    Stages of 5 iterations; after each, only the better half of the distinct
    restarts (at least `keep`) go on; the last `keep` run until they stop or
    max_iter. Returns theta, loglik, iterations per restart, their loglik
    traces and the indices of the finalists.
    """
    R = len(theta)
    ll, its, stopped = np.full(R, -np.inf), np.zeros(R, dtype=int), np.zeros(R, dtype=bool)
    traces = [np.empty(0)] * R
    rows, used = np.arange(R), 0
    while True:
        final = len(rows) <= keep
        run = rows[~stopped[rows]]
        if run.size:
            n_iter = max_iter - used if final else min(_STAGE_ITER, max_iter - used)
            th, lls, it, st, trace = _squarem(data, theta[run], free, n_iter, tol, accelerate, tick)
            theta[run], ll[run], stopped[run], its[run] = th, lls, st, its[run] + it
            for i, r in enumerate(run):
                col = trace[:, i][~np.isnan(trace[:, i])]
                traces[r] = np.concatenate([traces[r], col[1:] if traces[r].size else col])
            used += int(it.max())
        if final or used >= max_iter:
            return theta, ll, its, traces, rows
        rows = rows[_distinct_best(theta[rows], ll[rows], free, max(keep, (len(rows) + 1) // 2))]


# -- the fit -----------------------------------------------------------------------

@dataclass(frozen=True)
class FitResult:
    params: IOHMMParams  # NaN where the data never exercise a parameter
    loglik: float  # total log-likelihood of `params`
    stderr: np.ndarray  # (P,) Laplace standard errors, NaN unless status is "estimated"
    status: list[str]  # (P,) "estimated" | "boundary" | "not_exercised" | "unidentified"
    n_sequences: int
    n_trials: int
    restarts: int
    seed: int
    iterations: int  # EM/SQUAREM iterations of the returned restart
    converged: bool  # projected gradient ≤ 1e-6 × n_trials at `params`
    restart_logliks: np.ndarray  # (restarts,) loglik each restart reached (before any polish)
    loglik_trace: np.ndarray  # loglik of the returned restart after each iteration (+ polished value)

    def to_document(self, fitted_on: dict[str, Any] | None = None) -> dict[str, Any]:
        """The model JSON (SPEC §9) with standard errors, statuses and fit metadata."""
        return model_document(
            self.params, loglik=self.loglik,
            stderr=nest(dict(zip(PARAMETER_NAMES, self.stderr.tolist(), strict=True))),
            status=nest(dict(zip(PARAMETER_NAMES, self.status, strict=True))),
            fit={"restarts": self.restarts, "seed": self.seed, "iterations": self.iterations,
                 "converged": self.converged, "n_sequences": self.n_sequences, "n_trials": self.n_trials,
                 "stderr_method": STDERR_METHOD},
            fitted_on=fitted_on)


def fit_iohmm(sequences: list[Sequence], *, restarts: int = 20, seed: int = 0, tol: float = 1e-8,
              max_iter: int = 1000, progress: Callable[[int, int], None] | None = None,
              init: IOHMMParams | None = None, accelerate: bool = True, keep: int | None = None) -> FitResult:
    """Maximum-likelihood IOHMM: EM from `restarts` random starts, then a bounded quasi-Newton polish.

    Starts: every parameter ~ U(0.05, 0.95) from ``np.random.default_rng(seed)``
    (``init``, if given, replaces the first start). The restarts run
    SQUAREM-accelerated EM side by side, with successive halving: every 5
    iterations the worse half of the distinct restarts is dropped until
    `keep` (default 4) finalists are left. A restart stops when an iteration
    gains ≤ tol·(1 + |L|) (with acceleration ≤ max(tol, 1e-6)·(1 + |L|): EM
    crawls along flat or boundary directions, where the polish is far
    faster) or after `max_iter` iterations in all. Every finalist within 1.0
    of the best loglik is polished with L-BFGS-B on [0, 1] (exact gradient)
    and the best point wins. ``accelerate=False``: plain EM, no polish.
    The states are then labelled (high = larger P(rely | high complexity,
    auto)) and the loglik is recomputed at the returned parameters.
    ``progress(done, max_iter)`` is called after each iteration and once at
    the end with done = max_iter. Same arguments ⇒ bit-identical result.
    """
    if restarts < 1 or max_iter < 1:
        raise ValueError("restarts and max_iter must be at least 1")
    data = Data(sequences)
    free = data.exercised
    theta = np.random.default_rng(seed).uniform(0.05, 0.95, size=(restarts, N_PARAMETERS))
    if init is not None:
        theta[0] = np.where(np.isnan(init.to_vector()), theta[0], init.to_vector())
    theta[:, ~free] = 0.5
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, max_iter)

    keep = max(1, min(restarts, _KEEP if keep is None else keep))
    em_tol = max(tol, _SWITCH_TOL) if accelerate else tol
    theta, restart_ll, its, traces, rows = _run_restarts(data, theta, free, max_iter, em_tol, accelerate, keep, tick)
    order = rows[np.argsort(-restart_ll[rows], kind="stable")]
    best = int(order[0])
    final, final_ll, trace = theta[best], restart_ll[best], traces[best]
    for r in order[restart_ll[order] >= restart_ll[best] - _POLISH_WITHIN] if accelerate else []:
        polished = _polish(data, theta[r], free)
        polished_ll = e_step(data, polished[None]).loglik[0]
        if polished_ll > final_ll:
            best, final, final_ll, trace = int(r), polished, polished_ll, np.append(traces[r], polished_ll)
    final = _label(final, free)
    stats = e_step(data, final[None])
    stderr, status = assess(final, (stats.n1 + stats.n0)[0], free, lambda th: e_step(data, th).grad)
    if progress is not None:
        progress(max_iter, max_iter)
    return FitResult(
        params=IOHMMParams.from_vector(np.where(free, final, np.nan)), loglik=float(stats.loglik[0]),
        stderr=stderr, status=status, n_sequences=data.n_sequences, n_trials=data.n_trials, restarts=restarts,
        seed=seed, iterations=int(its[best]), converged=_kkt(final, stats.grad[0], free, data.n_trials),
        restart_logliks=restart_ll, loglik_trace=trace)
