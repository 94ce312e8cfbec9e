"""One trial of the object-collection task (paper §2): outcome, experience, reward.

The categorical variables are string enums whose values are exactly the
``trials.csv`` values of SPEC §9. Each has a fixed integer code (its position
in the enum), used to index the model's parameter arrays.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Self

from pydantic import BaseModel, ConfigDict, Field

from experiment import defaults


class _Coded(StrEnum):
    @property
    def code(self) -> int:
        """The integer index of this value in parameter arrays."""
        return _CODES[type(self)][self]

    @classmethod
    def from_code(cls, code: int) -> Self:
        return list(cls)[code]


class Complexity(_Coded):
    LOW = "low"
    HIGH = "high"


class RobotAction(_Coded):
    AUTO = "auto"  # a+: attempt autonomously
    ASK = "ask"  # a-: ask the human for help


class HumanAction(_Coded):
    RELY = "rely"  # o+
    INTERVENE = "intervene"  # o-: teleoperate (also the answer to "ask")


class Experience(_Coded):
    NEGATIVE = "negative"  # E-
    POSITIVE = "positive"  # E+


class Trust(_Coded):
    LOW = "low"
    HIGH = "high"


class Outcome(StrEnum):
    """Outcome of an autonomous attempt; ``none`` when the robot did not attempt."""

    SUCCESS = "success"
    FAILURE = "failure"
    NONE = "none"


_CODES: dict[type[_Coded], dict[_Coded, int]] = {cls: {member: i for i, member in enumerate(cls)}
                                                  for cls in (Complexity, RobotAction, HumanAction, Experience, Trust)}


#: The largest reward (in points, either sign) a trial may give: far past any study's, small enough that the policy's
#: value iteration cannot overflow.
MAX_REWARD = 1e6


class RewardTable(BaseModel):
    """Reward R^a_{o,E} of one trial (paper eq. 1)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    auto_rely_success: float = Field(defaults.REWARD_AUTO_RELY_SUCCESS, ge=-MAX_REWARD, le=MAX_REWARD,
                                     title="Robot alone, relied on, succeeded",
                                     description=(
        "Points when the robot tried alone, the participant relied on it and it succeeded"))
    auto_rely_failure: float = Field(defaults.REWARD_AUTO_RELY_FAILURE, ge=-MAX_REWARD, le=MAX_REWARD,
                                     title="Robot alone, relied on, failed",
                                     description=(
        "Points when the robot tried alone, the participant relied on it and it failed"))
    auto_intervene: float = Field(defaults.REWARD_AUTO_INTERVENE, ge=-MAX_REWARD, le=MAX_REWARD,
                                  title="Robot alone, participant intervened",
                                  description=(
        "Points when the robot tried alone and the participant intervened"))
    ask: float = Field(defaults.REWARD_ASK, ge=-MAX_REWARD, le=MAX_REWARD, title="Robot asked for help",
                       description="Points when the robot asked for help")

    @property
    def gives_points(self) -> bool:
        """Whether any outcome scores (all zero: the study does not play for points)."""
        return any(points != 0 for points in (self.auto_rely_success, self.auto_rely_failure, self.auto_intervene,
                                              self.ask))


class ExperienceRule(BaseModel):
    """Experience E_{t+1} for the cases that do not depend on the outcome (paper §2).

    An autonomous attempt the human relied on gives E+ on success and E- on
    failure; those two are fixed by the definition of experience.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    auto_intervene: Experience = Field(Experience.NEGATIVE, title="After an intervention",
                                       description="Experience after an intervention")
    ask_low: Experience = Field(Experience.NEGATIVE, title="After asking in low complexity",
                                description="Experience after the robot asked in low complexity")
    ask_high: Experience = Field(Experience.POSITIVE, title="After asking in high complexity",
                                 description="Experience after the robot asked in high complexity")


class TaskParams(BaseModel):
    """Everything that turns (complexity, robot action, human action) into a result."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    p_success_low: float = Field(defaults.P_SUCCESS_LOW, ge=0.0, le=1.0, title="P(success), low complexity",
                                 description=(
        "Probability that the robot's autonomous attempt succeeds in low complexity"))
    p_success_high: float = Field(defaults.P_SUCCESS_HIGH, ge=0.0, le=1.0, title="P(success), high complexity",
                                  description=(
        "Probability that the robot's autonomous attempt succeeds in high complexity"))
    rewards: RewardTable = Field(RewardTable(), title="Rewards (points)",
                                 description="Points per trial outcome (paper eq. 1)")
    experience_rule: ExperienceRule = Field(ExperienceRule(), description=(
        "Experience after the trials whose outcome does not decide it"))

    def p_success(self, complexity: Complexity) -> float:
        return self.p_success_high if complexity == Complexity.HIGH else self.p_success_low


class TrialResult(BaseModel):
    model_config = ConfigDict(frozen=True)

    outcome: Outcome
    experience: Experience
    reward: float


def outcome_of(robot_action: RobotAction, human_action: HumanAction, autonomous_success: bool) -> Outcome:
    """Only an autonomous attempt the human relied on has an outcome."""
    if robot_action == RobotAction.AUTO and human_action == HumanAction.RELY:
        return Outcome.SUCCESS if autonomous_success else Outcome.FAILURE
    return Outcome.NONE


def experience_of(complexity: Complexity, robot_action: RobotAction, human_action: HumanAction,
                  outcome: Outcome, rule: ExperienceRule = ExperienceRule()) -> Experience:
    """E_{t+1} from the trial (paper §2; the failure case is E-, SPEC §11)."""
    if robot_action == RobotAction.ASK:
        return rule.ask_high if complexity == Complexity.HIGH else rule.ask_low
    if human_action == HumanAction.INTERVENE:
        return rule.auto_intervene
    if outcome == Outcome.NONE:
        raise ValueError("an autonomous attempt the human relied on needs an outcome")
    return Experience.POSITIVE if outcome == Outcome.SUCCESS else Experience.NEGATIVE


def reward_of(robot_action: RobotAction, human_action: HumanAction, outcome: Outcome,
              table: RewardTable = RewardTable()) -> float:
    """R^a_{o,E} of eq. (1)."""
    if robot_action == RobotAction.ASK:
        return table.ask
    if human_action == HumanAction.INTERVENE:
        return table.auto_intervene
    return table.auto_rely_success if outcome == Outcome.SUCCESS else table.auto_rely_failure


def resolve_trial(complexity: Complexity, robot_action: RobotAction, human_action: HumanAction,
                  autonomous_success: bool, params: TaskParams = TaskParams()) -> TrialResult:
    """Outcome, experience and reward of one trial.

    ``autonomous_success`` is the draw of the trial's seeded outcome stream; it
    is ignored unless the robot attempted and the human relied.
    """
    if robot_action == RobotAction.ASK and human_action != HumanAction.INTERVENE:
        raise ValueError("when the robot asks, the human always assists (intervene)")
    outcome = outcome_of(robot_action, human_action, autonomous_success)
    return TrialResult(
        outcome=outcome,
        experience=experience_of(complexity, robot_action, human_action, outcome, params.experience_rule),
        reward=reward_of(robot_action, human_action, outcome, params.rewards),
    )


def p_positive_experience(complexity: Complexity, robot_action: RobotAction, human_action: HumanAction,
                          params: TaskParams = TaskParams()) -> float:
    """P(E_{t+1} = E+ | o_t, C_t, a_t) (paper §3.3)."""
    if robot_action == RobotAction.AUTO and human_action == HumanAction.RELY:
        return params.p_success(complexity)
    outcome = Outcome.NONE
    return float(experience_of(complexity, robot_action, human_action, outcome,
                               params.experience_rule) == Experience.POSITIVE)


def expected_reward_given_action(complexity: Complexity, robot_action: RobotAction, human_action: HumanAction,
                                 params: TaskParams = TaskParams()) -> float:
    """E[R | C, a, o], averaging over the autonomous outcome."""
    if robot_action == RobotAction.AUTO and human_action == HumanAction.RELY:
        p = params.p_success(complexity)
        return p * params.rewards.auto_rely_success + (1 - p) * params.rewards.auto_rely_failure
    return reward_of(robot_action, human_action, Outcome.NONE, params.rewards)
