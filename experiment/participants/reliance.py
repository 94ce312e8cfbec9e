"""A participant who relies on the robot or intervenes as an IOHMM says (SPEC §6).

The hidden trust state starts from the model's initial distribution, chooses rely/intervene with the model's
emission probabilities and moves with its transition probabilities after each trial. The in-process study simulation
(``experiment.simulate``) and the bots (``server.harness.bots``) run it.
"""

from __future__ import annotations

import numpy as np

from experiment.iohmm import IOHMMParams
from experiment.records import TrialRecord
from experiment.task import Complexity, Experience, HumanAction, RobotAction, Trust


class SimulatedHuman:
    """A participant whose behaviour follows an IOHMM."""

    def __init__(self, model: IOHMMParams, rng: np.random.Generator):
        self.model, self.rng = model, rng
        self.trust = Trust.HIGH if rng.random() < model.initial_high else Trust.LOW

    def respond(self, complexity: Complexity, robot_action: RobotAction) -> HumanAction:
        p_intervene = self.model.p_intervene(complexity, robot_action)[self.trust.code]
        return HumanAction.INTERVENE if self.rng.random() < p_intervene else HumanAction.RELY

    def experience(self, record: TrialRecord) -> None:
        self.update(record.complexity, record.robot_action, record.experience)

    def update(self, complexity: Complexity, robot_action: RobotAction, experience: Experience) -> None:
        """Move the hidden trust after a trial with the model's transition probabilities."""
        p_high = self.model.p_high_after(complexity, robot_action, experience)[self.trust.code]
        self.trust = Trust.HIGH if self.rng.random() < p_high else Trust.LOW
