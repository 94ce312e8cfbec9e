"""The participant's path through a study, as a pure step machine.

consent → instructions → practice trials → "practice is over" (when there was
a practice) → questionnaires before → for each block in the participant's
order: trials, with the shelf survey after each shelf's last trial, then that
block's questionnaires → the questionnaires at the end of the study → debrief.

A ``Step`` is one of the small frozen models below, told apart by its
``phase``; it is stored with the participant (and shown to the page) as its
``model_dump()``, a small JSON dict, and read back with ``parse_step``. The
server moves a participant only with ``next_step`` and only when the current
step's work is recorded, so ``GET`` of the state can always say what to show.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

from experiment.config import StudyConfig
from experiment.schedule import shelves


class ParticipantStatus(StrEnum):
    ACTIVE = "active"
    COMPLETED = "completed"  # reached the debrief
    DECLINED = "declined"  # did not consent
    ABANDONED = "abandoned"  # idle past the timeout
    WITHDRAWN = "withdrawn"  # by the participant (their page) or the researcher (server.services.withdrawal)
    SCREENED_OUT = "screened_out"  # an eligibility question, or failed attention checks (experiment.attention)


#: A session in one of these statuses records nothing more.
TERMINAL_STATUSES = frozenset(ParticipantStatus) - {ParticipantStatus.ACTIVE}


class TrialStage(StrEnum):
    """Where a started trial is (``Trial.stage``)."""

    PRESENTING = "presenting"  # the robot will try: waiting for the page to show the scene
    DECISION = "decision"  # the decision window is open
    ATTEMPT = "attempt"  # the robot is trying by itself
    TELEOP = "teleop"  # the participant teleoperates
    DONE = "done"


class SceneView(StrEnum):
    """What showed a trial's scene when the page proved it on screen (``Trial.scene_shown_view``)."""

    THREE_D = "3d"  # the 3D view
    TWO_D = "2d"  # the 2-D helper view
    TEXT = "text"  # a client without a view, e.g. a bot


class WindowOpener(StrEnum):
    """What opened a trial's decision window (``Trial.window_opened_by``): the view of the page's proof that the
    scene was shown (a ``SceneView``), or no proof within the study's ``timing.scene_wait_s``."""

    THREE_D = "3d"
    TWO_D = "2d"
    TEXT = "text"
    WAIT_LIMIT = "wait_limit"  # no evidence that the scene was on screen: a data-quality flag


#: The context of a questionnaire page asked before the first block (answers' ``context``).
BEFORE_BLOCKS = "before"
#: The context of a questionnaire page asked at the end of the study, after every block (``questionnaires_end``).
END_OF_STUDY = "end"


def after_block_context(block: int) -> str:
    """The context of a questionnaire page asked after block position ``block``."""
    return f"after:{block}"


def shelf_context(block: int, shelf: int) -> str:
    """The context of the survey after shelf ``shelf`` of block position ``block``."""
    return f"shelf:{block}:{shelf}"


class TrialRef(NamedTuple):
    """A trial of a participant, as its row is keyed: block 0 for practice; ``trial`` counts from 1."""

    practice: bool
    block: int
    trial: int

    def describe(self) -> str:
        """In words, for messages: "practice trial 2 of block 0", "trial 5 of block 1"."""
        return f"{'practice ' if self.practice else ''}trial {self.trial} of block {self.block}"


class QuestionnairePage(NamedTuple):
    """One questionnaire asked at one point of the study: what its answers are recorded with."""

    questionnaire: str
    context: str  # before | shelf:B:S | after:B | end
    block: int | None = None
    shelf: int | None = None


def _phase_required(schema: dict[str, Any]) -> None:
    """The JSON schema names ``phase`` required: it is in every step's JSON (a default only spares constructors)."""
    schema["required"] = ["phase", *schema.get("required", [])]


class _Step(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, json_schema_extra=_phase_required)

    @property
    def trial_ref(self) -> TrialRef | None:
        """The trial this step runs (None for steps that run no trial)."""
        return None

    @property
    def block_position(self) -> int | None:
        """The block (its position in the participant's order, from 1) this step belongs to, if any."""
        return None

    @property
    def questionnaire_context(self) -> str | None:
        """The context of the questionnaire page this step asks (before | shelf:B:S | after:B | end), if any."""
        return None

    def questionnaire_page(self, config: StudyConfig) -> QuestionnairePage | None:
        """The questionnaire page this step asks, if any."""
        return None


class ConsentStep(_Step):
    phase: Literal["consent"] = "consent"


class InstructionsStep(_Step):
    phase: Literal["instructions"] = "instructions"


class PracticeStep(_Step):
    phase: Literal["practice"] = "practice"
    index: int  # into the config's practice trials, from 0

    @property
    def trial_ref(self) -> TrialRef:
        return TrialRef(True, 0, self.index + 1)


class PracticeDoneStep(_Step):
    """After the last practice trial: the page says that the practice is over and choices count from now on."""

    phase: Literal["practice_done"] = "practice_done"


class TrialStep(_Step):
    phase: Literal["trial"] = "trial"
    block: int
    trial: int

    @property
    def trial_ref(self) -> TrialRef:
        return TrialRef(False, self.block, self.trial)

    @property
    def block_position(self) -> int:
        return self.block


class ShelfSurveyStep(_Step):
    """The survey after the last trial (``trial``) of a shelf."""

    phase: Literal["shelf_survey"] = "shelf_survey"
    block: int
    shelf: int
    trial: int

    @property
    def block_position(self) -> int:
        return self.block

    @property
    def questionnaire_context(self) -> str:
        return shelf_context(self.block, self.shelf)

    def questionnaire_page(self, config: StudyConfig) -> QuestionnairePage | None:
        if config.shelf_questionnaire is None:
            return None
        return QuestionnairePage(config.shelf_questionnaire, self.questionnaire_context, self.block, self.shelf)


class QuestionnaireStep(_Step):
    """A questionnaire before the blocks (context ``before``, no ``block``), after block position ``block`` (context
    ``after:B``) or at the end of the study (context ``end``, no ``block``)."""

    phase: Literal["questionnaire"] = "questionnaire"
    context: str
    # Stored without the key before the blocks (the JSON of existing sessions).
    block: int | None = Field(None, exclude_if=lambda block: block is None)
    questionnaire: str

    @property
    def block_position(self) -> int | None:
        return self.block

    @property
    def questionnaire_context(self) -> str:
        return self.context

    def questionnaire_page(self, config: StudyConfig) -> QuestionnairePage:
        return QuestionnairePage(self.questionnaire, self.context, self.block)


class DebriefStep(_Step):
    phase: Literal["debrief"] = "debrief"


class DeclinedStep(_Step):
    """Terminal, like the debrief: the participant did not consent."""

    phase: Literal["declined"] = "declined"


class ScreenedOutStep(_Step):
    """Terminal: the session ended at a questionnaire page (experiment.attention)."""

    phase: Literal["screened_out"] = "screened_out"


Step = Annotated[ConsentStep | InstructionsStep | PracticeStep | PracticeDoneStep | TrialStep | ShelfSurveyStep
                 | QuestionnaireStep | DebriefStep | DeclinedStep | ScreenedOutStep, Field(discriminator="phase")]
_STEP = TypeAdapter[Step](Step)

CONSENT = ConsentStep()
INSTRUCTIONS = InstructionsStep()
PRACTICE_DONE = PracticeDoneStep()
DEBRIEF = DebriefStep()
DECLINED = DeclinedStep()
SCREENED_OUT = ScreenedOutStep()
FINISHED_PHASES = ("debrief", "declined", "screened_out")


def parse_step(data: dict[str, Any]) -> Step:
    """The step stored as ``data`` (a step's ``model_dump()``)."""
    return _STEP.validate_python(data)


def first_step() -> Step:
    return CONSENT


def next_step(config: StudyConfig, step: Step, block_order: list[str] | None = None) -> Step:
    """The step after ``step`` (``block_order`` is needed once trials begin)."""
    match step:
        case ConsentStep():
            return INSTRUCTIONS
        case InstructionsStep():
            return _after_instructions(config)
        case PracticeStep(index=index):
            if index + 1 < len(config.practice.trials):
                return PracticeStep(index=index + 1)
            return PRACTICE_DONE
        case PracticeDoneStep():
            return _before_questionnaire(config, 0)
        case QuestionnaireStep(context="end", questionnaire=questionnaire):
            return _end_questionnaire(config, config.questionnaires_end.index(questionnaire) + 1)
        case QuestionnaireStep(block=None, questionnaire=questionnaire):
            return _before_questionnaire(config, config.questionnaires_before.index(questionnaire) + 1)
    if block_order is None:
        raise ValueError("the block order is needed after the first trial")
    match step:
        case TrialStep():
            return _after_trial(config, step, block_order)
        case ShelfSurveyStep():
            return _after_shelf(config, step, block_order)
        case QuestionnaireStep(block=int(block_position), questionnaire=questionnaire):
            block = config.block(block_order[block_position - 1])
            return _after_block(config, block_position, block.questionnaires_after.index(questionnaire) + 1,
                                block_order)
    raise ValueError(f"no step follows {step.phase!r}")


def _after_instructions(config: StudyConfig) -> Step:
    if config.practice.enabled and config.practice.trials:
        return PracticeStep(index=0)
    return _before_questionnaire(config, 0)


def _before_questionnaire(config: StudyConfig, index: int) -> Step:
    if index < len(config.questionnaires_before):
        return QuestionnaireStep(context=BEFORE_BLOCKS, questionnaire=config.questionnaires_before[index])
    return TrialStep(block=1, trial=1)


def _after_trial(config: StudyConfig, step: TrialStep, block_order: list[str]) -> Step:
    block = config.block(block_order[step.block - 1])
    n_trials = block.schedule.n_trials
    shelf_of = shelves(n_trials, config.shelf_size)
    index = step.trial - 1
    shelf_ends = index + 1 == n_trials or shelf_of[index + 1] != shelf_of[index]
    if shelf_ends and config.shelf_questionnaire:
        return ShelfSurveyStep(block=step.block, shelf=shelf_of[index], trial=step.trial)
    return _after_shelf(config, step, block_order)


def _after_shelf(config: StudyConfig, step: TrialStep | ShelfSurveyStep, block_order: list[str]) -> Step:
    block = config.block(block_order[step.block - 1])
    if step.trial < block.schedule.n_trials:
        return TrialStep(block=step.block, trial=step.trial + 1)
    return _after_block(config, step.block, 0, block_order)


def _after_block(config: StudyConfig, block_position: int, index: int, block_order: list[str]) -> Step:
    block = config.block(block_order[block_position - 1])
    if index < len(block.questionnaires_after):
        return QuestionnaireStep(context=after_block_context(block_position), block=block_position,
                                 questionnaire=block.questionnaires_after[index])
    if block_position < len(block_order):
        return TrialStep(block=block_position + 1, trial=1)
    return _end_questionnaire(config, 0)


def _end_questionnaire(config: StudyConfig, index: int) -> Step:
    if index < len(config.questionnaires_end):
        return QuestionnaireStep(context=END_OF_STUDY, questionnaire=config.questionnaires_end[index])
    return DEBRIEF


def all_steps(config: StudyConfig, block_order: list[str]) -> list[Step]:
    """Every step of a participant who consents, in order (for progress displays and tests)."""
    steps = [first_step()]
    while steps[-1].phase != "debrief":
        steps.append(next_step(config, steps[-1], block_order))
    return steps


def progress(config: StudyConfig, step: Step, block_order: list[str] | None) -> float:
    """Fraction of the study's steps done, for the participant's progress bar."""
    return progress_at(step_fractions(config, block_order), step)


def step_fractions(config: StudyConfig, block_order: list[str] | tuple[str, ...] | None) -> dict[Step, float]:
    """Each step of a participant with this block order (the study's order if None) and the fraction of the study's
    steps done when it is reached (steps are frozen, hence hashable: a page's state looks its step up)."""
    steps = all_steps(config, list(block_order or [b.name for b in config.blocks]))
    fractions: dict[Step, float] = {}
    for index, step in enumerate(steps):
        fractions.setdefault(step, index / (len(steps) - 1))
    return fractions


def progress_at(fractions: dict[Step, float], step: Step) -> float:
    """``progress`` from ``step_fractions``: a step off the path (declined, screened out) is all or nothing."""
    fraction = fractions.get(step)
    if fraction is None:
        return 1.0 if step.phase in FINISHED_PHASES else 0.0
    return fraction
