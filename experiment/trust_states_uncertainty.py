"""Laplace standard errors of the K-state trust IOHMM (issue 40), with the two-state fit's statuses and thresholds.

As ``experiment.fit_uncertainty`` (whose helpers this reuses): every entry of ``initial``, ``transition`` and
``p_rely`` gets a status, and a standard error sqrt(diag((−H)⁻¹)) where it is "estimated":

- ``not_exercised``: a transition row of an input the data never show (NaN in the model), ``p_rely`` of a
  complexity without autonomous trials;
- ``unidentified``: the data give the entry no expected use, or the observed information is flat (singular, not
  positive definite) in its direction;
- ``boundary``: the estimate is within ``fit_uncertainty.BOUNDARY`` of 0 or 1, where the Laplace approximation does
  not hold; such entries are held fixed;
- ``estimated``: otherwise.

Free coordinates: a simplex row (``initial``, each transition row) has one fewer than its interior entries: the
largest interior entry is the dependent one (ties: the first), moving against the others so that the row keeps its
sum; its variance is that of minus the sum of the free ones (delta method), and a row with a single interior entry
has none (the entry is pinned by its boundary entries: "boundary"). ``p_rely`` entries are free when interior.
H is the Hessian of the total log-likelihood in the free coordinates, by central differences of the exact gradient
(Fisher's identity, ``trust_states_em.gradient``) mapped by the chain rule, with every perturbed vector in one
batched E-step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from experiment.fit_uncertainty import classify, hessian, laplace_covariance
from experiment.iohmm import ModelError
from experiment.trust_ratings import RatingEmission
from experiment.trust_states import N_INPUTS, KStateParams
from experiment.trust_states_em import Layout, PaddedData, e_step, gradient

STDERR_METHOD_K = (
    "Laplace: sqrt(diag((-H)^-1)), H = Hessian of the total log-likelihood w.r.t. the free coordinates: per simplex "
    "row its interior entries but the largest (which moves against them; its SE by the delta method), and the "
    "interior p_rely; 'boundary'/'unidentified' entries held fixed at their estimates. H by central finite "
    "differences (step 1e-4 x the distance of the moved entries to 0 or 1) of the exact gradient (Fisher's "
    "identity), symmetrised; zero-information directions (eigenvalue <= max(1e-6, 1e-9 x largest)) mark their "
    "dominant coordinate 'unidentified'."
)


class KStateArrays(NamedTuple):
    """One array per part of a ``KStateParams``, of the same shape."""

    initial: np.ndarray  # (K,)
    transition: np.ndarray  # (2, 2, 2, K, K) [complexity, robot_action, experience, from, to]
    p_rely: np.ndarray  # (2, K) [complexity, state]


@dataclass(frozen=True)
class KStateUncertainty:
    stderr: KStateArrays  # Laplace standard errors, NaN unless the status is "estimated"
    status: KStateArrays  # "estimated" | "boundary" | "unidentified" | "not_exercised" (str arrays)
    method: str = STDERR_METHOD_K


def _parts(layout: Layout, vector: np.ndarray) -> KStateArrays:
    initial, transition, p_rely = (part[0] for part in layout.split(vector[None]))
    return KStateArrays(initial, transition.reshape(2, 2, 2, layout.k, layout.k), p_rely)


def _free_coordinates(layout: Layout, theta: np.ndarray, status: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Free entries (k,) and the entry each moves against (k,; −1: none); marks a lone interior entry "boundary"."""
    free, dependent = [], []
    for row in layout.simplex_rows:
        interior = row[status[row] == "estimated"]
        if interior.size == 1:
            status[interior] = "boundary"
        if interior.size > 1:
            largest = interior[np.argmax(theta[interior])]
            free += [i for i in interior if i != largest]
            dependent += [largest] * (interior.size - 1)
    rely = np.arange(layout.p_rely.start, layout.p_rely.stop)
    free_rely = rely[status[rely] == "estimated"]
    return np.array(free + free_rely.tolist(), dtype=int), np.array(dependent + [-1] * free_rely.size, dtype=int)


#: Appended to the method when the model was fitted with trust ratings.
CONDITIONAL_ON_RATINGS = (" Fitted with trust ratings: the Hessian is that of the joint likelihood (reliance and "
                          "ratings) with the rating emission held at its estimate, so the standard errors are "
                          "conditional on it (slightly smaller than the unconditional ones).")


def k_state_uncertainty(params: KStateParams, data: PaddedData,
                        ratings: RatingEmission | None = None) -> KStateUncertainty:
    """Statuses and Laplace standard errors of every entry of a (maximum-likelihood) K-state model on its data
    (with ``ratings``, its rating emission, for data with ratings: the standard errors are conditional on it)."""
    k = params.n_states
    rows_missing = np.isnan(params.transition.reshape(N_INPUTS, k, k)).any(axis=-1)  # (8, K)
    if rows_missing[data.inputs_used].any():
        raise ModelError("the model has no transition estimate for an input combination in the data")
    if (ratings is None) != (data.rating_scale is None):
        raise ValueError("data with ratings need the model's rating emission, and only they")
    layout = Layout(k, data.rating_scale)
    theta = layout.pack(params, ratings)
    stats = e_step(layout, theta[None], data)
    row_uses = stats.transition[0].sum(axis=-1, keepdims=True)  # (8, K, 1)
    held = None if ratings is None else np.zeros((1, 2, k))  # the rating emission: not a free coordinate
    uses = layout.join(np.full((1, k), stats.initial[0].sum()), np.broadcast_to(row_uses, (1, N_INPUTS, k, k)),
                       stats.rely + stats.intervene, held)[0]
    exercised = layout.join(np.ones((1, k), dtype=bool), np.broadcast_to(
        (data.inputs_used[:, None] & ~rows_missing)[..., None], (1, N_INPUTS, k, k)),
        np.broadcast_to(data.complexities_used[:, None], (1, 2, k)), held)[0].astype(bool)
    status = classify(theta, uses, exercised)
    free, dependent = _free_coordinates(layout, theta, status)
    stderr = np.full(layout.size, np.nan)
    if free.size:
        info = -hessian(theta, free, lambda th: gradient(layout, th, e_step(layout, th, data)), dependent)
        cov, flat = laplace_covariance(info)
        stderr[free] = np.sqrt(np.diag(cov))
        status[free[flat]] = "unidentified"
        for row in np.unique(dependent[dependent >= 0]):
            members = np.flatnonzero(dependent == row)
            if flat[members].any():
                status[row] = "unidentified"
            else:
                stderr[row] = np.sqrt(cov[np.ix_(members, members)].sum())
    status_array = np.array([str(s) for s in status])
    method = STDERR_METHOD_K + (CONDITIONAL_ON_RATINGS if ratings is not None else "")
    return KStateUncertainty(_parts(layout, stderr), _parts(layout, status_array), method)
