"""Questionnaires as data: scales, items, answer validation, reverse coding, scores (SPEC §5).

A lab adds its own questionnaire by writing a ``Questionnaire`` document in the
study configuration. Built in (``BUILTIN_QUESTIONNAIRES``, by id), each with its
citation, version and scoring rule on the document itself; a study uses one by
naming its id (``questionnaires_before``, a block's ``questionnaires_after``,
``shelf_questionnaire``), and its configuration then holds a copy
(``StudyConfig``); the default questionnaires of a study are the shelf questions
and ``SCHAEFER_14``:

- ``SHELF_TRUST_RELIANCE``: the trust and reliance questions asked after each
  shelf (paper §4.4–4.5 and appendix; after Lee & Moray 1992, 1994), each on
  an 11-point 0–10 scale. Not combined into a score.
- ``TPS_HRI_40`` and ``SCHAEFER_14``: the Trust Perception Scale–HRI and its
  14-item subscale, K. E. Schaefer (2016), "Measuring trust in human robot
  interactions: Development of the 'Trust Perception Scale-HRI'", in *Robust
  Intelligence and Trust in Autonomous Systems*, pp. 191–218, Springer,
  doi:10.1007/978-1-4899-7668-0_10. Each item completes "What percentage of
  the time will this robot …" and is rated 0–100 % in steps of 10; the score
  is the mean of the (reverse-coded) item ratings (paper §5.3). The subscale's
  items are the 40-item scale's own ``Item`` objects (one definition each,
  ``TPS_HRI_ITEMS``). Reverse-coded: "have errors", "be unresponsive",
  "malfunction" (both versions), and in the 40-item version also "require
  frequent maintenance" and "be incompetent".
- ``JIAN_TRUST_CHECKLIST``: the 12-item Checklist for Trust between People and
  Automation, J.-Y. Jian, A. M. Bisantz & C. G. Drury (2000), "Foundations for
  an empirically determined scale of trust in automated systems",
  *International Journal of Cognitive Ergonomics* 4(1), 53–71,
  doi:10.1207/S15327566IJCE0401_04. 7-point scale, 1 "not at all" to
  7 "extremely"; items 1–5 are the distrust items and are reverse-coded, so
  the score (the mean) is a trust score on 1–7.
- ``MUIR_TRUST_RATING``: one overall trust rating, after B. M. Muir (1989),
  *Operators' trust in and percentage of time spent using the automatic
  controllers in supervisory process control task*, PhD thesis, University of
  Toronto, and B. M. Muir & N. Moray (1996), "Trust in automation. Part II.
  Experimental studies of trust and human intervention in a process control
  simulation", *Ergonomics* 39(3), 429–460, doi:10.1080/00140139608964474.
  Rated 0–100; the score is the rating.

What was checked, and against what (December 2026, public web pages and
public repositories only; the chapter, the articles and the thesis themselves
could not be read):

- TPS-HRI: the 0–100 % rating, 40 items, a 14-item subscale and a percentage
  score are in the chapter's abstract (Mendeley catalogue page). The HRI Scale
  Database's page on the scale
  (hriscaledatabase.psychology.gmu.edu/trust/2024/10/31/trustschaefer.html)
  shows the stem "What % of the time will this robot be…" and, in this order,
  its items "considered part of the team", "responsible", "supportive",
  "incompetent", "dependable" (subscale), "friendly", "reliable"; the rest of
  its list could not be read (a later version of the page withholds the items
  pending the author's permission), and it notes that the chapter's text
  names only 11 of the 14 subscale items. The other 33 item texts, the order
  and the 40-item reverse-coded set were checked only against two independent
  study implementations on GitHub (a PHP form and a jsPsych trial), which
  agree on all 40 texts and on the five reverse-coded items; the PHP form also
  marks as the subscale the same 14 items as ``SCHAEFER_14``. Not verified
  against the chapter: the exact wording of those 33 items (the two differ on
  "make sensible decision(s)"; the plural is used here), and whether the
  chapter's scoring instructions reverse-code any further item (e.g. "be led
  astray by unexpected changes in the environment", not reverse-coded here nor
  in either implementation).
- Jian et al.: the 12 items, their order and that items 1–5 are the
  negatively worded (distrust) ones, against Table 2 of an article quoting the
  scale (pmc.ncbi.nlm.nih.gov/articles/PMC9945264/table/tab2; wording adapted
  there to its system, items marked − and +); the "the system" wording as in
  several independent implementations on GitHub; the DOI as several reference
  lists cite it. The 1 "not at all" – 7 "extremely" anchors agree with those
  implementations but were not checked against the article.
- Muir: the thesis title (as a 2020 HFES review's reference list gives it) and
  the article's citation and DOI. Not verified: the published scale (0–100 as
  the brief says; whether it was a line or a numbered scale, its step and its
  anchors are not known here, so steps of 10 — 11 buttons, as the TPS-HRI's
  percentages; whole points made a page of 101 buttons — and the shelf
  questions' "Not at all" / "Completely" labels are used; a lab that needs
  another step defines its own questionnaire) and the question's wording, which is
  ours ("How much do you trust the robot?"; Muir & Moray asked about the
  pasteuriser plant's automatic controllers).

Besides the published instruments, two of trustlab's own (our wording, no
citation): ``DEMOGRAPHICS`` (age band, gender, experience with robots and
with video games; single-choice items, each with "Prefer not to say") and
``COMMENTS`` (one optional free-text item).

Item kinds (``Item.kind``): ``rating`` (a point of the questionnaire's scale;
the only kind that is reverse-coded and scored), ``text`` (free text up to
``max_length`` characters) and ``choice`` (one of ``options``, each a stable
``value`` that is exported and a ``label`` that is shown). Any item may be
optional (``required: false``). An item with ``instructed_response`` is an
attention check: its text tells the participant what to answer, any other
answer is a failure (``experiment.attention``), and it is not scored. A choice
item with ``screen_out_options`` is an eligibility question. Rating answers
are stored as numbers (``Answer.value``/``scored_value``), text and choice
answers as text (``Answer.text``: a choice's option value).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from experiment import defaults

#: Relative tolerance when checking that a value lies on a scale step.
_STEP_TOLERANCE = 1e-9


def _missing(value: object) -> bool:
    """Provenance left out is left out of dumps too: a document without it keeps its config hash."""
    return value is None


class AnswerError(ValueError):
    """Answers that do not fit a questionnaire; ``problems`` lists every reason."""

    def __init__(self, questionnaire_id: str, problems: list[str]) -> None:
        self.problems = problems
        super().__init__(f"invalid answers to {questionnaire_id!r}: " + "; ".join(problems))


#: An anchor's scale point: a JSON document's keys are strings ("10"), also when it is validated strictly.
_ScalePoint = Annotated[int, BeforeValidator(lambda key: int(key) if isinstance(key, str) and key.lstrip("-").isdigit()
                                             else key)]


class Scale(BaseModel):
    """A rating scale: the values min, min + step, …, max."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min: float = Field(description="Lowest value of the scale")
    max: float = Field(description="Highest value of the scale")
    step: float = Field(gt=0, description="Distance between neighbouring values")
    anchors: dict[_ScalePoint, str] | None = Field(None, description=(
        "Labels shown at some scale points, by value"))
    unit: str | None = Field(None, description='Unit shown after the values, e.g. "%"; null: none')

    @model_validator(mode="after")
    def _consistent(self) -> Scale:
        if not self.min < self.max:
            raise ValueError(f"scale min ({self.min}) must be less than max ({self.max})")
        if not _is_whole((self.max - self.min) / self.step):
            raise ValueError(f"step {self.step} does not divide the range {self.min}–{self.max}")
        for point in self.anchors or {}:
            if self.problem(point) is not None:
                raise ValueError(f"anchor {point}: {self.problem(point)}")
        return self

    @property
    def n_points(self) -> int:
        return round((self.max - self.min) / self.step) + 1

    def points(self) -> list[float]:
        """Every allowed value, ascending."""
        return [self.min + i * self.step for i in range(self.n_points)]

    def problem(self, value: object) -> str | None:
        """Why ``value`` is not an allowed answer, or None when it is."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return f"{value!r} is not a number"
        number = float(value)
        if not math.isfinite(number):
            return f"{number} is not a finite number"
        if not self.min <= number <= self.max:
            return f"{number:.10g} is off the scale {self.min:g}–{self.max:g}"
        if not _is_whole((number - self.min) / self.step):
            return f"{number:.10g} is not on a step of {self.step:g} from {self.min:g}"
        return None


def _is_whole(x: float) -> bool:
    return abs(x - round(x)) <= _STEP_TOLERANCE * max(1.0, abs(x))


ItemKind = Literal["rating", "text", "choice"]
_IDENTIFIER = r"^[A-Za-z][A-Za-z0-9_]*$"
#: Characters a free-text answer may hold besides printable ones (a database refuses NUL; the rest are noise).
_TEXT_WHITESPACE = frozenset("\n\r\t")


class ChoiceOption(BaseModel):
    """One option of a single-choice item."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    value: str = Field(pattern=_IDENTIFIER, max_length=64, description=(
        "Stable identifier of the option: what surveys.csv records (column text), whatever the label says"))
    label: str = Field(min_length=1, max_length=300, description="What the participant reads")


class Item(BaseModel):
    """One question. ``id`` names its column in exports, so it is an identifier.

    Every field past ``reverse_coded`` is left out of dumps at its default, so a document written before item kinds
    existed keeps its config hash.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(pattern=_IDENTIFIER, max_length=64, description="The item's identifier, its name in exports")
    text: str = Field(min_length=1, description="The question or statement as participants read it")
    reverse_coded: bool = Field(False, description="Negatively worded: scored as max + min - value")
    kind: ItemKind = Field("rating", exclude_if=lambda kind: kind == "rating", description=(
        "rating: a point of the questionnaire's scale (the only kind that enters the score); text: free text; "
        "choice: one of options"))
    required: bool = Field(True, exclude_if=lambda required: required is True, description=(
        "Whether the page can be sent without an answer to this item"))
    max_length: int | None = Field(None, exclude_if=_missing, ge=1, le=defaults.TEXT_ANSWER_LIMIT, description=(
        f"text items: the longest answer, in characters (default {defaults.TEXT_ANSWER_MAX_LENGTH})"))
    options: list[ChoiceOption] | None = Field(None, exclude_if=_missing, min_length=2, max_length=50, description=(
        "choice items: the options, in the order shown"))
    instructed_response: float | str | None = Field(None, exclude_if=_missing, description=(
        "Makes the item an attention check (an instructed-response item, not scored): the answer its text tells "
        "the participant to give, a scale value (rating) or an option's value (choice). Any other answer is a "
        "failure, recorded and counted (study config attention)"))
    screen_out_options: list[str] | None = Field(None, exclude_if=_missing, min_length=1, description=(
        "choice items: an eligibility question. Choosing one of these option values ends the session at once as "
        "screened out, whatever the study's attention rule"))

    @model_validator(mode="after")
    def _fields_fit_kind(self) -> Item:
        problems = _kind_problems(self)
        if problems:
            raise ValueError(f"item {self.id!r}: " + "; ".join(problems))
        return self

    @property
    def is_attention_check(self) -> bool:
        return self.instructed_response is not None

    @property
    def scored(self) -> bool:
        """Whether the item enters the questionnaire's score: a rating that is not an attention check."""
        return self.kind == "rating" and not self.is_attention_check

    @property
    def text_limit(self) -> int:
        return self.max_length or defaults.TEXT_ANSWER_MAX_LENGTH

    @property
    def option_values(self) -> list[str]:
        return [option.value for option in self.options or []]


def _kind_problems(item: Item) -> list[str]:
    """What does not fit the item's kind (every problem, in words)."""
    allowed = {"rating": {"reverse_coded", "instructed_response"}, "text": {"max_length"},
               "choice": {"options", "instructed_response", "screen_out_options"}}[item.kind]
    present = {"reverse_coded": item.reverse_coded, "max_length": item.max_length is not None,
               "options": item.options is not None, "instructed_response": item.is_attention_check,
               "screen_out_options": item.screen_out_options is not None}
    problems = [f"{name} does not apply to a {item.kind} item" for name, set_ in present.items()
                if set_ and name not in allowed]
    if item.kind == "choice":
        problems += _choice_problems(item)
    elif item.kind == "rating" and isinstance(item.instructed_response, str):
        problems.append(f"instructed_response of a rating item must be a scale value, not {item.instructed_response!r}")
    if item.is_attention_check and not item.required:
        problems.append("an attention check (instructed_response) must be required")
    if item.is_attention_check and item.reverse_coded:
        problems.append("an attention check is not scored, so it cannot be reverse_coded")
    if item.is_attention_check and item.screen_out_options:
        problems.append("an item is either an attention check or an eligibility question, not both")
    return problems


def _choice_problems(item: Item) -> list[str]:
    values = item.option_values
    if not values:
        return ["a choice item needs options"]
    repeated = sorted({v for v in values if values.count(v) > 1})
    problems = [f"option values must be unique; repeated: {', '.join(repeated)}"] if repeated else []
    if item.is_attention_check and item.instructed_response not in values:
        problems.append(f"instructed_response {item.instructed_response!r} is not an option value "
                        f"({', '.join(values)})")
    unknown = [v for v in item.screen_out_options or [] if v not in values]
    if unknown:
        problems.append(f"screen_out_options {unknown} are not option values ({', '.join(values)})")
    elif item.screen_out_options and set(item.screen_out_options) == set(values):
        problems.append("screen_out_options cannot be every option (nobody could take part)")
    return problems


class Questionnaire(BaseModel):
    """A titled list of items sharing one scale and one scoring rule."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=64, description=(
        "The questionnaire's identifier, by which the study names it"))
    title: str = Field(min_length=1, description="The instrument's name, for researchers (admin page, report)")
    participant_title: str | None = Field(None, min_length=1, max_length=120, description=(
        "The page's heading as participants see it, in plain words; default: the title"))
    instructions: str = Field(description="Shown above the items")
    scale: Scale | None = Field(None, exclude_if=_missing, description=(
        "The rating items' scale; a questionnaire without rating items (e.g. demographics) has none"))
    items: list[Item] = Field(min_length=1, description="The questions, in the order asked")
    scoring: Literal["mean", "none"] = Field("mean", description=(
        'How the score is computed: "mean" of the (reverse-coded) ratings, or "none"'))
    citation: str | None = Field(None, exclude_if=_missing, min_length=1, description=(
        "Where the instrument was published, as a full reference (authors, year, title, venue, pages)"))
    doi: str | None = Field(None, exclude_if=_missing, pattern=r"^10\.\d{4,9}/\S+$", description=(
        'The publication\'s DOI, without "https://doi.org/", e.g. "10.1007/978-1-4899-7668-0_10"'))
    version: str | None = Field(None, exclude_if=_missing, min_length=1, max_length=120, description=(
        'Which form of the instrument this is, e.g. "40-item" or "14-item subscale"'))
    scoring_rule: str | None = Field(None, exclude_if=_missing, min_length=1, description=(
        "How the score is computed, in words (which items are reverse-coded; mean or sum), for whoever reads "
        "the configuration"))

    @model_validator(mode="after")
    def _unique_item_ids(self) -> Questionnaire:
        ids = [item.id for item in self.items]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"item ids must be unique; repeated: {', '.join(duplicates)}")
        return self

    @model_validator(mode="after")
    def _ratings_fit_scale(self) -> Questionnaire:
        ratings = [item for item in self.items if item.kind == "rating"]
        if ratings and self.scale is None:
            raise ValueError(f"rating items need the questionnaire's scale; no scale for {ratings[0].id!r}")
        for item in ratings:
            if item.is_attention_check and (problem := self.scale.problem(item.instructed_response)) is not None:
                raise ValueError(f"item {item.id!r}: instructed_response {problem}")
        if self.scoring == "mean" and not any(item.scored for item in self.items):
            raise ValueError("scoring 'mean' needs at least one rating item that is not an attention check; "
                             "use scoring 'none'")
        return self

    @property
    def heading(self) -> str:
        """What the participant sees as the page's title."""
        return self.participant_title or self.title

    @property
    def item_ids(self) -> list[str]:
        return [item.id for item in self.items]

    def item(self, item_id: str) -> Item:
        for item in self.items:
            if item.id == item_id:
                return item
        raise KeyError(f"questionnaire {self.id!r} has no item {item_id!r}")


#: An answer as it comes in and is kept: a number for a rating item, text for a text or choice item.
AnswerValue = float | str


def validate_answers(q: Questionnaire, answers: Mapping[str, object], *,
                     partial: bool = False) -> dict[str, AnswerValue]:
    """Check every answer against its item.

    Returns the answers in item order: ratings as floats, text answers with surrounding white space removed, choices
    as the option's value. An empty text (or choice) answer counts as no answer, and an optional item without an
    answer is left out. Raises ``AnswerError`` listing every missing required item, unknown item and answer that
    does not fit its item (not a number, off the scale or between steps, not text, too long, unknown option).
    ``partial`` allows missing items (a draft of a page being filled in).
    """
    given = {k: v.strip() if isinstance(v, str) else v for k, v in answers.items()}
    given = {k: v for k, v in given.items() if v != ""}
    problems = [] if partial else [f"missing item {item.id!r}" for item in q.items
                                   if item.required and item.id not in given]
    problems += [f"unknown item {k!r}" for k in given if k not in q.item_ids]
    problems += [f"item {item.id!r}: {p}" for item in q.items if item.id in given
                 if (p := answer_problem(q, item, given[item.id])) is not None]
    if problems:
        raise AnswerError(q.id, problems)
    return {item.id: float(given[item.id]) if item.kind == "rating" else given[item.id]  # type: ignore[arg-type]
            for item in q.items if item.id in given}


def answer_problem(q: Questionnaire, item: Item, value: object) -> str | None:
    """Why ``value`` is not an answer to ``item``, or None when it is."""
    if item.kind == "rating":
        assert q.scale is not None  # a questionnaire with rating items has a scale (validated)
        return q.scale.problem(value)
    if not isinstance(value, str):
        shown = f"{value:g}" if isinstance(value, float) else repr(value)  # JSON 3 arrives as 3.0
        return (f"{shown} is not text" if item.kind == "text"
                else f"{shown} is not one of the options ({', '.join(item.option_values)})")
    if item.kind == "choice":
        return None if value in item.option_values else (
            f"unknown option {value!r}; the options are {', '.join(item.option_values)}")
    if len(value) > item.text_limit:
        return f"the answer has {len(value)} characters, more than the {item.text_limit} allowed"
    if any(not c.isprintable() and c not in _TEXT_WHITESPACE for c in value):
        return "the answer holds control characters"
    return None


def reverse_code(q: Questionnaire, item: Item | str, value: int | float) -> float:
    """``max + min − value`` for a reverse-coded item, ``value`` otherwise (rating items only)."""
    item = q.item(item) if isinstance(item, str) else item
    if item.kind != "rating" or q.scale is None:
        raise AnswerError(q.id, [f"item {item.id!r}: a {item.kind} item has no scale to reverse-code on"])
    problem = q.scale.problem(value)
    if problem is not None:
        raise AnswerError(q.id, [f"item {item.id!r}: {problem}"])
    return float(q.scale.max + q.scale.min - value) if item.reverse_coded else float(value)


def answer_columns(q: Questionnaire, item: Item, value: AnswerValue) -> dict[str, float | str | None]:
    """How a validated answer is stored (``Answer.value``, ``scored_value``, ``text``): a rating's value and its
    reverse-coded value (none for an attention check: it is not scored); a text or choice answer as text."""
    if item.kind != "rating":
        return {"value": None, "scored_value": None, "text": str(value)}
    number = float(value)
    return {"value": number, "scored_value": reverse_code(q, item, number) if item.scored else None, "text": None}


def score(q: Questionnaire, answers: Mapping[str, object]) -> float:
    """The mean of the reverse-coded answers to the scored items (paper §5.3), on the scale's units.

    Only rating items that are not attention checks are scored; text and choice items and attention checks are
    validated but left out. Raises ``AnswerError`` for invalid answers (or when no scored item is answered) and
    ``ValueError`` when the questionnaire is not scored (``scoring="none"``).
    """
    if q.scoring == "none":
        raise ValueError(f"questionnaire {q.id!r} has no score (scoring='none'); use its items")
    values = validate_answers(q, answers)
    scored = [reverse_code(q, item, values[item.id]) for item in q.items  # type: ignore[arg-type]
              if item.scored and item.id in values]
    if not scored:
        raise AnswerError(q.id, ["no scored item is answered"])
    return math.fsum(scored) / len(scored)


# --- Built-in questionnaires ------------------------------------------------------

SHELF_TRUST_RELIANCE = Questionnaire(
    id="shelf_trust_reliance",
    title="Trust and reliance",
    participant_title="Two questions about the last shelf",
    instructions="Please answer both questions about the shelf you just finished.",
    scale=Scale(min=defaults.SHELF_SCALE_MIN, max=defaults.SHELF_SCALE_MAX, step=1,
                anchors={defaults.SHELF_SCALE_MIN: "Not at all", defaults.SHELF_SCALE_MAX: "Completely"}),
    items=[
        Item(id="trust", text="To what extent do you trust the automation in this scenario?"),
        Item(id="reliance", text="To what extent did you rely on the automation in this scenario?"),
    ],
    scoring="none",
    citation=("Mangalindan, Rovira & Srivastava, \"When To Seek Help: Trust-Aware Assistance-Seeking in "
              "Human-Supervised Autonomy\", §4.4–4.5 and appendix; after Lee & Moray (1992), Ergonomics 35(10), "
              "1243–1270, and Lee & Moray (1994), International Journal of Human-Computer Studies 40(1), 153–184"),
    version="2 items, after each shelf",
    scoring_rule="Not combined into a score; each answer (0–10) is analysed on its own.",
)

_SCHAEFER_CITATION = ("Schaefer, K. E. (2016). Measuring trust in human robot interactions: Development of the "
                      "\"Trust Perception Scale-HRI\". In Robust Intelligence and Trust in Autonomous Systems "
                      "(pp. 191–218). Springer.")
_SCHAEFER_DOI = "10.1007/978-1-4899-7668-0_10"
_SCHAEFER_STEM = "What percentage of the time will this robot …"

#: The 40 items of the Trust Perception Scale–HRI, in the form's order: (id, text after "What percentage of the
#: time will this robot …", reverse-coded). The 14-item subscale takes its items from here.
TPS_HRI_ITEMS: dict[str, Item] = {id_: Item(id=id_, text=text, reverse_coded=rev) for id_, text, rev in [
    ("act_consistently", "act consistently", False),
    ("protect_people", "protect people", False),
    ("act_as_part_of_the_team", "act as part of the team", False),
    ("function_successfully", "function successfully", False),
    ("malfunction", "malfunction", True),
    ("clearly_communicate", "clearly communicate", False),
    ("require_frequent_maintenance", "require frequent maintenance", True),
    ("openly_communicate", "openly communicate", False),
    ("have_errors", "have errors", True),
    ("perform_better_than_a_novice", "perform a task better than a novice human user", False),
    ("know_friend_from_foe", "know the difference between friend and foe", False),
    ("provide_feedback", "provide feedback", False),
    ("adequate_decision_making", "possess adequate decision-making capability", False),
    ("warn_of_risks", "warn people of potential risks in the environment", False),
    ("meet_the_needs_of_the_mission", "meet the needs of the mission", False),
    ("provide_appropriate_information", "provide appropriate information", False),
    ("communicate_with_people", "communicate with people", False),
    ("work_best_with_a_team", "work best with a team", False),
    ("keep_classified_information_secure", "keep classified information secure", False),
    ("perform_exactly_as_instructed", "perform exactly as instructed", False),
    ("make_sensible_decisions", "make sensible decisions", False),
    ("work_close_to_people", "work in close proximity with people", False),
    ("tell_the_truth", "tell the truth", False),
    ("perform_many_functions", "perform many functions at one time", False),
    ("follow_directions", "follow directions", False),
    ("part_of_the_team", "be considered part of the team", False),
    ("responsible", "be responsible", False),
    ("supportive", "be supportive", False),
    ("incompetent", "be incompetent", True),
    ("dependable", "be dependable", False),
    ("friendly", "be friendly", False),
    ("reliable", "be reliable", False),
    ("pleasant", "be pleasant", False),
    ("unresponsive", "be unresponsive", True),
    ("autonomous", "be autonomous", False),
    ("predictable", "be predictable", False),
    ("conscious", "be conscious", False),
    ("lifelike", "be lifelike", False),
    ("good_teammate", "be a good teammate", False),
    ("led_astray", "be led astray by unexpected changes in the environment", False),
]}

#: The 14-item subscale's items, in the order this study's form asks them.
_SCHAEFER_14_IDS = ["function_successfully", "act_consistently", "reliable", "predictable", "dependable",
                    "follow_directions", "meet_the_needs_of_the_mission", "perform_exactly_as_instructed",
                    "have_errors", "provide_appropriate_information", "unresponsive", "malfunction",
                    "communicate_with_people", "provide_feedback"]


def _tps_hri(id_: str, version: str, items: list[Item]) -> Questionnaire:
    reversed_items = ", ".join(f'"{item.text}"' for item in items if item.reverse_coded)
    return Questionnaire(
        id=id_,
        title=f"Trust Perception Scale–HRI ({version})",
        participant_title="Your view of the robot",
        instructions=_SCHAEFER_STEM,
        scale=Scale(min=defaults.SCHAEFER_SCALE_MIN, max=defaults.SCHAEFER_SCALE_MAX,
                    step=defaults.SCHAEFER_SCALE_STEP, unit="%"),
        items=items,
        scoring="mean",
        citation=_SCHAEFER_CITATION,
        doi=_SCHAEFER_DOI,
        version=version,
        scoring_rule=(f"Reverse-code {reversed_items} (100 − rating); the score is the mean of the {len(items)} "
                      "ratings, a percentage (0–100)."),
    )


TPS_HRI_40 = _tps_hri("tps_hri_40", "40-item", list(TPS_HRI_ITEMS.values()))
SCHAEFER_14 = _tps_hri("schaefer_14", "14-item subscale", [TPS_HRI_ITEMS[i] for i in _SCHAEFER_14_IDS])

#: Jian, Bisantz & Drury's checklist: (id, statement, reverse-coded). Items 1–5 are the distrust items.
_JIAN_ITEMS = [
    ("deceptive", "The system is deceptive.", True),
    ("underhanded", "The system behaves in an underhanded manner.", True),
    ("suspicious", "I am suspicious of the system's intent, action, or outputs.", True),
    ("wary", "I am wary of the system.", True),
    ("harmful", "The system's actions will have a harmful or injurious outcome.", True),
    ("confident", "I am confident in the system.", False),
    ("security", "The system provides security.", False),
    ("integrity", "The system has integrity.", False),
    ("dependable", "The system is dependable.", False),
    ("reliable", "The system is reliable.", False),
    ("trust", "I can trust the system.", False),
    ("familiar", "I am familiar with the system.", False),
]

JIAN_TRUST_CHECKLIST = Questionnaire(
    id="jian_trust_checklist",
    title="Checklist for Trust between People and Automation (Jian, Bisantz & Drury 2000)",
    participant_title="Your view of the robot",
    instructions=("Here \"the system\" is the robot you worked with. Rate how much each statement describes "
                  "your feelings about it."),
    scale=Scale(min=defaults.JIAN_SCALE_MIN, max=defaults.JIAN_SCALE_MAX, step=1,
                anchors={defaults.JIAN_SCALE_MIN: "Not at all", defaults.JIAN_SCALE_MAX: "Extremely"}),
    items=[Item(id=i, text=text, reverse_coded=rev) for i, text, rev in _JIAN_ITEMS],
    scoring="mean",
    citation=("Jian, J.-Y., Bisantz, A. M., & Drury, C. G. (2000). Foundations for an empirically determined scale "
              "of trust in automated systems. International Journal of Cognitive Ergonomics, 4(1), 53–71."),
    doi="10.1207/S15327566IJCE0401_04",
    version="12-item",
    scoring_rule=("Reverse-code items 1–5, the distrust items (8 − rating); the score is the mean of the 12 "
                  "ratings, a trust score on 1–7."),
)

MUIR_TRUST_RATING = Questionnaire(
    id="muir_trust_rating",
    title="Overall trust rating (after Muir 1989; Muir & Moray 1996)",
    participant_title="Your trust in the robot",
    instructions="Rate how much you trust the robot, from 0 (not at all) to 100 (completely).",
    scale=Scale(min=defaults.MUIR_SCALE_MIN, max=defaults.MUIR_SCALE_MAX, step=defaults.MUIR_SCALE_STEP,
                anchors={defaults.MUIR_SCALE_MIN: "Not at all", defaults.MUIR_SCALE_MAX: "Completely"}),
    items=[Item(id="trust", text="How much do you trust the robot?")],
    scoring="mean",
    citation=("Muir, B. M. (1989). Operators' trust in and percentage of time spent using the automatic controllers "
              "in supervisory process control task (Doctoral dissertation, University of Toronto); Muir, B. M., & "
              "Moray, N. (1996). Trust in automation. Part II. Experimental studies of trust and human intervention "
              "in a process control simulation. Ergonomics, 39(3), 429–460."),
    doi="10.1080/00140139608964474",
    version="single item (wording adapted to a robot)",
    scoring_rule="The rating itself (0–100); no item is reverse-coded.",
)

def _choice(id_: str, text: str, options: list[tuple[str, str]], *, required: bool = True) -> Item:
    return Item(id=id_, text=text, kind="choice", required=required,
                options=[ChoiceOption(value=value, label=label) for value, label in options])


_PREFER_NOT = ("prefer_not_to_say", "Prefer not to say")

DEMOGRAPHICS = Questionnaire(
    id="demographics",
    title="Demographics (trustlab)",
    participant_title="A few questions about you",
    instructions="These questions help us describe who took part. Choose the answer that fits best.",
    items=[
        _choice("age_band", "How old are you?", [("age_18_24", "18–24"), ("age_25_34", "25–34"),
                                                 ("age_35_44", "35–44"), ("age_45_54", "45–54"),
                                                 ("age_55_64", "55–64"), ("age_65_plus", "65 or older"),
                                                 _PREFER_NOT]),
        _choice("gender", "What is your gender?", [("woman", "Woman"), ("man", "Man"),
                                                   ("non_binary", "Non-binary"),
                                                   ("self_described", "I describe myself another way"),
                                                   _PREFER_NOT]),
        _choice("robot_experience", "How much experience do you have with robots (using, programming or working "
                "next to them)?", [("none", "None"), ("a_little", "A little (seen or tried one a few times)"),
                                   ("some", "Some (used one now and then)"),
                                   ("a_lot", "A lot (use, build or program them regularly)"), _PREFER_NOT]),
        _choice("video_game_experience", "How often do you play video games?",
                [("never", "Never"), ("less_than_monthly", "Less than once a month"),
                 ("monthly", "A few times a month"), ("weekly", "Every week"), _PREFER_NOT]),
    ],
    scoring="none",
    version="4 items (trustlab's own wording)",
    scoring_rule="Not scored; each answer is the chosen option's value (surveys.csv column text).",
)

COMMENTS = Questionnaire(
    id="comments",
    title="Comments (trustlab)",
    participant_title="Anything else?",
    instructions="If you have any comments about the study, please write them here. This is optional.",
    items=[Item(id="comments", text="Your comments", kind="text", required=False, max_length=2000)],
    scoring="none",
    version="1 optional free-text item (trustlab's own wording)",
    scoring_rule="Not scored; the text as written (surveys.csv column text).",
)

#: Built-in questionnaires by id, for study configurations that name them.
BUILTIN_QUESTIONNAIRES: dict[str, Questionnaire] = {q.id: q for q in (
    SHELF_TRUST_RELIANCE, SCHAEFER_14, TPS_HRI_40, JIAN_TRUST_CHECKLIST, MUIR_TRUST_RATING, DEMOGRAPHICS, COMMENTS)}
