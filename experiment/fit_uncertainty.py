"""How well each fitted IOHMM parameter is determined: statuses and Laplace standard errors.

The paper (§4.3) prints e = sqrt(diag(−H)); that is a slip (SPEC §11): the
Laplace approximation gives the covariance (−H)⁻¹, so the standard error is
sqrt(diag((−H)⁻¹)), which is what we compute.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

BOUNDARY = 1e-6  # an estimate this close to 0 or 1 is on the boundary
MIN_USES = 1e-6  # posterior expected uses (n0 + n1) below this: the data say nothing about the slot
FLAT_ABS = 1e-6  # information eigenvalue below this (or FLAT_REL × the largest): flat direction
FLAT_REL = 1e-9
STEP = 1e-4  # finite-difference step, relative to the distance of an estimate to 0 or 1

STDERR_METHOD = (
    "Laplace: sqrt(diag((-H)^-1)), H = Hessian of the total log-likelihood w.r.t. the interior "
    "('estimated') parameters only, the 'boundary'/'unidentified' ones held fixed at their estimates; "
    "H by central finite differences (step 1e-4·min(θ, 1-θ)) of the exact gradient (Fisher's identity), "
    "symmetrised. Zero-information directions of -H (eigenvalue <= max(1e-6, 1e-9·largest)) are removed by "
    "marking their dominant parameter 'unidentified'. Not the paper's sqrt(diag(-H)) (SPEC §11)."
)


def classify(theta: np.ndarray, uses: np.ndarray, exercised: np.ndarray) -> np.ndarray:
    """Status per parameter before looking at curvature; all arrays (P,)."""
    near = (theta <= BOUNDARY) | (theta >= 1.0 - BOUNDARY)
    return np.where(~exercised, "not_exercised",
                    np.where(uses < MIN_USES, "unidentified", np.where(near, "boundary", "estimated"))).astype(object)


def hessian(theta: np.ndarray, free: np.ndarray, grad_batch: Callable[[np.ndarray], np.ndarray],
            dependent: np.ndarray | None = None) -> np.ndarray:
    """(k, k) symmetrised Hessian of L w.r.t. theta[free] (k = free.size indices), others fixed.

    grad_batch maps parameter vectors (M, P) to exact gradients (M, P); all
    2k perturbed vectors go through it in one batch. ``dependent`` (k,), if
    given, names for each free coordinate j an entry that moves against it
    (−1: none), so that a simplex row keeps its sum: coordinate j adds t to
    theta[free[j]] and takes t from theta[dependent[j]], and by the chain rule
    its gradient is g[free[j]] − g[dependent[j]]. Step: STEP × the distance of
    the moved entries to the edge of [0, 1].
    """
    k = free.size
    dep = np.full(k, -1) if dependent is None else np.asarray(dependent)
    has = dep >= 0
    h = STEP * np.minimum(np.minimum(theta[free], 1.0 - theta[free]), np.where(has, theta[dep], np.inf))
    points = np.repeat(theta[None], 2 * k, axis=0)
    points[np.arange(k), free] += h
    points[k + np.arange(k), free] -= h
    points[np.arange(k)[has], dep[has]] -= h[has]
    points[k + np.arange(k)[has], dep[has]] += h[has]
    grad = grad_batch(points)
    g = grad[:, free] - np.where(has, grad[:, dep], 0.0)
    H = ((g[:k] - g[k:]) / (2.0 * h[:, None])).T  # column j: d grad / d theta_j
    return 0.5 * (H + H.T)


def laplace_covariance(info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (−H)⁻¹ (k, k) from the observed information info = −H (k, k).

    While the information is not clearly positive definite, the parameter with
    the largest weight in the weakest eigen-direction is dropped (held fixed).
    Returns the covariance of the kept ones (NaN in the rows and columns of
    dropped ones) and the dropped mask (k,).
    """
    keep = list(range(info.shape[0]))
    cov = np.full(info.shape, np.nan)
    dropped = np.ones(info.shape[0], dtype=bool)
    while keep:
        w, V = np.linalg.eigh(info[np.ix_(keep, keep)])
        if w[0] > max(FLAT_ABS, FLAT_REL * w[-1]):
            cov[np.ix_(keep, keep)] = (V / w) @ V.T
            dropped[keep] = False
            break
        keep.pop(int(np.argmax(np.abs(V[:, 0]))))
    return cov, dropped


def laplace(info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors (k,) from the observed information info = −H (k, k) (NaN for dropped ones), and the
    dropped mask (k,); see ``laplace_covariance``."""
    cov, dropped = laplace_covariance(info)
    return np.sqrt(np.diag(cov)), dropped


def assess(theta: np.ndarray, uses: np.ndarray, exercised: np.ndarray,
           grad_batch: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, list[str]]:
    """Standard errors (P,) and statuses (P,) at a maximum-likelihood estimate theta (P,).

    uses (P,) is the posterior expected number of uses n0 + n1 of each slot.
    """
    status = classify(theta, uses, exercised)
    free = np.flatnonzero(status == "estimated")
    stderr = np.full(theta.shape, np.nan)
    if free.size:
        se, flat = laplace(-hessian(theta, free, grad_batch))
        stderr[free] = se
        status[free[flat]] = "unidentified"
    return stderr, [str(s) for s in status]
