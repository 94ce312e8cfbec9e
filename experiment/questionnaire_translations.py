"""Questionnaires in several languages: a questionnaire's translations, checked whole (issue 41).

A questionnaire's own texts are in one language (``Questionnaire.language``, English unless it says otherwise); each
entry of its ``translations`` gives, in one more language, every text a participant reads: the page's title, the
instructions, each item's text, each choice option's label, the scale's anchor labels and unit. A translation is
checked whole, so a page never mixes languages: an item, option or anchor left out (or one the questionnaire does not
have) is a problem that names it, and ``{robot}`` must be in a translated text exactly where the original has it.

What is exported never depends on the language: item ids, option values and scale values are the questionnaire's
own, and a translation only replaces what is read. A translation with a ``citation`` is a published one; without, it
is the lab's own (not validated), as the instrument library (``experiment.instruments``) says per language.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field

from experiment.languages import MAX_TAG_LENGTH, TAG_PATTERN, canonical_tag, match_language

if TYPE_CHECKING:  # the questionnaire model holds its translations: at run time this module needs none of it
    from experiment.questionnaires import Questionnaire

#: The language of a questionnaire's own texts when it names none (every built-in instrument's).
DEFAULT_QUESTIONNAIRE_LANGUAGE = "en"
#: Written in a questionnaire's texts, replaced on the page by the robot's name (``experiment.questionnaires``).
_ROBOT = "{robot}"
_IDENTIFIER = r"^[A-Za-z][A-Za-z0-9_]*$"

#: Written as BCP 47 writes it by convention ("pt-BR"), as the study's ``languages`` are.
LanguageTag = Annotated[str, Field(pattern=TAG_PATTERN, max_length=MAX_TAG_LENGTH, description=(
    'A BCP 47 language tag, e.g. "en", "de", "pt-BR"')), AfterValidator(canonical_tag)]
#: An anchor's scale point: a JSON document's keys are strings ("10"), also when it is validated strictly.
ScalePoint = Annotated[int, BeforeValidator(lambda key: int(key) if isinstance(key, str) and key.lstrip("-").isdigit()
                                             else key)]


def _missing(value: object) -> bool:
    """Left out is left out of dumps too (as in ``experiment.questionnaires``)."""
    return value is None


class OptionTranslation(BaseModel):
    """A choice option's label in the translation's language; its value (what is exported) stays the option's."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    value: str = Field(pattern=_IDENTIFIER, max_length=64, description="The option's value in the questionnaire")
    label: str = Field(min_length=1, max_length=300, description="What the participant reads, in this language")


class ItemTranslation(BaseModel):
    """An item's text (and a choice item's option labels) in the translation's language."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(pattern=_IDENTIFIER, max_length=64, description="The item's id in the questionnaire")
    text: str = Field(min_length=1, description="The question or statement as participants of this language read it")
    options: list[OptionTranslation] | None = Field(None, exclude_if=_missing, max_length=50, description=(
        "choice items: every option's label, by the option's value"))


class QuestionnaireTranslation(BaseModel):
    """Every text of a questionnaire a participant reads, in one more language."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    language: LanguageTag
    participant_title: str = Field(title="Title participants see", min_length=1, max_length=120, description=(
        "The page's heading in this language"))
    instructions: str = Field(description="Shown above the items, in this language")
    anchors: dict[ScalePoint, str] | None = Field(None, title="Labels at scale points", exclude_if=_missing,
                                                   description=(
        "The scale's anchor labels in this language, at the same points as the scale's own"))
    unit: str | None = Field(None, exclude_if=_missing, description=(
        "The scale's unit in this language (when the scale has one)"))
    items: list[ItemTranslation] = Field(min_length=1, description="Every item, by its id")
    citation: str | None = Field(None, title="Published translation", exclude_if=_missing, min_length=1,
                                 description=(
        "Where this translation was published and validated (a full reference); left out: the lab's own "
        "translation, not validated"))

    @property
    def published(self) -> bool:
        return self.citation is not None


def translation_problems(q: Questionnaire, t: QuestionnaireTranslation) -> list[str]:
    """Every way ``t`` does not translate all of ``q`` (and only ``q``), each naming what is missing or unknown."""
    problems = _repeats("item", [item.id for item in t.items])
    given = {item.id: item for item in t.items}
    missing = [item.id for item in q.items if item.id not in given]
    if missing:
        problems.append(f"items not translated: {', '.join(missing)}")
    unknown = [i for i in given if i not in q.item_ids]
    if unknown:
        problems.append(f"items the questionnaire does not have: {', '.join(unknown)}")
    for item in q.items:
        if item.id in given:
            problems += [f"item {item.id!r}: {p}" for p in _option_problems(item.option_values, given[item.id])]
    problems += _scale_problems(q, t)
    pairs = [("participant_title", q.heading, t.participant_title), ("instructions", q.instructions, t.instructions)]
    pairs += [(f"item {item.id!r}", item.text, given[item.id].text) for item in q.items if item.id in given]
    pairs += [(f"item {item.id!r} option {option.value!r}", option.label, label)
              for item in q.items if item.id in given for option in item.options or []
              if (label := _label(given[item.id], option.value)) is not None]
    problems += [f"{where}: {_robot_problem(original)}" for where, original, translated in pairs
                 if (_ROBOT in original) != (_ROBOT in translated)]
    if q.instructions and not t.instructions:
        problems.append("instructions not translated")
    return problems


def _option_problems(values: list[str], item: ItemTranslation) -> list[str]:
    if not values:
        return [] if item.options is None else ["options given for an item that has none"]
    labels = [o.value for o in item.options or []]
    problems = _repeats("option", labels)
    missing = [v for v in values if v not in labels]
    if missing:
        problems.append(f"options not translated: {', '.join(missing)}")
    unknown = [v for v in labels if v not in values]
    if unknown:
        problems.append(f"options the item does not have: {', '.join(unknown)}")
    return problems


def _scale_problems(q: Questionnaire, t: QuestionnaireTranslation) -> list[str]:
    points = sorted((q.scale.anchors or {}) if q.scale else {})
    given = sorted(t.anchors or {})
    problems = []
    if given != points:
        problems.append(f"anchors must be translated at the scale's anchor points ({_points(points)}), "
                        f"not at {_points(given)}")
    unit = q.scale.unit if q.scale else None
    if (unit is None) != (t.unit is None):
        problems.append(f"unit: the scale's unit is {unit!r}, so the translation's must be "
                        + ("left out" if unit is None else "given"))
    return problems


def _points(points: list[int]) -> str:
    return ", ".join(map(str, points)) or "none"


def _label(item: ItemTranslation, value: str) -> str | None:
    return next((o.label for o in item.options or [] if o.value == value), None)


def _robot_problem(original: str) -> str:
    return (f"the original names the robot with {_ROBOT}, the translation must too" if _ROBOT in original
            else f"the original does not name the robot, so the translation cannot hold {_ROBOT}")


def _repeats(what: str, ids: list[str]) -> list[str]:
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    return [f"{what}s translated more than once: {', '.join(repeated)}"] if repeated else []


def translation_for(q: Questionnaire, language: str) -> QuestionnaireTranslation | None:
    """The translation a participant of ``language`` reads (the same tag, else one of its primary language: "de-AT"
    reads "de"), or None: the questionnaire's own texts (its language, or no translation for that language)."""
    chosen = match_language(language, [q.language, *(t.language for t in q.translations or [])])
    return next((t for t in q.translations or [] if t.language == chosen and chosen != q.language), None)


def serves(q: Questionnaire, language: str) -> bool:
    """Whether a participant of ``language`` reads ``q`` in their language (its own texts or a translation)."""
    return match_language(language, [q.language]) is not None or translation_for(q, language) is not None


TranslationStatus = Literal["original", "published", "lab"]


def language_statuses(q: Questionnaire) -> list[tuple[str, TranslationStatus, str | None]]:
    """Per language ``q`` can be read in: (tag, status, citation). ``original``: its own texts (the instrument's
    citation, if published); ``published``: a published translation (its citation); ``lab``: the lab's own
    translation, not validated (no citation)."""
    statuses: list[tuple[str, TranslationStatus, str | None]] = [(q.language, "original", q.citation)]
    return statuses + [(t.language, "published" if t.published else "lab", t.citation) for t in q.translations or []]
