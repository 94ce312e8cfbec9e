"""The trust IOHMM with K hidden trust states (issue 40): parameters, state order, filter and likelihood.

The paper's model (``experiment.iohmm``) has two trust states. Here trust takes K = 2…4 values with the same
inputs and output (paper §3.2): complexity C_t and robot action a_t act on the emission and the transition,
the experience E_{t+1} on the transition; the output is the human action o_t. Shapes:

- ``initial`` (K,): P(T_1 = j).
- ``transition`` (C=2, A=2, E=2, K, K): P(T_{t+1} = j | T_t = i, E_{t+1}, C_t, a_t) at ``[c, a, e, i, j]``; rows
  of input combinations that cannot occur (paper §4.2) may be NaN.
- ``p_rely`` (C=2, K): P(o_t = rely | T_t, C_t, a_t = auto); when the robot asks the human always assists.

States are labelled by ``order_states``: ascending P(rely | high complexity) (then low complexity), so that state 0
is the lowest trust and a relabelled model gets the same labels. At K = 2, state 0 is the paper's "low" and state 1
its "high" (``from_iohmm`` / ``to_iohmm``). Codes follow ``experiment.task``. The fast K = 2 fit of
``experiment.fit`` stays the production path; this module favours clarity.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from experiment import defaults
from experiment.iohmm import IOHMMParams, ModelError
from experiment.sequences import Sequence
from experiment.task import Complexity, HumanAction, RobotAction, TaskParams, resolve_trial

MIN_STATES, MAX_STATES = defaults.STATES_MIN, defaults.STATES_MAX
N_INPUTS = 8  # transition input k = (c·2 + a)·2 + e, as in experiment.iohmm


@dataclass(frozen=True)
class KStateParams:
    initial: np.ndarray = field(repr=False)  # (K,)
    transition: np.ndarray = field(repr=False)  # (2, 2, 2, K, K)
    p_rely: np.ndarray = field(repr=False)  # (2, K)

    def __post_init__(self) -> None:
        initial = np.array(self.initial, dtype=float)
        k = initial.shape[0] if initial.ndim == 1 else 0
        if not MIN_STATES <= k <= MAX_STATES:
            raise ModelError(f"the number of trust states must be {MIN_STATES}…{MAX_STATES}, got shape {initial.shape}")
        transition = np.array(self.transition, dtype=float).reshape(2, 2, 2, k, k)
        p_rely = np.array(self.p_rely, dtype=float).reshape(2, k)
        if np.isnan(initial).any() or np.isnan(p_rely).any():
            raise ModelError("the initial distribution and the emissions must be estimated (no NaN)")
        for name, rows in (("initial", initial[None]), ("transition", transition.reshape(-1, k))):
            known = rows[~np.isnan(rows).any(axis=1)]
            if (known < 0).any() or not np.allclose(known.sum(axis=1), 1.0, atol=1e-9):
                raise ModelError(f"{name} rows must be probability distributions")
        if ((p_rely < 0) | (p_rely > 1)).any():
            raise ModelError("p_rely outside [0, 1]")
        for name, array in (("initial", initial), ("transition", transition), ("p_rely", p_rely)):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def n_states(self) -> int:
        return int(self.initial.shape[0])

    def permuted(self, order: np.ndarray) -> KStateParams:
        """The same model with new state j = old state order[j]."""
        order = np.asarray(order)
        return KStateParams(self.initial[order], self.transition[..., order, :][..., order], self.p_rely[:, order])


def state_order(params: KStateParams) -> np.ndarray:
    """The states by ascending P(rely | high complexity), ties by P(rely | low complexity)."""
    return np.lexsort((params.p_rely[0], params.p_rely[1]))


def order_states(params: KStateParams) -> KStateParams:
    """Relabel states by ascending P(rely | high complexity), ties by P(rely | low complexity)."""
    return params.permuted(state_order(params))


# -- the paper's two-state model -----------------------------------------------

def from_iohmm(params: IOHMMParams) -> KStateParams:
    """K = 2 form of the paper's model: state 0 = low trust, 1 = high trust (not reordered)."""
    up = params.p_high_next  # (C, A, E, T)
    return KStateParams(np.array([1.0 - params.initial_high, params.initial_high]),
                        np.stack([1.0 - up, up], axis=-1), params.p_rely)


def to_iohmm(params: KStateParams) -> IOHMMParams:
    """The paper's parameters of a K = 2 model (state 1 is high trust)."""
    if params.n_states != 2:
        raise ModelError(f"only a 2-state model has the paper's form, this one has {params.n_states} states")
    return IOHMMParams(float(params.initial[1]), params.transition[..., 1], params.p_rely)


# -- per-trial probabilities ---------------------------------------------------

def emission_probabilities(params: KStateParams, seq: Sequence) -> np.ndarray:
    """(T, K) P(o_t | T_t = j, C_t, a_t): 1 when the robot asked (the human always assists)."""
    rely = params.p_rely[seq.complexity.astype(int)]  # (T, K)
    p = np.where((seq.human_action == 0)[:, None], rely, 1.0 - rely)
    return np.where((seq.robot_action == 1)[:, None], 1.0, p)


def transition_inputs(seq: Sequence) -> np.ndarray:
    """(T,) input code k = (c·2 + a)·2 + e of the transition after each trial."""
    return (seq.complexity.astype(int) * 2 + seq.robot_action) * 2 + seq.experience


def transition_matrices(params: KStateParams, seq: Sequence) -> np.ndarray:
    """(T, K, K) transition after each trial; a NaN row the filter needs is a ModelError."""
    return params.transition.reshape(N_INPUTS, params.n_states, params.n_states)[transition_inputs(seq)]


def _step(matrix: np.ndarray, belief: np.ndarray) -> np.ndarray:
    """belief @ matrix, where rows the belief gives no mass may be NaN (inputs the model has no estimate for)."""
    used = belief > 0
    if np.isnan(matrix[used]).any():
        raise ModelError("the model has no transition estimate for an input combination in the data")
    return np.asarray(belief[used] @ matrix[used])


# -- filter and likelihood -----------------------------------------------------

def filter_beliefs_k(params: KStateParams, seq: Sequence) -> np.ndarray:
    """(T + 1, K) beliefs P(T | history) before the first trial and after each one (the exact Bayes filter).

    As ``iohmm.update_belief`` with ``bayes``: condition on o_t, then apply the transition; an action the belief
    rules out (probability 0) is not conditioned on, so that a running study goes on.
    """
    emissions, matrices = emission_probabilities(params, seq), transition_matrices(params, seq)
    beliefs = [params.initial]
    for t in range(len(seq)):
        joint = beliefs[-1] * emissions[t]
        posterior = joint / joint.sum() if joint.sum() > 0 else beliefs[-1]
        beliefs.append(_step(matrices[t], posterior))
    return np.array(beliefs)


def sequence_log_likelihood(params: KStateParams, seq: Sequence) -> float:
    """log P(o_1..T | inputs) by the scaled forward pass (−inf if the model rules an observation out)."""
    emissions, matrices = emission_probabilities(params, seq), transition_matrices(params, seq)
    belief, total = params.initial, 0.0
    for t in range(len(seq)):
        joint = belief * emissions[t]
        scale = float(joint.sum())
        if scale <= 0.0:
            return -math.inf
        total += math.log(scale)
        if t < len(seq) - 1:
            belief = _step(matrices[t], joint / scale)
    return total


def log_likelihood_k(params: KStateParams, sequences: list[Sequence]) -> float:
    """Total log-likelihood of the sequences."""
    return float(sum(sequence_log_likelihood(params, s) for s in sequences if len(s)))


# -- simulation ----------------------------------------------------------------

def illustrative_three_state_model() -> KStateParams:
    """A three-state model for selection and recovery checks (not the paper's; no study has fitted it).

    Three levels told apart by reliance in high complexity (5 %, 50 %, 95 %); trust mostly stays (≈ 0.84), moves
    up after a positive experience and down after a negative one.
    """
    transition = np.zeros((2, 2, 2, 3, 3))
    for e, i in itertools.product(range(2), range(3)):
        row = np.full(3, 0.02) + 0.8 * np.eye(3)[i]
        row[min(i + 1, 2) if e else max(i - 1, 0)] += 0.14
        transition[:, :, e, i] = row / row.sum()
    return KStateParams(np.array([0.2, 0.3, 0.5]), transition, np.array([[0.6, 0.95, 0.99], [0.05, 0.5, 0.95]]))


def sample_sequences_k(params: KStateParams, n_sequences: int, n_trials: int, rng: np.random.Generator, *,
                       p_high: float = 0.5, p_ask_low: float = defaults.STUDY1_P_ASK_LOW,
                       p_ask_high: float = defaults.STUDY1_P_ASK_HIGH,
                       task: TaskParams = TaskParams()) -> tuple[list[Sequence], list[np.ndarray]]:
    """Participants of a K-state model under a random-assist robot (as ``sequences.sample_random_assist_sequences``).

    Returns the sequences and, for each, the true hidden state codes (T,).
    """
    sequences, states = [], []
    for _ in range(n_sequences):
        rows, path = np.zeros((4, n_trials), dtype=np.int8), np.zeros(n_trials, dtype=np.int8)
        state = int(rng.choice(params.n_states, p=params.initial))
        for t in range(n_trials):
            complexity = Complexity.HIGH if rng.random() < p_high else Complexity.LOW
            p_ask = p_ask_high if complexity == Complexity.HIGH else p_ask_low
            action = RobotAction.ASK if rng.random() < p_ask else RobotAction.AUTO
            p_rely = 0.0 if action == RobotAction.ASK else params.p_rely[complexity.code, state]
            human = HumanAction.RELY if rng.random() < p_rely else HumanAction.INTERVENE
            result = resolve_trial(complexity, action, human, rng.random() < task.p_success(complexity), task)
            path[t], rows[:, t] = state, (complexity.code, action.code, human.code, result.experience.code)
            row = params.transition[complexity.code, action.code, result.experience.code, state]
            state = int(rng.choice(params.n_states, p=row))
        sequences.append(Sequence(*rows))
        states.append(path)
    return sequences, states
