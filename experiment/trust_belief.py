"""The belief a study keeps about a participant's trust, under a model of any number of states (issue 40).

Under the paper's two-state model the belief is a number, P(trust high), exactly as it always was
(``iohmm.update_belief``). Under a model of K ≥ 3 states it is the vector P(T = j), j = 0 … K − 1, kept as a
list of floats so that it is stored in the participant's JSON as it is (the server restores it from there).
Wherever one number is recorded (the trial's ``belief_before``, ``belief_after``, ``policy_belief``, an
answer's ``belief``), it is ``p_highest``: P(the highest trust state), which is P(trust high) at K = 2.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from experiment.iohmm import BeliefUpdate, IOHMMParams, ModelError, update_belief
from experiment.task import Complexity, Experience, HumanAction, RobotAction
from experiment.trust_states import KStateParams
from experiment.trust_states_document import TrustModel

#: P(trust high) under a two-state model; the distribution over the states (lowest trust first) under K ≥ 3.
Belief = float | list[float]


def initial_belief(model: TrustModel) -> Belief:
    """The belief before the first trial."""
    if isinstance(model, IOHMMParams):
        return model.initial_high
    return [float(p) for p in model.initial]


def next_belief(model: TrustModel, belief: Belief, complexity: Complexity, robot_action: RobotAction,
                human_action: HumanAction, experience: Experience, method: BeliefUpdate = "bayes") -> Belief:
    """The belief after a trial: ``iohmm.update_belief`` at K = 2, ``update_belief_k`` at K ≥ 3."""
    if isinstance(model, IOHMMParams):
        return update_belief(model, scalar_belief(belief), complexity, robot_action, human_action, experience, method)
    return [float(p) for p in update_belief_k(model, np.asarray(belief, dtype=float), complexity, robot_action,
                                               human_action, experience, method)]


def update_belief_k(params: KStateParams, belief: np.ndarray, complexity: Complexity, robot_action: RobotAction,
                    human_action: HumanAction, experience: Experience, method: BeliefUpdate = "bayes") -> np.ndarray:
    """One step of ``trust_states.filter_beliefs_k`` from any belief (K,): condition on the human action
    ("bayes"; an action the belief rules out is not conditioned on, so a running study goes on), then apply the
    transition. "paper" applies the transition only, as ``iohmm.update_belief`` does."""
    if method not in ("bayes", "paper"):
        raise ValueError(f"unknown belief update {method!r} (use 'bayes' or 'paper')")
    if robot_action == RobotAction.ASK and human_action == HumanAction.RELY:
        raise ModelError("the robot asked, so the human cannot rely: the human action must be intervene")
    posterior = np.asarray(belief, dtype=float)
    if method == "bayes":  # the arithmetic of filter_beliefs_k (P(o | state) = 1 when the robot asks), bit for bit
        rely = params.p_rely[complexity.code]
        emission = (np.ones(params.n_states) if robot_action == RobotAction.ASK
                    else rely if human_action == HumanAction.RELY else 1.0 - rely)
        joint = posterior * emission
        if joint.sum() > 0:
            posterior = joint / joint.sum()
    matrix = params.transition[complexity.code, robot_action.code, experience.code]  # (K, K)
    used = posterior > 0  # rows without mass may be NaN (inputs the model has no estimate for)
    if np.isnan(matrix[used]).any():
        raise ModelError(f"the model has no transition estimate for {experience} experience after {robot_action} "
                         f"in {complexity} complexity")
    return np.asarray(posterior[used] @ matrix[used])


def p_highest(belief: Belief | Sequence[float]) -> float:
    """P(the highest trust state): the belief itself at K = 2 (P(trust high)), its last entry at K ≥ 3."""
    if isinstance(belief, (int, float)):
        return float(belief)
    return float(belief[-1])


def scalar_belief(belief: Belief) -> float:
    """The two-state belief P(trust high); a vector here is a programming error (a K-state belief given to the
    paper's model)."""
    if not isinstance(belief, (int, float)):
        raise TypeError(f"a two-state model keeps P(trust high), not a vector: {belief!r}")
    return float(belief)
