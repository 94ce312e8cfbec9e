"""The model JSON of a K-state trust model (issue 40), and the one reader of every model document.

Two formats, one per kind of model, so that a model has exactly one document (and one content hash):

- K = 2: the paper's model, written as today (``iohmm.model_document``, ``"format": "trustlab-iohmm"``).
- K = 3…4: ``"format": "trustlab-iohmm-k"``, ``"version": 1``, ``"n_states": K``, ``"states"`` (``state_0`` …,
  from the lowest trust to the highest) and ``"params"``, nested as the two-state document's::

      initial.state_j                             P(T_1 = j)
      transitions.{c}.{a}.{e}.from_state_i.to_state_j   P(T_{t+1} = j | T_t = i, E_{t+1} = e, C_t = c, a_t = a)
      emissions.{c}.auto.p_rely_state_j           P(rely | T_t = j, C_t = c, robot acts alone)

  A transition row the data never exercised (paper §4.2) is all ``null``; every other number is a probability.
  States are listed in the order of ``trust_states.order_states`` (ascending P(rely | high complexity)), so the
  last state is the highest trust; a document whose states are not in that order is refused.

Any other top-level keys (fit results, provenance) are kept as they are.
"""

from __future__ import annotations

import math
from itertools import product
from typing import Any

import numpy as np

from experiment.iohmm import (
    EMISSION_KEYS,
    PARAMETER_NAMES,
    TRANSITION_KEYS,
    IOHMMParams,
    ModelError,
    load_model_document,
    model_document,
    nest,
    params_from_document,
)
from experiment.iohmm import (
    FORMAT as TWO_STATE_FORMAT,
)
from experiment.task import Complexity, Experience, RobotAction
from experiment.trust_states import MAX_STATES, MIN_STATES, KStateParams, from_iohmm, order_states, to_iohmm

K_FORMAT = "trustlab-iohmm-k"
K_FORMAT_VERSION = 1
#: Rows of probabilities may miss 1 by this much (decimal rounding of a hand-written document).
ROW_SUM_TOLERANCE = 1e-9

#: A trust model: the paper's two-state form, or a model of 3…4 states.
TrustModel = IOHMMParams | KStateParams


def state_names(n_states: int) -> list[str]:
    """``state_0`` (lowest trust) … ``state_{K-1}`` (highest)."""
    return [f"state_{j}" for j in range(n_states)]


def _transition_name(c: Complexity, a: RobotAction, e: Experience, i: int, j: int) -> str:
    return f"transitions.{c}.{a}.{e}.from_state_{i}.to_state_{j}"


def _emission_name(c: Complexity, j: int) -> str:
    return f"emissions.{c}.auto.p_rely_state_{j}"


def parameter_names(n_states: int) -> list[str]:
    """Every parameter's dotted name, in document order."""
    k = range(n_states)
    return ([f"initial.state_{j}" for j in k]
            + [_transition_name(c, a, e, i, j) for c, a, e in product(Complexity, RobotAction, Experience)
               for i in k for j in k]
            + [_emission_name(c, j) for c in Complexity for j in k])


def k_state_document(params: KStateParams, **extra: Any) -> dict[str, Any]:
    """The model JSON of ``params``: today's two-state document at K = 2, ``trustlab-iohmm-k`` at K ≥ 3.

    At K ≥ 3 the states are written in ``order_states`` order (the same model, relabelled).
    """
    if params.n_states == 2:
        return model_document(to_iohmm(params), **extra)
    ordered = order_states(params)
    k = ordered.n_states
    flat = {name: float(value) for name, value in
            by_name(ordered.initial, ordered.transition, ordered.p_rely).items()}
    return {"format": K_FORMAT, "version": K_FORMAT_VERSION, "n_states": k, "states": state_names(k),
            "params": nest(flat), **extra}


def by_name(initial: np.ndarray, transition: np.ndarray, p_rely: np.ndarray) -> dict[str, Any]:
    """Entries of arrays shaped as a ``KStateParams``' (values, standard errors, statuses) by dotted name."""
    k = len(initial)
    flat: dict[str, Any] = {f"initial.state_{j}": initial[j] for j in range(k)}
    for c, a, e in product(Complexity, RobotAction, Experience):
        for i, j in product(range(k), range(k)):
            flat[_transition_name(c, a, e, i, j)] = transition[c.code, a.code, e.code, i, j]
    for c, j in product(Complexity, range(k)):
        flat[_emission_name(c, j)] = p_rely[c.code, j]
    return flat


def two_state_names(flat: dict[str, Any]) -> dict[str, Any]:
    """Entries of a two-state model by K-state name (``by_name``) under the paper's names (``PARAMETER_NAMES``):
    state 1 is high trust, and a row's P(high) carries the row's standard error and status (a row of two entries
    has one free coordinate)."""
    def state(trust: str) -> int:
        return 1 if trust == "high" else 0

    out: dict[str, Any] = {"initial.p_high": flat["initial.state_1"]}
    for c, a, e, t in TRANSITION_KEYS:
        out[f"transitions.{c}.{a}.{e}.from_{t}"] = flat[f"transitions.{c}.{a}.{e}.from_state_{state(t)}.to_state_1"]
    for c, t in EMISSION_KEYS:
        out[f"emissions.{c}.auto.p_rely_{t}"] = flat[f"emissions.{c}.auto.p_rely_state_{state(t)}"]
    assert list(out) == PARAMETER_NAMES
    return out


def k_state_params_from_document(doc: Any) -> KStateParams:
    """The K-state parameters of a model document of either format (a two-state one via ``from_iohmm``)."""
    model = trust_model_from_document(doc)
    return from_iohmm(model) if isinstance(model, IOHMMParams) else model


def trust_model_from_document(doc: Any) -> TrustModel:
    """The model of a document: ``IOHMMParams`` for a ``trustlab-iohmm`` one (exactly as today), ``KStateParams``
    for a ``trustlab-iohmm-k`` one. ``ModelError`` says what is wrong."""
    if not isinstance(doc, dict):
        raise ModelError(f"a model document is a JSON object, got {type(doc).__name__}")
    if doc.get("format") == TWO_STATE_FORMAT:
        return params_from_document(doc)
    if doc.get("format") != K_FORMAT:
        raise ModelError(f"not a trustlab model document (expected \"format\": \"{TWO_STATE_FORMAT}\" or "
                         f"\"{K_FORMAT}\", got {doc.get('format')!r})")
    if doc.get("version") != K_FORMAT_VERSION:
        raise ModelError(f"unsupported {K_FORMAT} version {doc.get('version')!r}; this trustlab reads version "
                         f"{K_FORMAT_VERSION}")
    k = doc.get("n_states")
    if isinstance(k, bool) or not isinstance(k, int) or not MIN_STATES < k <= MAX_STATES:
        raise ModelError(f"n_states of a {K_FORMAT} document must be a whole number {MIN_STATES + 1}…{MAX_STATES}, "
                         f"got {k!r} (a {MIN_STATES}-state model is a \"{TWO_STATE_FORMAT}\" document)")
    if doc.get("states") != state_names(k):
        raise ModelError(f"states must be {state_names(k)} (lowest trust first), got {doc.get('states')!r}")
    if not isinstance(doc.get("params"), dict):
        raise ModelError("model document has no \"params\" object")
    flat = _flatten_exactly(doc["params"], parameter_names(k))
    initial = np.array([_probability(flat[f"initial.state_{j}"], f"initial.state_{j}") for j in range(k)])
    p_rely = np.array([[_probability(flat[_emission_name(c, j)], _emission_name(c, j)) for j in range(k)]
                       for c in Complexity])
    transition = np.full((2, 2, 2, k, k), math.nan)
    for c, a, e, i in product(Complexity, RobotAction, Experience, range(k)):
        names = [_transition_name(c, a, e, i, j) for j in range(k)]
        values = [flat[n] for n in names]
        if all(v is None for v in values):
            continue  # an input the data never exercised
        transition[c.code, a.code, e.code, i] = [_probability(v, n) for v, n in zip(values, names, strict=True)]
        _check_row(transition[c.code, a.code, e.code, i], f"transitions.{c}.{a}.{e}.from_state_{i}")
    _check_row(initial, "initial")
    params = KStateParams(initial, transition, p_rely)
    if not np.array_equal(order_states(params).p_rely, params.p_rely):
        raise ModelError("the states must be listed from the lowest trust to the highest: ascending "
                         "P(rely | high complexity), ties by P(rely | low complexity) (trust_states.order_states)")
    return params


def _flatten_exactly(params: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """The leaves of ``params`` by dotted name; a missing or an unknown name is a ModelError (a typo is not ignored)."""
    flat: dict[str, Any] = {}

    def walk(node: Any, path: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{path}.{key}" if path else str(key))
        else:
            flat[path] = node

    walk(params, "")
    missing = [n for n in names if n not in flat]
    if missing:
        raise ModelError(f"model parameter {missing[0]!r} is missing" + (
            f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    unknown = sorted(set(flat) - set(names))
    if unknown:
        raise ModelError(f"unknown model parameter {unknown[0]!r}" + (
            f" (and {len(unknown) - 1} more)" if len(unknown) > 1 else ""))
    return flat


def _probability(value: Any, name: str) -> float:
    if value is None:
        raise ModelError(f"model parameter {name!r} is null; only a whole transition row may be null")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ModelError(f"model parameter {name!r} must be a number, got {value!r}")
    if not math.isfinite(value) or not 0.0 <= value <= 1.0:
        raise ModelError(f"model parameter {name!r} must be a probability in [0, 1], got {value!r}")
    return float(value)


def _check_row(row: np.ndarray, name: str) -> None:
    if abs(float(row.sum()) - 1.0) > ROW_SUM_TOLERANCE:
        raise ModelError(f"{name} must sum to 1 over the states, got {float(row.sum())!r}")


def load_trust_model_document(path_or_name: str) -> dict[str, Any]:
    """A model JSON file of either format as a checked document; ``paper``: the paper's parameters."""
    return load_model_document(path_or_name, check=trust_model_from_document)


def n_states_of(model: TrustModel) -> int:
    return 2 if isinstance(model, IOHMMParams) else model.n_states
