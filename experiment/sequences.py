"""Trial sequences as the model sees them: integer-coded arrays per participant.

A ``Sequence`` holds, for trials t = 1..T of one participant (practice and
excluded trials removed), the inputs and output of the IOHMM:
complexity C_t, robot action a_t, human action o_t and the experience E_{t+1}
that trial t produced. Codes follow ``experiment.task``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from experiment import defaults
from experiment.iohmm import IOHMMParams
from experiment.task import Complexity, Experience, HumanAction, RobotAction, TaskParams, Trust, resolve_trial


@dataclass(frozen=True)
class Sequence:
    complexity: np.ndarray  # (T,) int: 0 low, 1 high
    robot_action: np.ndarray  # (T,) int: 0 auto, 1 ask
    human_action: np.ndarray  # (T,) int: 0 rely, 1 intervene
    experience: np.ndarray  # (T,) int: E_{t+1}, 0 negative, 1 positive

    def __post_init__(self) -> None:
        arrays = [np.asarray(x, dtype=np.int8)
                  for x in (self.complexity, self.robot_action, self.human_action, self.experience)]
        lengths = {a.shape for a in arrays}
        if len(lengths) != 1 or len(arrays[0].shape) != 1:
            raise ValueError(f"sequence arrays must be 1-D and of equal length, got shapes {sorted(lengths)}")
        if any(((a != 0) & (a != 1)).any() for a in arrays):
            raise ValueError("sequence codes must be 0 or 1")
        if (arrays[1] == RobotAction.ASK.code)[arrays[2] == HumanAction.RELY.code].any():
            raise ValueError("a trial where the robot asked cannot have human action 'rely'")
        for name, array in zip(("complexity", "robot_action", "human_action", "experience"), arrays, strict=True):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    def __len__(self) -> int:
        return int(self.complexity.shape[0])

    def trials(self) -> list[tuple[Complexity, RobotAction, HumanAction, Experience]]:
        """The sequence as enum tuples, the form ``iohmm.filter_beliefs`` takes."""
        return [(Complexity.from_code(c), RobotAction.from_code(a), HumanAction.from_code(o), Experience.from_code(e))
                for c, a, o, e in zip(self.complexity, self.robot_action, self.human_action, self.experience,
                                      strict=True)]


def sample_random_assist_sequences(params: IOHMMParams, n_sequences: int, n_trials: int, rng: np.random.Generator, *,
                                   p_high: float = 0.5, p_ask_low: float = defaults.STUDY1_P_ASK_LOW,
                                   p_ask_high: float = defaults.STUDY1_P_ASK_HIGH,
                                   task: TaskParams = TaskParams()) -> tuple[list[Sequence], list[np.ndarray]]:
    """Draw participants from an IOHMM under a random-assist robot (the study-1 design).

    Returns the sequences and, for each, the true hidden trust codes (T,).
    Complexity is i.i.d. Bernoulli(p_high). Used for parameter-recovery tests
    and benchmarks; full studies are simulated by ``experiment.simulate``.
    """
    sequences, trusts = [], []
    for _ in range(n_sequences):
        rows = np.zeros((4, n_trials), dtype=np.int8)
        trust = np.zeros(n_trials, dtype=np.int8)
        state = Trust.HIGH if rng.random() < params.initial_high else Trust.LOW
        for t in range(n_trials):
            complexity = Complexity.HIGH if rng.random() < p_high else Complexity.LOW
            p_ask = p_ask_high if complexity == Complexity.HIGH else p_ask_low
            robot_action = RobotAction.ASK if rng.random() < p_ask else RobotAction.AUTO
            p_int = params.p_intervene(complexity, robot_action)[state.code]
            human_action = HumanAction.INTERVENE if rng.random() < p_int else HumanAction.RELY
            result = resolve_trial(complexity, robot_action, human_action, rng.random() < task.p_success(complexity),
                                   task)
            trust[t] = state.code
            rows[:, t] = (complexity.code, robot_action.code, human_action.code, result.experience.code)
            p_next = params.p_high_after(complexity, robot_action, result.experience)[state.code]
            state = Trust.HIGH if rng.random() < p_next else Trust.LOW
        sequences.append(Sequence(*rows))
        trusts.append(trust)
    return sequences, trusts
