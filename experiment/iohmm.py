"""The trust IOHMM: parameters, their JSON form, and the belief filter (paper §3.2, §3.4).

Hidden trust T ∈ {low, high}. Inputs: complexity C_t and robot action a_t on
both the emission and the transition, and the experience E_{t+1} on the
transition. Output: the human action o_t.

Parameters (all Bernoulli probabilities, NaN where not estimated):

- ``initial_high``: P(T_1 = high).
- ``p_high_next``, shape (C=2, A=2, E=2, T=2): P(T_{t+1} = high | T_t, E_{t+1}, C_t, a_t).
- ``p_rely``, shape (C=2, T=2): P(o_t = rely | T_t, C_t, a_t = auto). When the
  robot asks, the human always assists: P(o = intervene | ask) = 1, a
  structural fact, not a parameter.

Axis order and codes follow ``experiment.task`` (low/auto/negative = 0).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import product
from typing import Any, Literal

import numpy as np

from experiment import defaults
from experiment.task import Complexity, Experience, HumanAction, RobotAction, Trust

FORMAT = "trustlab-iohmm"
FORMAT_VERSION = 1

BeliefUpdate = Literal["bayes", "paper"]

#: Names of the free parameters, in the order of ``IOHMMParams.to_vector``.
TRANSITION_KEYS = [(c, a, e, t) for c, a, e, t in product(Complexity, RobotAction, Experience, Trust)]
EMISSION_KEYS = [(c, t) for c, t in product(Complexity, Trust)]
PARAMETER_NAMES = (
    ["initial.p_high"]
    + [f"transitions.{c}.{a}.{e}.from_{t}" for c, a, e, t in TRANSITION_KEYS]
    + [f"emissions.{c}.auto.p_rely_{t}" for c, t in EMISSION_KEYS]
)
N_PARAMETERS = len(PARAMETER_NAMES)  # 1 + 16 + 4 = 21

# -- layout of the parameter vector --------------------------------------------
# Three blocks, each in C order of its array's axes (codes as in ``experiment.task``):
# - ``INITIAL``: P(T_1 = high);
# - ``TRANSITIONS``: ``p_high_next`` over (C, A, E, T_t); transition input k = (c·2 + a)·2 + e
#   (k < N_TRANSITION_INPUTS) from state s sits at TRANSITIONS.start + 2k + s;
# - ``EMISSIONS``: ``p_rely`` over (C, T); complexity c, state s at EMISSIONS.start + 2c + s.
# ``TRANSITIONS_FROM[s]``: the transitions out of state s (low = 0, high = 1), by input k;
# ``EMISSIONS_OF[s]``: P(rely | s, C, auto), by complexity c.
INITIAL = 0
TRANSITIONS = slice(INITIAL + 1, INITIAL + 1 + len(TRANSITION_KEYS))
EMISSIONS = slice(TRANSITIONS.stop, TRANSITIONS.stop + len(EMISSION_KEYS))
N_TRANSITION_INPUTS = len(TRANSITION_KEYS) // len(Trust)  # 8 combinations (C, A, E)
TRANSITIONS_FROM = tuple(slice(TRANSITIONS.start + s, TRANSITIONS.stop, len(Trust)) for s in range(len(Trust)))
EMISSIONS_OF = tuple(slice(EMISSIONS.start + s, EMISSIONS.stop, len(Trust)) for s in range(len(Trust)))


def _state_swap() -> tuple[np.ndarray, np.ndarray]:
    order, complement = np.arange(N_PARAMETERS), np.zeros(N_PARAMETERS, dtype=bool)
    for block in (TRANSITIONS, EMISSIONS):
        order[block] = order[block].reshape(-1, len(Trust))[:, ::-1].ravel()
    complement[INITIAL] = complement[TRANSITIONS] = True
    order.setflags(write=False)
    complement.setflags(write=False)
    return order, complement


#: Label switching: exchanging low and high trust gives the same model (same likelihood) with the
#: vector ``swap_states(v)``: entry i is v[STATE_SWAP[i]], complemented (1 − ·) where
#: STATE_SWAP_COMPLEMENTS[i]: P(T_1 = high) -> 1 − P(T_1 = high); P(high | from s) -> 1 − P(high | from
#: the other state); P(rely | s) -> P(rely | the other state).
STATE_SWAP, STATE_SWAP_COMPLEMENTS = _state_swap()


def swap_states(vector: np.ndarray) -> np.ndarray:
    """The same model with low and high trust exchanged; vector (..., P)."""
    swapped = vector[..., STATE_SWAP]
    return np.where(STATE_SWAP_COMPLEMENTS, 1.0 - swapped, swapped)


class ModelError(ValueError):
    """A model document or parameter set that cannot be used."""


@dataclass(frozen=True)
class IOHMMParams:
    initial_high: float
    p_high_next: np.ndarray = field(repr=False)  # (2, 2, 2, 2)
    p_rely: np.ndarray = field(repr=False)  # (2, 2)

    def __post_init__(self) -> None:
        object.__setattr__(self, "p_high_next", np.array(self.p_high_next, dtype=float).reshape(2, 2, 2, 2))
        object.__setattr__(self, "p_rely", np.array(self.p_rely, dtype=float).reshape(2, 2))
        vector = self.to_vector()
        bad = [n for n, v in zip(PARAMETER_NAMES, vector, strict=True) if not math.isnan(v) and not 0.0 <= v <= 1.0]
        if bad:
            raise ModelError(f"probabilities outside [0, 1]: {', '.join(bad)}")
        if math.isnan(self.initial_high):
            raise ModelError("initial.p_high is required")
        self.p_high_next.setflags(write=False)
        self.p_rely.setflags(write=False)

    # -- vector form, used by fitting and standard errors ---------------------
    def to_vector(self) -> np.ndarray:
        """(21,) in the order of ``PARAMETER_NAMES``."""
        return np.concatenate([[self.initial_high], self.p_high_next.ravel(), self.p_rely.ravel()])

    @classmethod
    def from_vector(cls, vector: np.ndarray) -> IOHMMParams:
        vector = np.asarray(vector, dtype=float)
        if vector.shape != (N_PARAMETERS,):
            raise ModelError(f"expected {N_PARAMETERS} parameters, got shape {vector.shape}")
        return cls(float(vector[INITIAL]), vector[TRANSITIONS], vector[EMISSIONS])

    # -- probabilities --------------------------------------------------------
    def p_intervene(self, complexity: Complexity, robot_action: RobotAction) -> np.ndarray:
        """P(o = intervene | T, C, a) for T = (low, high), shape (2,)."""
        if robot_action == RobotAction.ASK:
            return np.ones(2)
        return 1.0 - self.p_rely[complexity.code]

    def p_observation(self, complexity: Complexity, robot_action: RobotAction, human_action: HumanAction) -> np.ndarray:
        """P(o | T, C, a) for T = (low, high), shape (2,)."""
        if human_action == HumanAction.INTERVENE:
            return self.p_intervene(complexity, robot_action)
        return np.zeros(2) if robot_action == RobotAction.ASK else self.p_rely[complexity.code].copy()

    def p_high_after(self, complexity: Complexity, robot_action: RobotAction, experience: Experience) -> np.ndarray:
        """P(T_{t+1} = high | T_t, E, C, a) for T_t = (low, high), shape (2,)."""
        return self.p_high_next[complexity.code, robot_action.code, experience.code]

    # -- JSON -----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return nest(dict(zip(PARAMETER_NAMES, self.to_vector().tolist(), strict=True)))

    @classmethod
    def from_dict(cls, params: dict[str, Any]) -> IOHMMParams:
        return cls.from_vector(np.array([_number(v, n) for n, v in flatten(params).items()]))


def nest(flat: dict[str, Any]) -> dict[str, Any]:
    """``{"a.b.c": x}`` -> ``{"a": {"b": {"c": x}}}``; NaN becomes ``None`` (JSON null)."""
    out: dict[str, Any] = {}
    for name, value in flat.items():
        *path, leaf = name.split(".")
        node = out
        for key in path:
            node = node.setdefault(key, {})
        node[leaf] = None if isinstance(value, float) and math.isnan(value) else value
    return out


def flatten(nested: dict[str, Any]) -> dict[str, Any]:
    """Inverse of ``nest`` over ``PARAMETER_NAMES``; a missing name is a ModelError."""
    flat = {}
    for name in PARAMETER_NAMES:
        node: Any = nested
        for key in name.split("."):
            if not isinstance(node, dict) or key not in node:
                raise ModelError(f"model parameter {name!r} is missing")
            node = node[key]
        flat[name] = node
    return flat


def _number(value: Any, name: str) -> float:
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ModelError(f"model parameter {name!r} must be a number or null, got {value!r}")
    return float(value)


def model_document(params: IOHMMParams, **extra: Any) -> dict[str, Any]:
    """The versioned model JSON of SPEC §9 (fit results go in ``extra``)."""
    return {"format": FORMAT, "version": FORMAT_VERSION, "states": [t.value for t in Trust],
            "params": params.to_dict(), **extra}


def params_from_document(doc: Any) -> IOHMMParams:
    if isinstance(doc, dict) and isinstance(doc.get("n_states"), int) and doc.get("format") != FORMAT:
        raise ModelError(f"this is a model of {doc['n_states']} trust states; here only the paper's two-state model "
                         f"(\"format\": \"{FORMAT}\") can be used")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ModelError(f"not a trustlab model document (expected \"format\": \"{FORMAT}\")")
    if doc.get("version") != FORMAT_VERSION:
        raise ModelError(f"unsupported model version {doc.get('version')!r}; this trustlab reads version "
                         f"{FORMAT_VERSION}")
    if not isinstance(doc.get("params"), dict):
        raise ModelError("model document has no \"params\" object")
    return IOHMMParams.from_dict(doc["params"])


def load_model(path_or_name: str) -> IOHMMParams:
    """Read a model JSON file; the word ``paper`` gives the paper's parameters."""
    if path_or_name == "paper":
        return paper_params()
    return params_from_document(load_model_document(path_or_name))


def load_model_document(path_or_name: str, check: Callable[[Any], object] = params_from_document) -> dict[str, Any]:
    """A model JSON file as a document ``check`` accepts (it raises otherwise; default: a two-state model);
    ``paper``: the paper's parameters as a document."""
    if path_or_name == "paper":
        return model_document(paper_params())
    doc = read_model_json(path_or_name)
    check(doc)
    return doc


def read_model_json(path: str) -> Any:
    """The JSON of a model file, unchecked; a missing or unreadable file is a ModelError."""
    try:
        with open(path, encoding="utf-8") as handle:
            return json.load(handle)
    except FileNotFoundError:
        raise ModelError(f"model file not found: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelError(f"model file {path} is not valid JSON: {exc}") from None


def paper_params() -> IOHMMParams:
    """The estimates printed in the paper (§4.1–4.2); unestimable slots are NaN."""
    p_high_next = np.full((2, 2, 2, 2), np.nan)
    for (c, a, e, t), value in defaults.PAPER_P_HIGH_NEXT.items():
        p_high_next[Complexity(c).code, RobotAction(a).code, Experience(e).code, Trust(t).code] = value
    p_rely = np.zeros((2, 2))
    for (c, t), value in defaults.PAPER_P_RELY.items():
        p_rely[Complexity(c).code, Trust(t).code] = value
    return IOHMMParams(defaults.PAPER_INITIAL_HIGH, p_high_next, p_rely)


# -- belief filter -------------------------------------------------------------

def update_belief(params: IOHMMParams, belief_high: float, complexity: Complexity, robot_action: RobotAction,
                  human_action: HumanAction, experience: Experience, method: BeliefUpdate = "bayes") -> float:
    """P(T_{t+1} = high | history up to trial t) from P(T_t = high | history before t).

    ``bayes`` (default) is the exact filter: it first conditions the belief on
    the observed human action o_t (Bayes' rule with the emission probabilities)
    and then applies the transition. ``paper`` is eq. (belief-update) of the
    paper, which applies the transition only and ignores o_t; a rely or an
    intervention then tells the robot nothing about trust, which is why it is
    not the default. When the robot asks, o_t carries no information (the
    human always assists), so both agree.

    A fitted model with estimates on the boundary of [0, 1] can give an
    observed human action probability 0 at the current belief (e.g. belief 1
    and P(intervene | high trust) = 0). The data then contradict the model and
    Bayes' rule is undefined; ``bayes`` does not condition on that trial's
    action (it updates as ``paper`` does), so that a running study goes on.
    """
    prior = np.array([1.0 - belief_high, belief_high])
    if method == "bayes":
        joint = prior * params.p_observation(complexity, robot_action, human_action)
        total = joint.sum()
        if robot_action == RobotAction.ASK and human_action == HumanAction.RELY:
            raise ModelError("the robot asked, so the human cannot rely: the human action must be intervene")
        if total > 0.0:
            prior = joint / total
    elif method != "paper":
        raise ValueError(f"unknown belief update {method!r} (use 'bayes' or 'paper')")
    p_next = params.p_high_after(complexity, robot_action, experience)
    weighted = prior * p_next
    if np.isnan(p_next[prior > 0]).any():
        raise ModelError(f"the model has no transition estimate for {experience} experience after "
                         f"{robot_action} in {complexity} complexity")
    return float(np.clip(np.nansum(weighted), 0.0, 1.0))


def filter_beliefs(params: IOHMMParams, trials: list[tuple[Complexity, RobotAction, HumanAction, Experience]],
                   method: BeliefUpdate = "bayes") -> np.ndarray:
    """Beliefs P(T = high) before the first trial and after each one, shape (len(trials) + 1,)."""
    beliefs = [params.initial_high]
    for complexity, robot_action, human_action, experience in trials:
        beliefs.append(update_belief(params, beliefs[-1], complexity, robot_action, human_action, experience, method))
    return np.array(beliefs)
