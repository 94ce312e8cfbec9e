"""A participant who relies on the robot or intervenes as an IOHMM says (SPEC §6).

The hidden trust state starts from the model's initial distribution, chooses rely/intervene with the model's
emission probabilities and moves with its transition probabilities after each trial. The in-process study simulation
(``experiment.simulate``) and the bots (``server.harness.bots``) run it. A model of 3 or 4 trust states
(``KStateHuman``) draws the same way from its K states; ``simulated_human`` picks the class of a model.
"""

from __future__ import annotations

import numpy as np

from experiment.iohmm import IOHMMParams, ModelError
from experiment.records import TrialRecord
from experiment.task import Complexity, Experience, HumanAction, RobotAction, Trust
from experiment.trust_states import KStateParams


class SimulatedHuman:
    """A participant whose behaviour follows an IOHMM."""

    def __init__(self, model: IOHMMParams, rng: np.random.Generator):
        self.model, self.rng = model, rng
        self.trust = Trust.HIGH if rng.random() < model.initial_high else Trust.LOW

    @property
    def state_index(self) -> int:
        """The hidden state's index as a two-state model document orders them: 0 low trust, 1 high."""
        return self.trust.code

    def respond(self, complexity: Complexity, robot_action: RobotAction) -> HumanAction:
        p_intervene = self.model.p_intervene(complexity, robot_action)[self.trust.code]
        return HumanAction.INTERVENE if self.rng.random() < p_intervene else HumanAction.RELY

    def experience(self, record: TrialRecord) -> None:
        self.update(record.complexity, record.robot_action, record.experience)

    def update(self, complexity: Complexity, robot_action: RobotAction, experience: Experience) -> None:
        """Move the hidden trust after a trial with the model's transition probabilities."""
        p_high = self.model.p_high_after(complexity, robot_action, experience)[self.trust.code]
        self.trust = Trust.HIGH if self.rng.random() < p_high else Trust.LOW


class KStateHuman:
    """A participant whose behaviour follows a model of K trust states (states 0 … K − 1, lowest to highest)."""

    def __init__(self, model: KStateParams, rng: np.random.Generator):
        self.model, self.rng = model, rng
        self.state = self._draw(model.initial)

    def _draw(self, probabilities: np.ndarray) -> int:
        return min(int(np.searchsorted(np.cumsum(probabilities), self.rng.random(), side="right")),
                   self.model.n_states - 1)

    @property
    def state_index(self) -> int:
        """The hidden state's index in the model's order (lowest reliance first)."""
        return self.state

    def respond(self, complexity: Complexity, robot_action: RobotAction) -> HumanAction:
        if robot_action == RobotAction.ASK:
            return HumanAction.INTERVENE  # asked: the person takes over (as the two-state model's P(intervene) = 1)
        p_rely = self.model.p_rely[complexity.code, self.state]
        return HumanAction.RELY if self.rng.random() < p_rely else HumanAction.INTERVENE

    def experience(self, record: TrialRecord) -> None:
        self.update(record.complexity, record.robot_action, record.experience)

    def update(self, complexity: Complexity, robot_action: RobotAction, experience: Experience) -> None:
        """Move the hidden trust after a trial with the model's transition row."""
        row = self.model.transition[complexity.code, robot_action.code, experience.code, self.state]
        if np.isnan(row).any():
            raise ModelError(f"the model has no transition estimate for {complexity} complexity, {robot_action}, "
                             f"{experience} experience (its data never showed it), which this design produces")
        self.state = self._draw(row)


def simulated_human(model: IOHMMParams | KStateParams, rng: np.random.Generator) -> SimulatedHuman | KStateHuman:
    """The simulated participant of a model: the paper's two-state one, or one of K states."""
    return SimulatedHuman(model, rng) if isinstance(model, IOHMMParams) else KStateHuman(model, rng)
