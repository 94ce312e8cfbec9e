"""Typed request and response bodies of the HTTP API (they make /openapi.json).

Names follow one convention: ``XCreate`` for a request body that adds something (a study, a fit, a participant's
answers, events, an intervention), ``XUpdate`` for one that changes something that exists (a study's config, a
draft, a participant's exclusion), ``XRead`` for a response and the parts of one. One exception: ``ErrorResponse``,
the body of every error answer of every route (``error_responses``), is the API's error envelope rather than a
resource read back, and keeps the name clients know it by.
"""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, WrapValidator, field_validator

from experiment.config import StudyConfig, validate_document
from experiment.defaults import SELECTION_FOLDS, STATES_MAX, STATES_MIN
from experiment.evaluation import EVALUATION_TEMPLATES
from experiment.events import CLIENT_KIND_LENGTH
from experiment.flow import ParticipantStatus, Step, TrialRef, TrialStage
from experiment.lifecycle import INITIAL_STATUSES
from experiment.task import Complexity
from experiment.templates import TEMPLATES
from server import strict_json
from server.strict_json import WHOLE_FLOAT_AS_INT, JsonInt
from server.teleop_messages import SceneInfo, WorldView

MAX_EVENT_PAYLOAD_BYTES = 4096
#: Study slugs: 2-63 lower-case letters, digits and '-' (they appear in join links).
SLUG_REGEX = r"^[a-z0-9][a-z0-9\-]{1,62}$"


class _RequestBody(BaseModel):
    """Request bodies: unknown fields, non-finite numbers (NaN, Infinity) and values of another JSON type
    (``false`` or ``"1"`` for a number) are refused, so a body is accepted exactly when it matches the schema."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


# --- participant -------------------------------------------------------------------------

class CameraUpdate(_RequestBody):
    """The 3D view's camera preset the participant chose (``POST /api/p/{token}/camera``)."""

    view: Literal["world", "local", "end_effector"]
    client_time_ms: float | None = Field(None, description="performance.now() when the view was chosen")


class CameraRead(BaseModel):
    view: str
    viewers: int = Field(description="viewer connections whose camera was moved now")


#: A resume key: 128 to 768 random bits, base64url (the join page makes one with crypto.getRandomValues).
RESUME_KEY_PATTERN = r"^[A-Za-z0-9_-]{22,128}$"


class JoinCreate(_RequestBody):
    """Recruitment parameters (also accepted as query parameters of the join link) and the browser's resume key."""

    params: dict[str, str] = Field(default_factory=dict, max_length=16)
    resume_key: str | None = Field(None, pattern=RESUME_KEY_PATTERN, description=(
        "The joining browser's resume key (the join page keeps one per study in localStorage and sends it with every "
        "join). A join with a known external id resumes that session only with the key it was joined with (or, from "
        "Prolific, the same SESSION_ID; from MTurk, the same assignmentId); otherwise it starts a new session marked "
        "as a duplicate. Omitted: the server makes one and returns it"))


class ConsentCreate(_RequestBody):
    agree: bool




class AtTrial(_RequestBody):
    """The trial a step acts on (the fields the trial bodies share; not a body of its own)."""

    practice: bool = False
    block: JsonInt = Field(ge=0, le=100)
    trial: JsonInt = Field(ge=1, le=100_000)

    @property
    def ref(self) -> TrialRef:
        return TrialRef(self.practice, self.block, self.trial)


class TrialCreate(AtTrial):
    """Start the trial the session is at."""


class InterventionCreate(AtTrial):
    window_opened_ms: float | None = Field(None, description="performance.now() when the decision window opened")
    pressed_ms: float | None = Field(None, description="performance.now() when Intervene was pressed")


class SceneShownCreate(AtTrial):
    """The page shows the trial's scene: the decision window opens now (a repeat returns the same window)."""

    view: Literal["3d", "2d", "text"] = Field(description=(
        "What shows the scene: the 3D view (its viewer has received the trial's scene and drawn since), the 2-D "
        "helper view (drawn from GET trials/scene), or text only (a client without a view, e.g. a bot)"))
    client_time_ms: float | None = Field(None, ge=0, le=1e13, description=(
        "performance.now() when the first frame proven to show the scene was drawn (3d, 2d), or when the text "
        "was shown"))
    scene_stamp: str | None = Field(None, pattern=r"^[0-9a-f]{16}$", description=(
        "3d and 2d: the stamp of the scene the frame on screen was drawn from (trial.scene_stamp): in the 3D "
        "view, the scene node /scene_stamp_<stamp> that the 3D client held when it began drawing that frame; "
        "in the 2-D view, the scene_stamp of the GET trials/scene it drew. Only a report with the trial's stamp "
        "opens the window; any other is answered with the trial still presenting"))


#: An item's answer: a number for a rating item, text for a text item, the option's value for a choice item.
AnswerIn = Annotated[float | str, Field(union_mode="left_to_right")]


class AnswersCreate(_RequestBody):
    questionnaire: str = Field(min_length=1, max_length=64)
    answers: dict[str, AnswerIn] = Field(max_length=200, description=(
        "Item id → answer: a scale value (rating items), text (text items) or an option's value (choice items); an "
        "optional item may be left out"))
    context: str | None = Field(None, min_length=1, max_length=64,
                                description="The page answered, as the state named it (questionnaire.context): "
                                            "answers meant for another page, e.g. a stale tab's, are refused with 409")


class DraftUpdate(_RequestBody):
    """The answers given so far on the questionnaire page on screen (any subset of its items)."""

    questionnaire: str = Field(min_length=1, max_length=64)
    context: str = Field(min_length=1, max_length=64,
                         description="The page, as the state named it (questionnaire.context): a draft for a page the "
                                     "session is not at is refused with 409")
    answers: dict[str, AnswerIn] = Field(max_length=200, description=(
        "Item id → answer (as in AnswersCreate); items not answered yet are left out"))


class DraftRead(BaseModel):
    """The stored draft: the state returns it with the page until the page's answers are submitted."""

    questionnaire: str
    context: str
    answers: dict[str, float | str]


#: Bounds of one client event's payload (the pages send flat objects of a few short fields, ~70 bytes: see
#: ``static/js/events.js`` and its callers): what an export, the report and a spreadsheet can always read.
EVENT_PAYLOAD_MAX_DEPTH = 8
EVENT_PAYLOAD_MAX_KEYS = 64
EVENT_PAYLOAD_MAX_STRING = 1000
#: The largest integer JavaScript holds exactly (2^53 - 1): a larger one would not read back as written.
EVENT_PAYLOAD_MAX_INT = 2**53 - 1


class EventCreate(_RequestBody):
    """One client event. Its payload is a JSON object of at most 4096 bytes (as compact UTF-8 JSON), nested at most
    8 levels (the object itself is level 1), with at most 64 keys in any object, strings and keys of at most 1000
    characters, finite numbers and integers within ±(2^53 - 1); anything else is refused with 422, naming the
    place. (The numbers are the ``MAX_EVENT_PAYLOAD_BYTES`` and ``EVENT_PAYLOAD_*`` constants.)"""

    kind: str = Field(min_length=1, max_length=CLIENT_KIND_LENGTH, pattern=r"^[a-z0-9_.\-]+$")
    client_time_ms: float | None = None
    payload: dict[str, Any] = Field(default_factory=dict, description=(
        f"Event details: a JSON object of at most {MAX_EVENT_PAYLOAD_BYTES} bytes, nested at most "
        f"{EVENT_PAYLOAD_MAX_DEPTH} levels, at most {EVENT_PAYLOAD_MAX_KEYS} keys per object, strings of at most "
        f"{EVENT_PAYLOAD_MAX_STRING} characters, integers within ±{EVENT_PAYLOAD_MAX_INT}."))

    @field_validator("payload")
    @classmethod
    def _plain_json(cls, payload: dict[str, Any]) -> dict[str, Any]:
        try:  # bounds first: a deep value is refused before anything recurses into it
            strict_json.check(payload, max_depth=EVENT_PAYLOAD_MAX_DEPTH, max_keys=EVENT_PAYLOAD_MAX_KEYS,
                              max_string=EVENT_PAYLOAD_MAX_STRING, max_int=EVENT_PAYLOAD_MAX_INT)
        except strict_json.StrictJsonError as exc:
            raise ValueError(f"payload{'.' + exc.where if exc.where else ''}: {exc.reason}") from None
        if len(strict_json.dumps(payload, separators=(",", ":")).encode()) > MAX_EVENT_PAYLOAD_BYTES:
            raise ValueError(f"payload larger than {MAX_EVENT_PAYLOAD_BYTES} bytes")
        return payload


class EventsCreate(_RequestBody):
    events: list[EventCreate] = Field(max_length=100)


class HeartbeatUpdate(_RequestBody):
    client_time_ms: float | None = None


class WithdrawCreate(_RequestBody):
    """The participant withdraws from the study (``POST /api/p/{token}/withdraw``), having read on the page's
    confirmation what happens to their data."""

    confirm: Literal[True] = Field(description="true: the participant confirmed on the page")


class WithdrawalRead(BaseModel):
    """What withdrawing does in this study (config ``privacy``), for the page's confirmation; once withdrawn, who
    withdrew."""

    data: Literal["keep", "delete"] = Field(description=(
        "keep: the data stay, marked withdrawn and excluded, personal fields erased; delete: every row of the "
        "participant is deleted"))
    text: str | None = Field(None, description=(
        "The study's own confirmation text (config privacy.withdrawal_text); null: the page says what 'data' does"))
    by: Literal["participant", "researcher"] | None = Field(None, description=(
        "Who withdrew the session (null while it is not withdrawn)"))


class ScaleRead(BaseModel):
    min: float
    max: float
    step: float
    anchors: dict[int, str] | None = None
    unit: str | None = None


class OptionRead(BaseModel):
    value: str = Field(description="What the answer sends (and surveys.csv records) when this option is chosen")
    label: str = Field(description="What the participant reads")


class ItemRead(BaseModel):
    """An item as the page shows it (an attention check looks like any other item)."""

    id: str
    text: str
    kind: Literal["rating", "text", "choice"] = Field("rating", description=(
        "rating: one point of the questionnaire's scale; text: free text up to max_length characters; choice: one "
        "of options"))
    required: bool = Field(True, description="Whether the page can be sent without this item")
    max_length: int | None = Field(None, description="text items: the longest answer, in characters")
    options: list[OptionRead] | None = Field(None, description="choice items: the options, in order")


class QuestionnaireRead(BaseModel):
    id: str
    title: str = Field(description="The page's heading in plain words (the questionnaire's participant_title; the "
                                   "instrument's name stays in the configuration and the exports)")
    instructions: str
    language: str = Field("en", max_length=16, description=(
        "The language of the questionnaire's texts (BCP 47): the participant's, or the questionnaire's own when it "
        "has no translation for the participant's language"))
    about: str | None = Field(None, description='Which robot or shelf the questions are about, e.g. "These questions '
                                                'are about Robot A, the robot you have just worked with."')
    scale: ScaleRead | None = Field(None, description="The rating items' scale (null without rating items)")
    items: list[ItemRead]
    context: str
    draft: dict[str, float | str] = Field(default_factory=dict, description="Answers saved as a draft on this page "
                                                                      "(PUT answers/draft), restored after a reload")


class TutorialTryRead(BaseModel):
    try_number: int = Field(description="Which try of the guided practice teleoperation this is, from 1")
    max_tries: int


class TutorialRead(BaseModel):
    """The study's guided practice teleoperation (see ``PracticeConfig.tutorial``)."""

    max_tries: int
    time_limit_s: float


class TrialRead(BaseModel):
    """What the page shows for the current trial; the outcome only once it has happened."""

    practice: bool
    block: int
    block_label: str
    trial: int
    n_trials: int
    shelf: int
    complexity: Complexity
    robot_action: Literal["auto", "ask"]
    message: str
    stage: TrialStage = Field(description=(
        "presenting: the robot will try by itself and the page is bringing up the trial's scene; the decision "
        "window opens when the page reports it shown (POST trials/shown) or after timing.scene_wait_s"))
    human_action: Literal["rely", "intervene"] | None = None
    decision_window_s: float | None = None
    decision_ms_left: float | None = None
    scene_wait_ms_left: float | None = Field(None, description=(
        "While presenting: until the server opens the decision window without a report of the scene"))
    scene_stamp: str | None = Field(None, description=(
        "While presenting and in the decision window: the stamp of this trial's scene. The 3D view's client gets "
        "the scene node /scene_stamp_<stamp> after the rest of the trial's first picture; the 2-D view's scene "
        "(GET trials/scene) carries it too. A page reports the scene shown (POST trials/shown) with the stamp of "
        "a frame it drew"))
    scene_in_viewer: bool | None = Field(None, description=(
        "In the answer to a trial's start (POST trials/start) and to a 3d report (POST trials/shown): whether the "
        "session's 3D viewer holds the trial's scene with a client connected (frames the view draws from then on "
        "show it); null in other answers"))
    attempt_ms_left: float | None = None
    teleop_ms_left: float | None = None
    teleop_time_limit_s: float | None = Field(None, description="Time limit of this teleoperation (try), seconds")
    tutorial: TutorialTryRead | None = Field(None, description="Set while this teleoperation is the guided practice")
    target: str = Field(description='The item to collect, in words ("the purple can on the top shelf, far left")')
    hint: str | None = None
    expected_human_action: Literal["rely", "intervene"] | None = Field(
        None, description="What this practice trial asks the participant to do when the robot tries by itself")


class TrialSceneRead(BaseModel):
    """The current trial's scene for the 2-D helper view before teleoperation: the scene and the robot parked,
    in the teleoperation socket's terms (``server.teleop_messages``: ``SceneInfo``, ``WorldView``)."""

    scene: SceneInfo
    world: WorldView
    scene_stamp: str = Field(description="The scene's stamp (as trial.scene_stamp): what a report of this scene "
                                         "drawn carries (POST trials/shown, view 2d)")


class TrialResultRead(BaseModel):
    practice: bool
    block: int
    trial: int
    complexity: Complexity
    robot_action: str
    human_action: str
    outcome: str
    experience: str
    reward: float
    score: float
    teleop_success: bool | None = None
    failure_mode: str | None = None
    expected_human_action: Literal["rely", "intervene"] | None = Field(
        None, description="What this practice trial asked the participant to do (None: nothing asked)")
    hint_followed: bool | None = Field(None, description="Whether the participant did what the practice trial asked")


class CompletionRead(BaseModel):
    """How the session ended for the recruitment platform (experiment.outcomes): the code shown and the redirect."""

    outcome: Literal["completed", "declined", "screened_out", "timed_out", "withdrawn"] = Field(description=(
        "completed (debrief), declined (consent), screened_out (eligibility or attention checks), timed_out "
        "(the session was abandoned: inactive too long), withdrawn (by the participant or the researcher)"))
    code: str | None = Field(None, description="The outcome's completion code (null: the outcome has none)")
    redirect_url: str | None = Field(None, description="The outcome's redirect, placeholders filled in")
    compensation: float | None = Field(None, description="The payment, only when the study pays one itself "
                                                         "(config compensation); otherwise null and not shown")
    currency: str | None = None


class ScoredPartRead(BaseModel):
    """What the page says between the practice and the scored trials (phase ``practice_done``)."""

    decision_window_s: float = Field(description=(
        "Seconds the participant has to press Intervene when the robot says it will try by itself (config "
        "timing.decision_window_s)"))
    plays_for_points: bool = Field(description="Whether the scored trials score points (config task.rewards)")
    robots: list[str] = Field(description='The robots the participant supervises next, as the pages name them, in '
                                          'the order met ("Robot A", "Robot B")')
    n_trials: int = Field(description="Scored trials in all")


class DurationRead(BaseModel):
    """How long the whole study takes, from a quick to a slow participant (``experiment.duration``)."""

    low_minutes: int
    high_minutes: int
    text: str = Field(description='In words, e.g. "about 10–20 minutes"')


class StateRead(BaseModel):
    """Everything the participant page needs to render the current step."""

    token_valid: bool = True
    status: ParticipantStatus
    phase: str
    step: Step
    progress: float
    score: float
    study_title: str = Field(description="The study's name as participants see it (config texts.title)")
    language: str = Field("en", max_length=16, description=(
        "The session's language (BCP 47), chosen at the join: the page loads its words from /api/messages/{language}"))
    duration: DurationRead | None = Field(None, description="How long the study takes (on consent and instructions)")
    text: str | None = None
    video_url: str | None = None
    ready_to_start: dict[str, Any] | None = None
    trial: TrialRead | None = None
    last_trial: TrialResultRead | None = None
    questionnaire: QuestionnaireRead | None = None
    completion: CompletionRead | None = None
    final_score: float | None = Field(None, description=(
        "On the debrief of a study that plays for points (config task.rewards): the participant's final score, the "
        "total of the scored trials; null otherwise"))
    scored_part: ScoredPartRead | None = Field(None, description="Phase practice_done: what the scored part is like")
    timing: dict[str, float]
    teleop_time_limit_s: float = Field(description="Time limit of each teleoperation of the scored trials, seconds")
    tutorial: TutorialRead | None = Field(None, description="The guided practice teleoperation, if the study has it")
    server_time: datetime
    preview: bool = Field(False, description="An experimenter's preview session (the page says so; not data)")
    withdrawal: WithdrawalRead | None = Field(None, description=(
        "What the page's \"Withdraw from the study\" does to the data (config privacy); once withdrawn, who did"))


class MessagesRead(BaseModel):
    """One language's catalogue of participant-facing texts (``server.i18n``), as the pages load it."""

    language: str = Field(description="The catalogue's language (BCP 47): the one asked for, or English")
    direction: Literal["ltr", "rtl"] = Field(description="Its writing direction (the page's <html dir>)")
    plural_categories: list[str] = Field(description="The language's CLDR plural categories")
    fallback: list[str] = Field(description="The keys this language has no text for: their texts are English")
    messages: dict[str, str | dict[str, str]] = Field(description=(
        "Every text by key, with {name} placeholders; a plural text by CLDR plural category (one, other, …)"))


class LanguageRead(BaseModel):
    """The language a join of a study gets now (``experiment.languages.resolve_language``)."""

    language: str
    direction: Literal["ltr", "rtl"]


class JoinRead(BaseModel):
    token: str
    participant_url: str
    created: bool = Field(description="A new session (false: this browser's or recruitment session's own, resumed)")
    resume_key: str = Field(description="The resume key in effect (the one sent, or a new one): keep it and send it "
                                        "with the next join of this study to resume")
    state: StateRead


class OkRead(BaseModel):
    ok: bool = True


class ErrorResponse(BaseModel):
    """Every 4xx (and a full study's 503) answer: what is wrong, in words, and its kind (``server.errors``)."""

    model_config = ConfigDict(extra="allow")  # some errors add context, e.g. the session's ``step`` with a 409

    detail: str = Field(description="What is wrong, for a person to read")
    code: str = Field(description=("Kind of error: unauthorized, not_found, conflict, gone, too_large, invalid, "
                                   "rate_limited, address_busy, study_full"))
    message: str | None = Field(None, description=(
        "The catalogue key of the sentence the participant pages show for this error (GET /api/messages/{language})"))
    message_params: dict[str, Any] | None = Field(None, description="Values of that sentence's {placeholders}")
    problems: list[str] | None = Field(None, description="Every problem found (422)")
    retry_after_s: int | None = Field(None, description="Seconds to wait before trying again, as in the Retry-After "
                                                        "header (429, 503)")


_ERROR_MEANINGS = {
    400: "The request body could not be read (e.g. not UTF-8)",
    401: "Missing or invalid admin token",
    404: "No such study, participant or session link",
    409: ("The request does not fit the current state (out of order, repeated, already finished; a join of a study "
          "that has not opened yet: code study_not_open)"),
    410: "The study is closed or the session is over (abandoned, withdrawn)",
    413: "Request body too large",
    422: "Invalid request: every problem is listed",
    429: "Too many requests; retry after the Retry-After header's seconds",
    503: ("The study is full right now (code study_full: its cap on active participants is reached); the detail "
          "is a message for the participant; retry after the Retry-After header's seconds"),
}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries for the error statuses a route can answer with."""
    return {status: {"model": ErrorResponse, "description": _ERROR_MEANINGS[status]} for status in statuses}


# --- admin -------------------------------------------------------------------------------

class ReportAccessRead(BaseModel):
    """This browser may open report pages (``GET /api/admin/studies/{slug}/report.html``) until ``expires_at``."""

    path: str = Field(description="The cookie is sent to addresses under this path")
    expires_at: datetime



#: What a study can be created as (experiment.lifecycle).
if TYPE_CHECKING:  # a Literal of the vocabulary, built at run time: mypy cannot read it, and checks str
    InitialStatus = str
else:
    InitialStatus = Literal[*(s.value for s in INITIAL_STATUSES)]
#: A study config in a request body: as strictly typed as the schema reads (``validate_document``).
StudyConfigDocument = Annotated[StudyConfig, WrapValidator(
    lambda value, handler: validate_document(value) if isinstance(value, dict) else handler(value))]
Author = Annotated[str | None, Field(min_length=1, max_length=120, description=(
    "Who saves this version: the name the designer's user typed (default 'admin')"))]


class StudyCreate(_RequestBody):
    slug: str | None = Field(None, pattern=SLUG_REGEX, description="URL name of the study (default: from the title)")
    template: Literal[*TEMPLATES] | None = Field(  # type: ignore[valid-type]  # the names in TEMPLATES
        None, description="A built-in study design")
    config: StudyConfigDocument | None = Field(None, description="The study's configuration (give it or a template)")
    status: InitialStatus = Field("draft", description=(
        "Status of the new study: 'draft' (default: only preview sessions until POST .../open) or 'open' "
        "(participants can join at once)"))
    author: Author = None


class StudyConfigUpdate(_RequestBody):
    config: StudyConfigDocument = Field(description=(
        "The new configuration: a new version unless it equals the current one (then nothing changes)"))
    author: Author = None


class StudyDuplicateCreate(_RequestBody):
    """A new study with the current configuration of another (e.g. to run the next wave)."""

    slug: str | None = Field(None, pattern=SLUG_REGEX, description=(
        "URL name of the copy (default: the original's slug + '-copy'; an existing slug is a 409, so a retried "
        "request never makes a second copy)"))
    title: str | None = Field(None, min_length=1, max_length=200, description=(
        "The copy's title for researchers (default: the original's + ' (copy)')"))
    author: Author = None


class ConfigCheckCreate(_RequestBody):
    """A study configuration document to check without saving it (the designer's live validation)."""

    config: Any = Field(description="The document to check: any JSON; what is wrong with it is the answer")


class ConfigProblemRead(BaseModel):
    path: str = Field(description="Where, as a person reads it, e.g. blocks[1].schedule.n_low; '' for the document")
    loc: list[str | int] = Field(description=(
        "The same place as keys and indices into the document (union tags left out), e.g. ['blocks', 1, "
        "'schedule', 'n_low'], for a form to put the message beside its field"))
    message: str = Field(description="What is wrong there")


class BlockSummaryRead(BaseModel):
    name: str
    trials: int = Field(description="Scored trials in the block")
    n_low: float = Field(description="Low-complexity trials (expected number for a Bernoulli schedule)")
    n_high: float = Field(description="High-complexity trials (expected number for a Bernoulli schedule)")
    schedule: str = Field(description="The schedule in words")
    shelves: int = Field(description="Shelves (a shelf questionnaire follows each)")
    policy: str = Field(description=("The policy in words with its numbers, e.g. 'trust-aware: asks in high "
                                     "complexity when the belief of high trust ≤ 0.69; never asks in low complexity'"))
    questionnaires_after: list[str] = Field(description="Ids of the questionnaires asked after the block")


class InstrumentLanguageRead(BaseModel):
    language: str = Field(description="A language the instrument can be read in (BCP 47)")
    status: Literal["original", "published", "lab"] = Field(description=(
        "original: the instrument's own texts; published: a published translation (see citation); lab: the lab's "
        "own translation, not validated"))
    citation: str | None = Field(description="The publication of these texts (the instrument's, or the "
                                             "translation's); null for the lab's own")


class InstrumentRead(BaseModel):
    """A built-in instrument of the library (``experiment.instruments``), as a study can name it by id."""

    id: str
    title: str
    version: str | None = Field(description="Which form of the instrument, e.g. 14-item subscale")
    items: int = Field(description="Number of items")
    about_robot: bool = Field(description="Whether its questions are about the robot of the block just done")
    citation: str | None = Field(description="Where the instrument was published; null for trustlab's own")
    doi: str | None
    languages: list[InstrumentLanguageRead] = Field(description="Each language it can be read in, its own first")


class QuestionnaireUseRead(BaseModel):
    id: str
    title: str
    items: int = Field(description="Number of items")
    when: str = Field(description="When it is asked, in words")


class StudySummaryRead(BaseModel):
    """What a configuration amounts to, for a researcher to check before launch (``experiment.summary``)."""

    blocks: list[BlockSummaryRead]
    scored_trials: int = Field(description="Scored trials of every block together (practice not counted)")
    practice_trials: int = Field(description="Practice trials (not scored, not model data)")
    duration_low_minutes: int = Field(description="Expected duration for a quick participant")
    duration_high_minutes: int = Field(description="Expected duration for a slow participant")
    duration: str = Field(description="The expected duration in words")
    counterbalance: str = Field(description="How block orders are assigned, in words")
    orders: list[list[str]] = Field(description="The block orders participants are assigned, by block name")
    questionnaires: list[QuestionnaireUseRead] = Field(description="The questionnaires asked and when")
    payment: str = Field(description="What a participant is paid, in words")


class ConfigCheckRead(BaseModel):
    valid: bool = Field(description="Whether the document is a study configuration that can run")
    problems: list[ConfigProblemRead] = Field(description="Every problem found (empty when valid)")
    warnings: list[ConfigProblemRead] = Field(default_factory=list, description=(
        "What a valid study may still want to fix, placed as problems are: a questionnaire asked without a "
        "translation for a language the study offers (its participants of that language read it untranslated)"))
    summary: StudySummaryRead | None = Field(description="The summary of a valid document; null when invalid")


class StudyVersionRead(BaseModel):
    version: int
    created_at: datetime
    author: str = Field(description="Who saved it ('admin' when no name was given)")
    config_hash: str
    participants: int = Field(description="Participants who ran (or run) under this version")


class ConfigChangeRead(BaseModel):
    path: str = Field(description="Where, e.g. blocks[1].policy.kind ('' for the whole document)")
    kind: Literal["changed", "added", "removed"]
    before: Any = Field(None, description="The value before (null when added)")
    after: Any = Field(None, description="The value after (null when removed)")


class ConfigDiffRead(BaseModel):
    from_version: int
    to_version: int
    changes: list[ConfigChangeRead] = Field(description="Every difference, in document order")


class StudyRead(BaseModel):
    slug: str
    title: str
    status: str = Field(description=("draft (only preview sessions), open (taking participants) or closed (no new "
                                     "participants; running sessions finish)"))
    version: int
    config_hash: str
    join_url: str
    participants: dict[str, int] = Field(description="Participants per status, preview sessions left out")
    preview_sessions: int = Field(0, description="The experimenter's preview sessions (not counted in participants)")
    max_active_participants: int | None = Field(description=(
        "The current version's cap on active participants (config recruitment.max_active_participants); null: none"))
    refused_joins: int = Field(description="New joins refused because the study was full (events join_refused)")
    created_at: datetime
    personal_data: PersonalDataRead | None = Field(None, description=(
        "Withdrawal and retention of participants' personal data (config privacy), and what was erased"))


class StudyDetailRead(StudyRead):
    config: dict[str, Any]


class QualityFlagRead(BaseModel):
    code: str
    detail: str


class ParticipantRead(BaseModel):
    public_id: str
    external_id: str | None
    status: ParticipantStatus
    phase: str
    block: int | None
    block_name: str | None
    trial: int | None
    score: float
    belief: float | None = Field(description=(
        "Belief that trust is high now, under the study's model (K ≥ 3 trust states: of the highest state)"))
    block_order: list[str] | None
    excluded: bool
    exclusion_reason: str | None
    completion_code: str | None
    version: int
    created_at: datetime
    last_seen_at: datetime
    belief_history: list[float] = Field(default_factory=list,
                                        description=("Belief that trust is high after each scored trial, in "
                                                     "order (K ≥ 3 trust states: of the highest state)"))
    flags: list[QualityFlagRead] = Field(default_factory=list, description="Data-quality hints (experiment.quality)")
    preview: bool = Field(False, description=("An experimenter's preview session: not data (left out of "
                                              "counterbalancing, exports, reports and fits by default); deletable"))
    attention_failures: int = Field(0, description="Failed attention checks (instructed-response items)")
    outcome: str | None = Field(None,
                                description="completed | declined | screened_out | timed_out | withdrawn "
                                            "(experiment.outcomes); null while active")


class PreviewRead(BaseModel):
    """A new preview session: open ``participant_url`` to go through the study as a participant would."""

    public_id: str = Field(description="The preview session's participant id (marked preview in the table)")
    token: str = Field(description="The session token (as a join returns it): the participant page is /p/{token}")
    participant_url: str = Field(description="The participant page of the preview session")


class DeletedRead(BaseModel):
    deleted: int = Field(description=("Sessions deleted by this request (0: nothing left to delete, e.g. a repeated "
                                      "request)"))


class ParticipantDelete(_RequestBody):
    """Why a real participant's data are deleted (e.g. "asked by email on 3 March"): required for a real participant,
    kept in the audit log (write no personal data in it); a preview session needs none."""

    reason: str | None = Field(None, min_length=1, max_length=2000)


class PersonalDataRead(BaseModel):
    """The study's rules for its participants' data (current config ``privacy``) and what retention has erased."""

    withdrawal: Literal["keep", "delete"] = Field(description="What withdrawal does to a participant's data")
    retention: str = Field(description='The retention rule in words, e.g. "erased 30 days after each session ends"')
    erase_on: str | None = Field(None, description="The date (YYYY-MM-DD) the rule erases every ended session's "
                                                   "personal fields, if it gives one")
    erased_sessions: int = Field(description="Sessions whose personal fields are erased (retention or withdrawal)")
    last_erased_at: datetime | None = Field(None, description="When personal fields were last erased")
    deleted_participants: int = Field(0, description="Participants whose data were deleted (audit participant.delete)")


class ServerLoadRead(BaseModel):
    """How this server process is keeping up over the last minute (``server.loadmeter``). With several workers
    (``serve --workers``), the figures are those of the worker that answers the admin API (worker 0)."""

    status: Literal["fault", "ok", "busy", "overloaded", "starting", "off"] = Field(description=(
        "fault: the server contained failures in its background loops in the last minutes (every other participant "
        "went on; see the server log); ok: the 3D views show every world update; busy: they skip a few so that "
        "requests and teleoperation keep "
        "their pace; overloaded: they skip many or the world loop runs slow, and requests slow down; starting: "
        "too early to tell; off: the process runs no world loop"))
    message: str = Field(description="What the status means and what to do, in words")
    window_s: float = Field(description="Seconds the figures cover (up to a minute; 0 while starting)")
    world_hz: float = Field(description="The world loop's rate (TRUSTLAB_WORLD_HZ)")
    world_ticks_per_s: float | None = Field(description="World updates a second in the window (None while starting)")
    late_tick_share: float | None = Field(description=(
        "Share of the world's ticks that started 0.3 of a period or more after their time (10 ms at 30 Hz): the "
        "event loop was held up"))
    longest_tick_delay_ms: float | None = Field(description=(
        "The latest start of a world tick in the window: the longest the event loop was held up, about"))
    view_skipped_share: float | None = Field(description=(
        "Share of the world's ticks that the 3D views skipped (a lower frame rate, nothing lost)"))
    viewers: int = Field(description="3D view sockets open")
    attempts_playing: int = Field(description="Autonomous attempts being played back")
    arms_teleoperated: int = Field(description="Arms under teleoperation")
    faults_recent: int = Field(0, description=(
        "Failures the server contained in the last five minutes (one participant's step in the world loop, one "
        "participant's sweep, a log write, a loop restarted): ``server.faults``"))


class ParticipantUpdate(_RequestBody):
    """Exclude a participant, include them again or withdraw their data: why (the audit log keeps it)."""

    reason: str = Field(min_length=1, max_length=2000)


class TemplateRead(BaseModel):
    name: str
    config: dict[str, Any]


# --- fitted models (the model registry) -----------------------------------------------------

class FitCreate(_RequestBody):
    restarts: JsonInt = Field(20, ge=1, le=1000, description="Random restarts of EM.")
    seed: JsonInt = Field(0, ge=0, le=2**32 - 1, description="Seed of the random restarts.")
    p_high: float | None = Field(None, ge=0, le=1, description="P(high complexity) the trust-aware policy is solved "
                                 "for; default: the high-complexity fraction of the evaluation design (0.5).")
    include_preview: bool = Field(False, description=(
        "Fit the experimenter's preview sessions too (left out by default: they are not data)."))
    # the bounds before the validator: after it, pydantic writes them as "ge"/"le", which JSON Schema does not know
    states: Annotated[list[Annotated[int, Field(ge=STATES_MIN, le=STATES_MAX), WHOLE_FLOAT_AS_INT]],
                      Field(min_length=1, max_length=STATES_MAX - STATES_MIN + 1,
                            json_schema_extra={"uniqueItems": True})] | None = Field(None, description=(
        f"Numbers of trust states ({STATES_MIN}…{STATES_MAX}, distinct) to compare by cross-validation by "
        "participant; the model is the number the data support (docs/analysis.md). One number: a model of that "
        "many states. Absent: the paper's two-state model"))
    folds: JsonInt = Field(SELECTION_FOLDS, ge=2, le=20, description=(
        "Folds of the cross-validation by participant (when several numbers of states are compared, or with "
        "ratings); the study needs at least as many participants"))
    with_ratings: bool = Field(False, description=(
        "Use the shelf questionnaire's trust ratings as a second observation of the trust state, and compare the "
        "model with the one fitted without them on held-out reliance (docs/analysis.md); 409 when the study has "
        "no ratings"))

    @field_validator("states")
    @classmethod
    def _distinct_states(cls, states: list[int] | None) -> list[int] | None:
        if states is None:
            return None
        if len(set(states)) != len(states):
            raise ValueError(f"the numbers of trust states must be distinct, got {states}")
        return sorted(states)


class ParameterEstimateRead(BaseModel):
    """One IOHMM parameter: estimate, Laplace standard error and how well the data determine it."""

    name: str  # e.g. transitions.high.auto.negative.from_low (experiment.iohmm.PARAMETER_NAMES)
    value: float | None  # null: not exercised by the data
    stderr: float | None  # null unless status is "estimated"
    status: Literal["estimated", "boundary", "not_exercised", "unidentified"]


class FitProgressRead(BaseModel):
    iterations_done: int  # EM iterations run so far (over all restarts' stages); comparing numbers of trust
    # states: the share of the comparison and the final fit done, in units of the same budget
    iterations_max: int  # the iteration budget; a converged fit ends below it and then reports it as done


class InterventionRateRead(BaseModel):
    rate: float | None  # null: no autonomous attempts in this complexity
    interventions: int
    auto_trials: int


class AgnosticBaselineRead(BaseModel):
    """The trust-agnostic policy from the same data: observed rates -> expected rewards -> actions."""

    rates: dict[str, InterventionRateRead]  # by complexity (low, high)
    expected_reward: dict[str, dict[str, float | None]] | None  # {"auto": {low, high}, "ask": {low, high}}
    action: dict[str, Literal["auto", "ask"]] | None  # by complexity
    error: str | None  # why there is no baseline (a complexity without autonomous attempts)


class PolicyThresholdsRead(BaseModel):
    """The trust-aware policy solved for ``p_high`` (as ``trustlab policy --json``)."""

    p_high: float
    threshold: dict[str, float | None] | None = None  # belief of high trust above which the robot acts alone
    action: dict[str, Literal["auto", "ask"] | None] | None = None  # the action where it does not depend on belief
    threshold_shaped: dict[str, bool] | None = None
    switches: dict[str, list[float]] | None = None
    myopic_threshold: dict[str, float | None] | None = None
    grid: int | None = None
    discount: float | None = None
    belief_update: str | None = None
    error: str | None = None  # why the policy cannot be solved for this model
    n_states: int | None = None  # set for a model of 3 or more trust states (no thresholds: the summary below)
    ask_share: dict[str, float] | None = None  # K ≥ 3: by complexity, the share of the belief grid where it asks


class SelectionCandidateRead(BaseModel):
    """One number of trust states compared: its fit on everyone and its cross-validated score."""

    n_states: int
    loglik: float  # of the fit on all participants
    n_free: int  # free parameters the data inform
    bic: float  # −2 L + p log(trials)
    icl: float  # BIC + 2 × the entropy of the posterior over state paths
    held_out_per_trial: float  # mean over folds of the held-out log-likelihood per trial
    held_out_se: float  # its standard error across folds


class RatingsComparisonRead(BaseModel):
    """The model fitted with the trust ratings against the same number of states without them, both scored on
    the held-out participants' reliance (``experiment.model_selection.RatingsComparison``)."""

    n_states: int
    n_ratings: int
    held_out_with_ratings: float  # held-out reliance log-likelihood per trial
    held_out_without_ratings: float
    difference_per_trial: float  # with minus without
    difference_se: float  # paired by participant
    verdict: str  # one sentence


class RatingsRead(BaseModel):
    """The rating emission of a model fitted with trust ratings: a beta-binomial per state."""

    n_ratings: int
    scale: list[int]  # [minimum, maximum] of the rating
    mean_rating: list[float]  # per state, lowest reliance first
    sd_rating: list[float]  # standard deviation of a state's ratings
    alpha: list[float]
    beta: list[float]
    comparison: RatingsComparisonRead | None = None


class SelectionRead(BaseModel):
    """How the number of trust states was chosen (``experiment.model_selection``; docs/analysis.md)."""

    candidates: list[SelectionCandidateRead]
    chosen: int  # the number of trust states of the model
    reason: str  # one sentence: why that number
    folds: int
    seed: int
    se_rule: float | None = None  # standard errors of the paired difference an extra state must beat
    n_participants: int | None = None
    n_trials: int | None = None


class ModelProvenanceRead(BaseModel):
    study: str
    study_id: int
    study_versions: list[int]
    participants: list[str]  # public ids, in fitting order
    n_participants: int
    n_trials: int
    restarts: int
    seed: int
    p_high: float
    data_hash: str  # SHA-256 of the model columns of the rows fitted on
    code_version: str  # trustlab version that fitted it


class ModelRead(BaseModel):
    id: int
    status: Literal["running", "done", "failed"]
    error: str | None
    progress: FitProgressRead
    loglik: float | None
    converged: bool | None
    content_hash: str | None  # SHA-256 of the canonical JSON of the model document
    parameters: list[ParameterEstimateRead]  # empty until done
    n_states: int | None = None  # of the fitted model (null until done)
    selection: SelectionRead | None = Field(None, description=(
        "The comparison of numbers of trust states that chose this model; null when one number was fitted"))
    ratings: RatingsRead | None = Field(None, description=(
        "The trust ratings' emission and what they add on held-out reliance; null when fitted without ratings"))
    policy: PolicyThresholdsRead | None
    agnostic: AgnosticBaselineRead | None
    provenance: ModelProvenanceRead
    evaluation_studies: list[str]  # slugs of the studies deployed from this model
    evaluation_blocked: str | None = Field(None, description=(
        "Why no policy-evaluation study can be made of this model (POST .../evaluation-study would answer 409 with "
        "it): the fit is not done, the trust-agnostic baseline lacks a rate, or the trust-aware policy cannot be "
        "solved. null: it can"))
    created_at: datetime
    finished_at: datetime | None


EvaluationTemplate = Literal[*EVALUATION_TEMPLATES]  # type: ignore[valid-type]  # its names, at run time


class EvaluationStudyCreate(_RequestBody):
    slug: str = Field(pattern=SLUG_REGEX, description="URL name of the new study")
    title: str | None = Field(None, min_length=1, max_length=200)
    template: EvaluationTemplate = "policy-evaluation"
    p_high: float | None = Field(None, ge=0, le=1, description="Default: the p_high the model was solved for.")
    status: InitialStatus = Field("draft", description=(
        "'draft' (default: open it with POST /api/admin/studies/{slug}/open) or 'open' (participants can join at "
        "once; a repeated request opens a draft it created, never reopens a closed study)"))
