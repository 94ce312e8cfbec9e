"""Questionnaires as data: scales, items, answer validation, reverse coding, scores (SPEC §5).

A lab adds its own questionnaire by writing a ``Questionnaire`` document in the
study configuration. The built-in instruments, each with its citation, version
and scoring rule on the document itself, and what their texts were checked
against, are in ``experiment.instruments`` (the library); a study uses one by
naming its id and its configuration then holds a copy (``StudyConfig``).

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

A questionnaire's texts are in its ``language`` (English by default); its
``translations`` give them in more languages, each checked whole
(``experiment.questionnaire_translations``), and ``in_language`` is the
questionnaire as a participant of a language reads it. Ids and option values
are never translated, so answers and exports are the same in every language.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Literal, cast

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from experiment import defaults
from experiment.questionnaire_translations import (
    DEFAULT_QUESTIONNAIRE_LANGUAGE,
    LanguageTag,
    QuestionnaireTranslation,
    ScalePoint,
    translation_for,
    translation_problems,
)

#: Relative tolerance when checking that a value lies on a scale step.
_STEP_TOLERANCE = 1e-9
#: Written in a questionnaire's texts, replaced on the page by the name of the robot the page is about, as every page
#: names it ("Robot A": the study's ``texts.block_label`` of the block the page belongs to).
ROBOT_PLACEHOLDER = "{robot}"


def _missing(value: object) -> bool:
    """Provenance left out is left out of dumps too: a document without it keeps its config hash."""
    return value is None


class AnswerError(ValueError):
    """Answers that do not fit a questionnaire; ``problems`` lists every reason."""

    def __init__(self, questionnaire_id: str, problems: list[str]) -> None:
        self.problems = problems
        super().__init__(f"invalid answers to {questionnaire_id!r}: " + "; ".join(problems))


class Scale(BaseModel):
    """A rating scale: the values min, min + step, …, max."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    min: float = Field(title="Lowest value", description="Lowest value of the scale")
    max: float = Field(title="Highest value", description="Highest value of the scale")
    step: float = Field(gt=0, title="Step between values", description="Distance between neighbouring values")
    anchors: dict[ScalePoint, str] | None = Field(None, title="Labels at scale points", description=(
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

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    value: str = Field(pattern=_IDENTIFIER, max_length=64, description=(
        "Stable identifier of the option: what surveys.csv records (column text), whatever the label says"))
    label: str = Field(min_length=1, max_length=300, description="What the participant reads")


class Item(BaseModel):
    """One question. ``id`` names its column in exports, so it is an identifier.

    Every field past ``reverse_coded`` is left out of dumps at its default, so a document written before item kinds
    existed keeps its config hash.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    id: str = Field(pattern=_IDENTIFIER, max_length=64, description="The item's identifier, its name in exports")
    text: str = Field(min_length=1, description="The question or statement as participants read it")
    reverse_coded: bool = Field(False, description="Negatively worded: scored as max + min - value")
    kind: ItemKind = Field("rating", title="Answer kind", exclude_if=lambda kind: kind == "rating", description=(
        "rating: a point of the questionnaire's scale (the only kind that enters the score); text: free text; "
        "choice: one of options"))
    required: bool = Field(True, title="Answer required", exclude_if=lambda required: required is True, description=(
        "Whether the page can be sent without an answer to this item"))
    max_length: int | None = Field(None, title="Longest answer (characters)", exclude_if=_missing, ge=1,
                                   le=defaults.TEXT_ANSWER_LIMIT, description=(
        f"text items: the longest answer, in characters (default {defaults.TEXT_ANSWER_MAX_LENGTH})"))
    options: list[ChoiceOption] | None = Field(None, exclude_if=_missing, min_length=2, max_length=50, description=(
        "choice items: the options, in the order shown"))
    instructed_response: float | str | None = Field(None, title="Attention check: the instructed answer",
                                                    exclude_if=_missing, description=(
        "Makes the item an attention check (an instructed-response item, not scored): the answer its text tells "
        "the participant to give, a scale value (rating) or an option's value (choice). Any other answer is a "
        "failure, recorded and counted (study config attention)"))
    screen_out_options: list[str] | None = Field(None, title="Options that screen out", exclude_if=_missing,
                                                 min_length=1, description=(
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

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    id: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=64, description=(
        "The questionnaire's identifier, by which the study names it"))
    title: str = Field(min_length=1, description="The instrument's name, for researchers (admin page, report)")
    participant_title: str | None = Field(None, title="Title participants see", min_length=1, max_length=120,
                                          description=(
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
    version: str | None = Field(None, title="Form of the instrument", exclude_if=_missing, min_length=1,
                                max_length=120, description=(
        'Which form of the instrument this is, e.g. "40-item" or "14-item subscale"'))
    scoring_rule: str | None = Field(None, title="Scoring rule in words", exclude_if=_missing, min_length=1,
                                     description=(
        "How the score is computed, in words (which items are reverse-coded; mean or sum), for whoever reads "
        "the configuration"))
    # Left out of dumps at the default, so a document written before it keeps its config hash.
    about_robot: bool = Field(True, title="About the robot", exclude_if=lambda about: about is True, description=(
        "Whether the questions are about the robot the participant has just worked with: asked after a block (or a "
        "shelf), the page then says which robot (\"These questions are about Robot B …\"). false for questions "
        "about the participant or the study as a whole (demographics, comments): no robot is named above them"))
    # Both left out of dumps at their defaults, so a document written before translations keeps its config hash.
    language: LanguageTag = Field(DEFAULT_QUESTIONNAIRE_LANGUAGE, title="Language of its texts",
                                  exclude_if=lambda tag: tag == DEFAULT_QUESTIONNAIRE_LANGUAGE)
    translations: list[QuestionnaireTranslation] | None = Field(None, exclude_if=_missing, max_length=50,
                                                                description=(
        "Its texts in other languages, each translating every text a participant reads (title, instructions, item "
        "texts, option labels, anchors, unit); a participant whose language has none reads its own texts. Item ids "
        "and option values are never translated: exports are the same in every language"))

    @model_validator(mode="after")
    def _unique_item_ids(self) -> Questionnaire:
        ids = [item.id for item in self.items]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"item ids must be unique; repeated: {', '.join(duplicates)}")
        return self

    @model_validator(mode="after")
    def _translations_whole(self) -> Questionnaire:
        """Every translation translates every text (a page never mixes languages); each problem at its place."""
        errors = []
        tags = [self.language.lower()]
        for index, translation in enumerate(self.translations or []):
            problems = translation_problems(self, translation)
            if translation.language.lower() in tags:
                problems.insert(0, f"{translation.language!r} is given twice (or is the questionnaire's own language)")
            tags.append(translation.language.lower())
            if problems:
                message = f"translation {translation.language!r}: " + "; ".join(problems)
                errors.append(InitErrorDetails(type=PydanticCustomError("incomplete_translation", "{message}",
                                                                        {"message": message}),
                                               loc=("translations", index), input=translation.language))
        if errors:
            raise ValidationError.from_exception_data(type(self).__name__, errors)
        return self

    @model_validator(mode="after")
    def _ratings_fit_scale(self) -> Questionnaire:
        ratings = [item for item in self.items if item.kind == "rating"]
        if ratings and self.scale is None:
            raise ValueError(f"rating items need the questionnaire's scale; no scale for {ratings[0].id!r}")
        for item in ratings:
            if (item.is_attention_check and self.scale is not None
                    and (problem := self.scale.problem(item.instructed_response)) is not None):
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

    @property
    def names_robot(self) -> bool:
        """Whether any of its texts the participant reads holds ``ROBOT_PLACEHOLDER``."""
        return any(ROBOT_PLACEHOLDER in text for text in self.participant_texts())

    def participant_texts(self) -> list[str]:
        """Every text of it a participant reads: heading, instructions, items, options."""
        texts = [self.heading, self.instructions]
        for item in self.items:
            texts += [item.text, *(option.label for option in item.options or [])]
        return texts

    @property
    def languages(self) -> list[str]:
        """The languages it can be read in: its own, then its translations'."""
        return [self.language, *(t.language for t in self.translations or [])]

    def in_language(self, language: str) -> Questionnaire:
        """This questionnaire as a participant of ``language`` reads it: a translation's texts in place of its own
        (ids, option values and the scale's values unchanged), or its own texts when it has no translation for that
        language (``experiment.questionnaire_translations.translation_for``). The result has no translations."""
        t = translation_for(self, language)
        if t is None:
            return self if not self.translations else self.model_copy(update={"translations": None})
        given = {item.id: item for item in t.items}  # complete: validated
        items = [item.model_copy(update={"text": given[item.id].text, "options": None if item.options is None else [
            option.model_copy(update={"label": next(o.label for o in given[item.id].options or []
                                                    if o.value == option.value)}) for option in item.options]})
            for item in self.items]
        scale = None if self.scale is None else self.scale.model_copy(update={"anchors": t.anchors, "unit": t.unit})
        return self.model_copy(update={"participant_title": t.participant_title, "instructions": t.instructions,
                                       "items": items, "scale": scale, "language": t.language, "translations": None})

    def naming(self, robot: str) -> Questionnaire:
        """This questionnaire as a page about ``robot`` shows it: ``ROBOT_PLACEHOLDER`` replaced by its name."""
        if not self.names_robot:
            return self

        def fill(text: str) -> str:
            return text.replace(ROBOT_PLACEHOLDER, robot)

        items = [item.model_copy(update={"text": fill(item.text), "options": None if item.options is None else [
            option.model_copy(update={"label": fill(option.label)}) for option in item.options]})
            for item in self.items]
        return self.model_copy(update={"participant_title": fill(self.heading), "instructions": fill(self.instructions),
                                       "items": items})

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
    valid = cast(dict[str, AnswerValue], given)  # each answer passed answer_problem above
    return {item.id: float(valid[item.id]) if item.kind == "rating" else valid[item.id]
            for item in q.items if item.id in valid}


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
    scored = [reverse_code(q, item, float(values[item.id])) for item in q.items  # scored items are ratings: floats
              if item.scored and item.id in values]
    if not scored:
        raise AnswerError(q.id, ["no scored item is answered"])
    return math.fsum(scored) / len(scored)
