"""StudyConfig: the validated, versioned document that defines a study (SPEC §3–§5).

A study is a list of blocks, each with a robot policy and a complexity
schedule, wrapped in the participant's flow: consent, instructions, practice,
questionnaires before, shelf surveys during and questionnaires after each
block, debrief with a completion code. Everything a lab may change is here;
the paper's values are the defaults (``experiment.defaults``) and the
templates (``experiment.templates``).
"""

from __future__ import annotations

import difflib
import json
from typing import Annotated, Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from experiment import defaults
from experiment.attention import AttentionConfig, has_attention_checks
from experiment.instruments import BUILTIN_QUESTIONNAIRES, SCHAEFER_14, SHELF_TRUST_RELIANCE_NAMED
from experiment.iohmm import BeliefUpdate, IOHMMParams, ModelError, paper_params, params_from_document
from experiment.languages import DEFAULT_LANGUAGES, canonical_tag, valid_tag
from experiment.outcomes import RECEIVED_DOCUMENT, CompletionConfig
from experiment.privacy import PrivacyConfig
from experiment.psychds import DatasetInfo
from experiment.questionnaires import ROBOT_PLACEHOLDER, Questionnaire
from experiment.schedule import ScheduleSpec
from experiment.task import Complexity, RobotAction, TaskParams
from experiment.trust_states_document import TrustModel, trust_model_from_document
from experiment.world.constants import GRASP_RADIUS

CONFIG_VERSION: Final = 1
#: The largest amount of money a config may state (in its currency): a bound, so that a typo cannot overflow.
MAX_AMOUNT = 1e6


class _Strict(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


ModelRef = Literal["paper"] | dict[str, Any]


def resolve_model(ref: ModelRef) -> IOHMMParams:
    """The two-state IOHMM parameters a config refers to: ``"paper"`` or an inline model JSON."""
    return paper_params() if ref == "paper" else params_from_document(ref)


def resolve_trust_model(ref: ModelRef) -> TrustModel:
    """The trust model a config refers to: the paper's form (``IOHMMParams``, as ``resolve_model``) for ``"paper"``
    and a two-state document, ``KStateParams`` for a document of 3…4 states (``experiment.trust_states_document``)."""
    return paper_params() if ref == "paper" else trust_model_from_document(ref)


def _check_model(ref: ModelRef) -> ModelRef:
    try:
        resolve_trust_model(ref)
    except ModelError as exc:
        raise ValueError(str(exc)) from None
    return ref


class RandomAssistSpec(_Strict):
    kind: Literal["random_assist"] = Field("random_assist", description=(
        "Random assistance-seeking (paper study 1): the robot asks at random with a fixed probability per complexity"))
    p_ask_low: float = Field(defaults.STUDY1_P_ASK_LOW, ge=0, le=1, title="P(ask), low complexity", description=(
        "Probability that the robot asks for help in a low-complexity trial"))
    p_ask_high: float = Field(defaults.STUDY1_P_ASK_HIGH, ge=0, le=1, title="P(ask), high complexity", description=(
        "Probability that the robot asks for help in a high-complexity trial"))


class TrustAgnosticSpec(_Strict):
    """Either observed intervention rates (the optimal action is computed) or explicit actions."""

    kind: Literal["trust_agnostic"] = Field("trust_agnostic", description=(
        "The optimal complexity-only policy (paper §5.1): one action per complexity, whatever the participant's trust"))
    intervention_rate_low: float | None = Field(defaults.PAPER_INTERVENTION_RATE_LOW, ge=0, le=1,
                                                title="Intervention rate, low complexity",
                                                description=(
        "Observed P(intervene | low complexity, robot acts alone), from earlier data; the action with the higher "
        "expected reward is computed from it"))
    intervention_rate_high: float | None = Field(defaults.PAPER_INTERVENTION_RATE_HIGH, ge=0, le=1,
                                                 title="Intervention rate, high complexity",
                                                 description=(
        "Observed P(intervene | high complexity, robot acts alone), from earlier data"))
    actions: dict[Complexity, RobotAction] | None = Field(None, title="Explicit actions", description=(
        "Explicit actions per complexity (low and high: auto or ask) instead of computing them from the rates; "
        "null: computed"))

    @model_validator(mode="after")
    def _rates_or_actions(self) -> TrustAgnosticSpec:
        has_rates = self.intervention_rate_low is not None and self.intervention_rate_high is not None
        if self.actions is None and not has_rates:
            raise ValueError("trust_agnostic needs both intervention rates or explicit actions for low and high")
        if self.actions is not None and set(self.actions) != set(Complexity):
            raise ValueError("trust_agnostic actions must name both complexities: low and high")
        return self


class TrustAwareSpec(_Strict):
    """The belief-MDP policy of a model; ``p_high`` defaults to the block's schedule."""

    kind: Literal["trust_aware"] = Field("trust_aware", description=(
        "The belief-MDP policy (paper §3.4): asks for help while its belief that trust is high is low"))
    model: ModelRef = Field("paper", title="Trust model", description=(
        'The trust model (IOHMM) the policy plans with and keeps its belief by: "paper" for the paper\'s '
        "parameters, or a model JSON document (e.g. one fitted on this platform) of 2 to 4 trust states"))
    p_high: float | None = Field(None, ge=0, le=1, title="P(high complexity) planned for", description=(
        "P(high complexity) the policy plans for; null: the block's schedule's share of high-complexity trials"))
    grid: int = Field(1001, ge=11, le=100_001, title="Belief grid points",
                      description=(
        "Number of belief points of the value iteration; a model of K ≥ 3 states gets the finest regular grid "
        "of the belief simplex with at most this many points"))
    belief_update: BeliefUpdate = Field("bayes", description=(
        'How the belief is updated after a trial: "bayes" (exact filter) or "paper" (the paper\'s equation)'))
    discount: float = Field(defaults.DISCOUNT, ge=0, lt=1, title="Discount γ",
                            description="Discount factor γ of the belief MDP")

    @field_validator("model")
    @classmethod
    def _model_resolves(cls, ref: ModelRef) -> ModelRef:
        return _check_model(ref)


class AlwaysAutoSpec(_Strict):
    kind: Literal["always_auto"] = Field("always_auto", description="The robot always acts alone (a baseline)")


class AlwaysAskSpec(_Strict):
    kind: Literal["always_ask"] = Field("always_ask", description="The robot always asks for help (a baseline)")


PolicySpec = Annotated[RandomAssistSpec | TrustAgnosticSpec | TrustAwareSpec | AlwaysAutoSpec | AlwaysAskSpec,
                       Field(discriminator="kind")]


class BlockConfig(_Strict):
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$", description=(
        "The block's identifier, recorded with every trial (column block_name); letters, digits, _ and -"))
    label: str = Field("", description=(
        "Deprecated, not shown. Participants see the block's position label (texts.block_label: 'Robot A' for the "
        "first block they meet, 'Robot B' for the second, whatever the order), so a label can neither reveal the "
        "policy nor contradict the order; the block's name and policy are recorded with every trial. Kept so "
        "older configurations load."))
    policy: PolicySpec = Field(title="Robot policy", description=(
        "How the robot decides, trial by trial, whether to ask for help"))
    schedule: ScheduleSpec = Field(title="Trial schedule", description=(
        "How many trials the block has and how their complexity is drawn"))
    questionnaires_after: list[str] = Field([], title="Questionnaires after the block", description=(
        "Ids of the questionnaires asked right after the block, about its robot (the page names it: \"These "
        "questions are about Robot B\"). With counterbalanced orders a block is not always the last: questions "
        "for the end of the study belong in questionnaires_end"))

    @field_validator("questionnaires_after")
    @classmethod
    def _after_once(cls, ids: list[str]) -> list[str]:
        return asked_once(ids)

    @model_validator(mode="after")
    def _a_session_can_hold_it(self) -> BlockConfig:
        if self.schedule.n_trials > defaults.MAX_TRIALS_PER_BLOCK:
            raise ValueError(f"a block may have at most {defaults.MAX_TRIALS_PER_BLOCK:,} trials; block "
                             f"{self.name!r} has {self.schedule.n_trials:,}")
        return self


class PracticeTrial(_Strict):
    complexity: Complexity = Field(description="The practice trial's complexity (high: obstacles in the way)")
    robot_action: RobotAction = Field(description="What the robot does: auto (tries alone) or ask (asks for help)")
    human_action_hint: Literal["rely", "intervene"] | None = Field(None, title="Suggested participant action",
                                                                   description=(
        "What the page suggests the participant does when the robot tries alone; null: no suggestion"))


class TutorialConfig(_Strict):
    """The guided first teleoperation of the practice phase.

    Every practice teleoperation is guided until the participant has put an item in the bin once:
    it has its own, generous time limit, and when that runs out the same trial starts over (from the
    ready pose) until ``max_tries`` tries are used up.
    """

    enabled: bool = Field(True, title="Guide the first teleoperation",
                          description="Guide practice teleoperations until the first deposit")
    max_tries: int = Field(3, ge=1, le=10, title="Tries per practice trial",
                           description="Tries per practice trial before it counts as failed")
    time_limit_s: float = Field(300.0, gt=0, le=1800, title="Time limit per try (s)",
                                description="Time limit of each guided try (s)")


class PracticeConfig(_Strict):
    """Familiarisation (§4): every complexity × robot action, with teleoperation; not scored."""

    enabled: bool = Field(True, title="Practice before the blocks",
                          description="Whether participants practise before the scored blocks")
    tutorial: TutorialConfig = Field(TutorialConfig(), title="Guided tutorial",
                                     description="The guided first teleoperation")
    trials: list[PracticeTrial] = Field(title="Practice trials", description="The practice trials, in order", default=[
        PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.AUTO, human_action_hint="rely"),
        PracticeTrial(complexity=Complexity.HIGH, robot_action=RobotAction.AUTO, human_action_hint="intervene"),
        PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.ASK),
        PracticeTrial(complexity=Complexity.HIGH, robot_action=RobotAction.ASK),
    ])


#: The page's visible "Next item" pause between an outcome and the next item (timing.next_item_pause_s): not from
#: the paper; long enough to read as a new item rather than the last one's consequence.
NEXT_ITEM_PAUSE_S = 2.0


class TimingConfig(_Strict):
    """Pacing the server enforces (tests and load runs may speed it up)."""

    decision_window_s: float = Field(4.0, gt=0, le=60, title="Decision window (s)", description=(
        "Seconds the participant has to press Intervene when the robot announces that it will try alone"))
    scene_wait_s: float = Field(10.0, gt=0, le=120, title="Longest wait for the scene (s)", description=(
        "The decision window opens when the page reports the trial's scene shown (3D or 2-D view); without a "
        "report it opens this many seconds after the trial started, and the trial records that it did"))
    animation_speed: float = Field(1.0, gt=0, le=100, description="The robot's pace: 1 is as designed, 2 twice as fast")
    teleop_time_limit_s: float = Field(90.0, gt=0, le=600, title="Teleoperation time limit (s)", description=(
        "Seconds a teleoperation may take before it ends as failed"))
    idle_timeout_s: float = Field(900.0, ge=30, le=86_400, title="Idle timeout (s)", description=(
        "Seconds without any request after which a session counts as abandoned (a day at most)"))
    # Left out of dumps at its default, so documents written before it keep their config hash.
    next_item_pause_s: float = Field(NEXT_ITEM_PAUSE_S, ge=0, le=30, title="Pause before the next item (s)",
                                     exclude_if=lambda seconds: seconds == NEXT_ITEM_PAUSE_S, description=(
        "After an item's outcome, the page says 'Next item' for this many seconds before the next item starts, so "
        "that no decision window follows an outcome at once (0: none)"))


class TeleopConfig(_Strict):
    """How forgiving teleoperation is. The defaults are the task as designed (no assistance)."""

    grasp_radius_m: float = Field(GRASP_RADIUS, gt=0, le=0.2, title="Grasp radius (m)", description=(
        "Closing the gripper grasps the item when the gripper's centre is this close to the item's grasp point (m)"))
    align_radius_m: float = Field(0.0, ge=0, le=0.3, title="Alignment assistance radius (m)", description=(
        "Assistance: closing the gripper farther than grasp_radius_m but within this distance (m) first moves "
        "it onto the grasp point when the way is free, then grasps. 0 turns the assistance off"))

    @model_validator(mode="after")
    def _align_beyond_grasp(self) -> TeleopConfig:
        if 0 < self.align_radius_m <= self.grasp_radius_m:
            raise ValueError("align_radius_m must be 0 (off) or larger than grasp_radius_m")
        return self


class CompensationConfig(_Strict):
    """What the study pays (base plus a score bonus, capped). All zero: the study pays nothing itself (e.g. the
    recruitment site pays), and the participant is not shown a payment."""

    currency: str = Field("USD", description="Currency of the amounts below, e.g. USD, GBP, EUR")
    base: float = Field(0.0, ge=0, le=MAX_AMOUNT, title="Base payment", description="Paid for taking part")
    bonus_per_point: float = Field(0.0, ge=0, le=MAX_AMOUNT,
                                   description="Bonus per point of the final score (negative scores: none)")
    bonus_cap: float = Field(0.0, ge=0, le=MAX_AMOUNT, description="Largest bonus paid (0: no bonus)")

    @property
    def has_bonus(self) -> bool:
        return self.bonus_per_point > 0 and self.bonus_cap > 0

    @property
    def defined(self) -> bool:
        """Whether the study pays anything itself (a payment is shown on the debrief only then)."""
        return self.base > 0 or self.has_bonus

    def amount(self, score: float) -> float:
        """What a participant who finished with ``score`` is paid: base plus the capped bonus (none for a negative
        score), to the cent. The one rule: the debrief and participants.csv show it, the summary describes it."""
        return round(self.base + min(max(score, 0.0) * self.bonus_per_point, self.bonus_cap), 2)


class RecruitmentConfig(_Strict):
    """Admission control: how many participants the study runs at once."""

    max_active_participants: int | None = Field(None, gt=0, title="Most participants active at once", description=(
        "Most sessions active at once: consented sessions until they complete, are abandoned or withdrawn, and "
        "sessions not yet consented while their page is open (seen in the last two minutes: the server's "
        "unconsented_place_hold_s), so bare joins do not fill the study. A new join past it is refused with 503 and "
        "Retry-After, and the join page tells the participant the study is full right now; a returning participant "
        "(their browser, or their Prolific session) is never refused. null: no cap"))


#: The placeholders a block label may use: the block's position in the participant's order as a letter or number.
BLOCK_LABEL_FIELDS = ("letter", "number")


def block_label(pattern: str, position: int) -> str:
    """The participant-facing name of the block at ``position`` (1-based) in the participant's order."""
    return pattern.format(letter=_letters(position), number=position)


def _letters(position: int) -> str:
    """1 → A, 2 → B, …, 26 → Z, 27 → AA (a study has at most 12 blocks)."""
    text = ""
    while position > 0:
        position, rest = divmod(position - 1, 26)
        text = chr(ord("A") + rest) + text
    return text


#: A text the lab writes: one string for every language, or a text per language ({"en": "…", "de": "…"}; the keys
#: are BCP 47 tags and cover every language the study offers).
LocalText = str | dict[str, str]


def text_in(text: LocalText, language: str, default_language: str) -> str:
    """``text`` as a participant in ``language`` reads it (a single string serves every language)."""
    if isinstance(text, str):
        return text
    return text.get(language, text.get(default_language, next(iter(text.values()), "")))


class TextsConfig(_Strict):
    title: LocalText = Field("Robot supervision study", min_length=1, max_length=120, title="Title participants see",
                       description=(
        "The study's name as participants see it (tab title, top bar); the study's own title is the researchers' "
        "name and is not shown to participants"))
    block_label: LocalText = Field("Robot {letter}", min_length=1, max_length=60, title="Block label", description=(
        "How the page names each block, by its position in the participant's order: {letter} is A for the first "
        "block the participant meets, B for the second …; {number} is 1, 2, …"))
    consent: LocalText = Field(description="The consent page's text (one text, or one per language)",
                         default=("You are invited to take part in a research study on how people supervise a robot. "
                    "You will watch a robot collect groceries and decide when to step in. Participation is "
                    "voluntary; you may stop at any time. Your answers are stored without your name."))
    instructions: LocalText = Field(description="The instructions page's text (one text, or one per language)",
                              default=("The robot collects items from a shelf into the bin on its base. Before each "
                                       "attempt it "
                         "tells you whether it will collect the item itself or needs your help. If it tries by itself "
                         "you may press Intervene and collect the item yourself. Scores: +3 robot success, "
                         "-4 robot failure, 0 if you intervene, +1 when the robot asks for help."))
    instructions_video_url: str | None = Field(None, title="Instructions video URL",
                                               description="A video shown with the instructions; null: none")
    debrief: LocalText = Field(
        "Thank you for taking part. The study looked at how trust in a robot changes over time.",
        description="The text of the last page, with the completion code (one text, or one per language)")

    @field_validator("block_label")
    @classmethod
    def _known_placeholders(cls, pattern: LocalText) -> LocalText:
        for text in [pattern] if isinstance(pattern, str) else pattern.values():
            try:
                block_label(text, 1)
            except (KeyError, IndexError, ValueError, AttributeError) as exc:
                raise ValueError(f"block_label may use only the placeholders "
                                 f"{', '.join('{' + f + '}' for f in BLOCK_LABEL_FIELDS)} ({exc!r})") from None
        return pattern

    @field_validator("title", "block_label", "consent", "instructions", "debrief")
    @classmethod
    def _per_language(cls, text: LocalText) -> LocalText:
        if isinstance(text, dict):
            bad = [tag for tag in text if not valid_tag(tag)]
            if bad or not text:
                raise ValueError("a text per language is keyed by BCP 47 language tags (\"en\", \"de\"), "
                                 f"at least one{'; not tags: ' + ', '.join(map(repr, bad)) if bad else ''}")
            if any(not value.strip() for value in text.values()):
                raise ValueError("a text per language may not be empty")
            return {canonical_tag(tag): value for tag, value in text.items()}
        return text

    def in_language(self, language: str, default_language: str) -> TextsConfig:
        """These texts as a participant in ``language`` reads them: every text a single string."""
        return self.model_copy(update={name: text_in(value, language, default_language)
                                       for name, value in self.mapped().items()})

    def mapped(self) -> dict[str, dict[str, str]]:
        """The texts given per language, by field."""
        return {name: value for name in ("title", "block_label", "consent", "instructions", "debrief")
                if isinstance(value := getattr(self, name), dict)}


def _list(value: Any) -> list[Any]:
    return value if isinstance(value, list) else []


def _strings(value: Any) -> list[str]:
    """The strings in ``value`` when it is a list (a malformed document is left for validation to report)."""
    return [v for v in _list(value) if isinstance(v, str)]


class StudyConfig(_Strict):
    config_version: Literal[1] = Field(CONFIG_VERSION, title="Format version",
                                       description="Version of this document's format")
    title: str = Field(min_length=1, max_length=200, description="The study's name for researchers (admin page)")
    description: str = Field("", description="Notes for researchers: what the study is for")
    # Left out of dumps at the default, so documents written before it keep their config hash.
    languages: list[str] = Field(list(DEFAULT_LANGUAGES), min_length=1, max_length=20,
                                 exclude_if=lambda tags: tags == list(DEFAULT_LANGUAGES), description=(
        'The languages participants may take the study in, as BCP 47 tags ("en", "de", "ar"); the first is the '
        "default. A participant's language is chosen once, at the join: the join link's lang parameter "
        "(/join/SLUG?lang=de) if the study offers it, else the browser's preferred language the study offers, else "
        "the first. The pages' own words come from trustlab's catalogues (English where a language has none); the "
        "study's texts and questionnaires may give a text per language"))
    seed: int = Field(0, ge=0, le=2**63 - 1, description=(
        "Seed of every random draw (schedules, robot choices, outcomes): the same seed gives the same sessions"))
    task: TaskParams = Field(TaskParams(), description="The task: success probabilities, rewards, experience")
    #: The model whose belief is stored with every trial (SPEC §4), and the
    #: default model of trust-aware blocks.
    model: ModelRef = Field("paper", title="Trust model of the stored belief", description=(
        'The trust model whose belief is stored with every trial: "paper" or a model JSON document (2 to 4 trust '
        'states)'))
    belief_update: BeliefUpdate = Field("bayes", description=(
        'How the stored belief is updated: "bayes" (exact filter) or "paper" (the paper\'s equation)'))
    blocks: list[BlockConfig] = Field(min_length=1, max_length=12, description=(
        "The scored blocks, each with its robot policy and trial schedule"))
    counterbalance: Literal["none", "all", "latin"] = Field("all", title="Counterbalancing", description=(
        'Block orders participants are assigned to: "none" (as listed), "all" (every order), "latin" (Latin square)'))
    shelf_size: int = Field(8, ge=1, le=200, title="Trials per shelf",
                            description="Trials per shelf; the shelf questionnaire follows each shelf")
    practice: PracticeConfig = Field(PracticeConfig(), description="The practice phase before the scored blocks")
    questionnaires: list[Questionnaire] = Field([SHELF_TRUST_RELIANCE_NAMED, SCHAEFER_14], description=(
        "The questionnaires the study defines (built-ins named by id are added)"))
    questionnaires_before: list[str] = Field([], title="Questionnaires before the first block",
                                             description="Ids of the questionnaires asked before the first block")
    shelf_questionnaire: str | None = Field(SHELF_TRUST_RELIANCE_NAMED.id, title="Questionnaire after each shelf",
                                            description=(
        "Id of the questionnaire asked after each shelf; null: none. Built in: shelf_trust_reliance_named (the "
        "paper's trust and reliance questions naming the robot as the pages do: \"To what extent do you trust "
        "Robot A in this scenario?\") and shelf_trust_reliance (the paper's own wording: \"… the automation …\")"))
    # Left out of dumps when empty, so documents written before it keep their config hash.
    questionnaires_end: list[str] = Field([], title="Questionnaires at the end of the study",
                                          exclude_if=lambda ids: not ids, description=(
        "Ids of the questionnaires asked once at the end of the study, after every block (and its "
        "questionnaires_after), whatever the participant's block order. Their pages name no robot (with several "
        "blocks there is no one robot they are about): for demographics, comments, questions about the study as "
        "a whole. Questions about one robot belong in its block's questionnaires_after"))
    timing: TimingConfig = Field(TimingConfig(), description="Pacing: decision window, robot speed, time limits")
    teleop: TeleopConfig = Field(TeleopConfig(), description="How forgiving teleoperation is")
    compensation: CompensationConfig = Field(CompensationConfig(), description="What the participant is paid")
    recruitment: RecruitmentConfig = Field(RecruitmentConfig(), description="Admission control")
    completion: CompletionConfig = Field(CompletionConfig(), description="Completion codes and the final redirect")
    texts: TextsConfig = Field(TextsConfig(), title="Texts participants read", description="What participants read")
    # Left out of dumps at the default, so existing documents keep their hash (experiment.attention).
    attention: AttentionConfig = Field(AttentionConfig(), exclude_if=lambda rule: rule == AttentionConfig(),
title="Attention checks",
                                       description=("What failed attention checks do: flag only (default) or "
                                                    "screen out after max_failures"))
    # Left out of dumps when not given, so existing documents keep their hash.
    dataset: DatasetInfo | None = Field(None, title="Published dataset", exclude_if=lambda info: info is None,
                                        description=(
        "How the study's Psych-DS export describes the dataset (dataset_description.json): authors, license, "
        "citation, keywords; null: none given"))
    # Left out of dumps at the default, so existing documents keep their hash (experiment.privacy).
    privacy: PrivacyConfig = Field(PrivacyConfig(), exclude_if=lambda rules: rules == PrivacyConfig(),
                                   title="Withdrawal and retention", description=(
        "The participant's rights over their data: what withdrawing does (delete or keep the data), what the "
        "withdrawal confirmation says, and when personal fields (recruitment ids) are erased"))

    @field_validator("model")
    @classmethod
    def _model_resolves(cls, ref: ModelRef) -> ModelRef:
        return _check_model(ref)

    @field_validator("languages")
    @classmethod
    def _languages_are_tags(cls, tags: list[str]) -> list[str]:
        bad = [t for t in tags if not valid_tag(t)]
        if bad:
            raise ValueError(f"not a BCP 47 language tag: {', '.join(map(repr, bad))} (write e.g. \"en\", \"de\", "
                             "\"pt-BR\")")
        tags = [canonical_tag(t) for t in tags]
        repeated = sorted({t for t in tags if tags.count(t) > 1})
        if repeated:
            raise ValueError(f"a language is offered once; repeated: {', '.join(repeated)}")
        return tags

    @property
    def default_language(self) -> str:
        return self.languages[0]

    @model_validator(mode="after")
    def _texts_cover_the_languages(self) -> StudyConfig:
        """A text given per language gives it in every language the study offers (a single string serves all)."""
        for name, texts in self.texts.mapped().items():
            missing = [tag for tag in self.languages if tag not in texts]
            if missing:
                raise ValueError(f"texts.{name} is given per language but not in {', '.join(missing)} (the study "
                                 f"offers {', '.join(self.languages)}): add it, or write one text for every language")
        return self

    @field_validator("questionnaires_before")
    @classmethod
    def _before_once(cls, ids: list[str]) -> list[str]:
        return asked_once(ids)

    @field_validator("questionnaires_end")
    @classmethod
    def _end_once(cls, ids: list[str]) -> list[str]:
        return asked_once(ids)

    @property
    def plays_for_points(self) -> bool:
        """Whether the participant plays for points: some outcome of a trial scores (``task.rewards``); the trial
        page shows the score, and the debrief the final one."""
        return self.task.rewards.gives_points

    @model_validator(mode="before")
    @classmethod
    def _add_named_builtins(cls, data: Any) -> Any:
        """A questionnaire the study uses by id without defining it is the built-in of that id
        (``BUILTIN_QUESTIONNAIRES``), added to ``questionnaires``; so the stored document holds what was asked."""
        if not isinstance(data, dict) or not isinstance(data.get("questionnaires", []), list):
            return data
        defined = data.get("questionnaires", cls.model_fields["questionnaires"].default)
        ids = set(_strings([q.id if isinstance(q, Questionnaire) else q.get("id") if isinstance(q, dict) else None
                            for q in defined]))
        used = _strings(data.get("questionnaires_before")) + _strings([data.get("shelf_questionnaire")])
        used += _strings(data.get("questionnaires_end"))
        for block in _list(data.get("blocks")):
            after = block.questionnaires_after if isinstance(block, BlockConfig) else (
                block.get("questionnaires_after") if isinstance(block, dict) else None)
            used += _strings(after)
        added = [BUILTIN_QUESTIONNAIRES[i] for i in dict.fromkeys(used) if i not in ids and i in BUILTIN_QUESTIONNAIRES]
        return data | {"questionnaires": [*defined, *added]} if added else data

    @model_validator(mode="after")
    def _references_resolve(self) -> StudyConfig:
        names = [b.name for b in self.blocks]
        if len(set(names)) != len(names):
            raise ValueError(f"block names must be unique, got {names}")
        known = {q.id for q in self.questionnaires}
        if len(known) != len(self.questionnaires):
            raise ValueError("questionnaire ids must be unique")
        used = list(self.questionnaires_before) + [q for b in self.blocks for q in b.questionnaires_after]
        used += list(self.questionnaires_end)
        used += [self.shelf_questionnaire] if self.shelf_questionnaire else []
        unknown = self._unknown_questionnaires(known)
        if unknown:
            raise ValidationError.from_exception_data(type(self).__name__, unknown)
        asked = [self.questionnaire(q) for q in dict.fromkeys(used)]
        if self.attention.rule == "screen_out" and not has_attention_checks(asked):
            raise ValueError("attention.rule 'screen_out' needs an attention check (an item with "
                             "instructed_response) in a questionnaire the study asks")
        return self

    def _unknown_questionnaires(self, known: set[str]) -> list[InitErrorDetails]:
        """An error at each field that names a questionnaire the study neither defines nor has built in (a built-in
        named by id is defined by now: ``_add_named_builtins``), beside that field, with every valid id and the
        closest ones."""
        places: list[tuple[tuple[str | int, ...], str]] = [
            (("questionnaires_before", i), q) for i, q in enumerate(self.questionnaires_before)]
        places += [(("blocks", b, "questionnaires_after", i), q) for b, block in enumerate(self.blocks)
                   for i, q in enumerate(block.questionnaires_after)]
        places += [(("shelf_questionnaire",), self.shelf_questionnaire)] if self.shelf_questionnaire else []
        places += [(("questionnaires_end", i), q) for i, q in enumerate(self.questionnaires_end)]
        return [InitErrorDetails(type=PydanticCustomError("unknown_questionnaire", "{message}",
                                                          {"message": unknown_questionnaire_message(q, known)}),
                                 loc=loc, input=q)
                for loc, q in places if q not in known]

    @model_validator(mode="after")
    def _robot_named_only_where_known(self) -> StudyConfig:
        """A questionnaire whose texts name the robot (``{robot}``) is asked only where the page is about one."""
        where = [("questionnaires_before", "before the first block", self.questionnaires_before)]
        if len(self.blocks) > 1:
            where.append(("questionnaires_end", "at the end of a study of several blocks", self.questionnaires_end))
        for field, when, ids in where:
            for q in ids:
                if self.questionnaire(q).names_robot:
                    raise ValueError(f"{field}: questionnaire {q!r} names the robot ({ROBOT_PLACEHOLDER}), but "
                                     f"{when} no page is about one robot; ask it after a block or a shelf")
        return self

    def questionnaire(self, questionnaire_id: str) -> Questionnaire:
        return next(q for q in self.questionnaires if q.id == questionnaire_id)

    def block(self, name: str) -> BlockConfig:
        return next(b for b in self.blocks if b.name == name)


def unknown_questionnaire_message(questionnaire_id: str, defined: set[str]) -> str:
    """What is wrong with a questionnaire id the study neither defines (``defined``) nor has built in: the closest
    valid ids first ("did you mean"), then every valid id, the study's own and the built-ins."""
    own = sorted(defined - set(BUILTIN_QUESTIONNAIRES))
    builtins = sorted(BUILTIN_QUESTIONNAIRES)
    close = difflib.get_close_matches(questionnaire_id, own + builtins, n=3, cutoff=0.6)
    guess = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else "."
    valid = f"{', '.join(builtins)} (built-in)" + (f"; {', '.join(own)} (this study's own)" if own else "")
    return f"unknown questionnaire id {questionnaire_id!r}{guess} Valid ids: {valid}."


def asked_once(ids: list[str]) -> list[str]:
    """``ids`` when no questionnaire is in it twice (the participant's path through a list goes by position)."""
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    if repeated:
        raise ValueError(f"a questionnaire is asked once per place; repeated: {', '.join(repeated)}")
    return ids


def validate_document(document: Any) -> StudyConfig:
    """A configuration received as a JSON document, validated as strictly as its JSON Schema reads: a number is
    not ``true`` or ``"3"``, a string not a number (``StudyConfig.model_validate`` coerces those, for stored
    documents); a whole number written 3.0 is still an integer, as JSON Schema counts it. Raises
    ``pydantic.ValidationError`` listing every problem with its location."""
    received = {RECEIVED_DOCUMENT: True}
    if not isinstance(document, dict):
        return StudyConfig.model_validate(document, context=received)
    return StudyConfig.model_validate_json(json.dumps(_whole_numbers(document)), strict=True, context=received)


def _whole_numbers(value: Any) -> Any:
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, dict):
        return {key: _whole_numbers(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_whole_numbers(item) for item in value]
    return value
