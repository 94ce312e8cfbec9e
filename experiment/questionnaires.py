"""Questionnaires as data: scales, items, answer validation, reverse coding, scores (SPEC §5).

A lab adds its own questionnaire by writing a ``Questionnaire`` document in the
study configuration. Two are built in:

- ``SHELF_TRUST_RELIANCE``: the trust and reliance questions asked after each
  shelf (paper §4.4–4.5 and appendix; after Lee & Moray 1992, 1994), each on
  an 11-point 0–10 scale. Not combined into a score.
- ``SCHAEFER_14``: the 14-item subscale of the Trust Perception Scale–HRI,
  K. E. Schaefer (2016), "Measuring trust in human robot interactions:
  Development of the 'Trust Perception Scale-HRI'", in *Robust Intelligence
  and Trust in Autonomous Systems*, pp. 191–218, Springer,
  doi:10.1007/978-1-4899-7668-0_10. Each item is rated 0–100 % in steps of
  10; "have errors", "be unresponsive" and "malfunction" are reverse-coded;
  the score is the mean of the (reverse-coded) item ratings (paper §5.3).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from experiment import defaults

#: Relative tolerance when checking that a value lies on a scale step.
_STEP_TOLERANCE = 1e-9


class AnswerError(ValueError):
    """Answers that do not fit a questionnaire; ``problems`` lists every reason."""

    def __init__(self, questionnaire_id: str, problems: list[str]) -> None:
        self.problems = problems
        super().__init__(f"invalid answers to {questionnaire_id!r}: " + "; ".join(problems))


class Scale(BaseModel):
    """A rating scale: the values min, min + step, …, max."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min: float
    max: float
    step: float = Field(gt=0)
    anchors: dict[int, str] | None = None  # labels shown at some scale points
    unit: str | None = None  # e.g. "%"

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


class Item(BaseModel):
    """One question. ``id`` names its column in exports, so it is an identifier."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=64)
    text: str = Field(min_length=1)
    reverse_coded: bool = False


class Questionnaire(BaseModel):
    """A titled list of items sharing one scale and one scoring rule."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=64)
    title: str = Field(min_length=1, description="The instrument's name, for researchers (admin page, report)")
    participant_title: str | None = Field(None, min_length=1, max_length=120, description=(
        "The page's heading as participants see it, in plain words; default: the title"))
    instructions: str
    scale: Scale
    items: list[Item] = Field(min_length=1)
    scoring: Literal["mean", "none"] = "mean"

    @model_validator(mode="after")
    def _unique_item_ids(self) -> Questionnaire:
        ids = [item.id for item in self.items]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"item ids must be unique; repeated: {', '.join(duplicates)}")
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


def validate_answers(q: Questionnaire, answers: Mapping[str, int | float], *, partial: bool = False) -> dict[str, float]:
    """Check that every item is answered once with an allowed scale value.

    Returns the answers as floats, in item order. Raises ``AnswerError`` listing
    every missing item, unknown item, non-number and value off the scale or
    between steps. ``partial`` allows missing items (a draft of a page being filled in).
    """
    problems = [] if partial else [f"missing item {i!r}" for i in q.item_ids if i not in answers]
    problems += [f"unknown item {k!r}" for k in answers if k not in q.item_ids]
    problems += [f"item {i!r}: {p}" for i in q.item_ids if i in answers
                 if (p := q.scale.problem(answers[i])) is not None]
    if problems:
        raise AnswerError(q.id, problems)
    return {i: float(answers[i]) for i in q.item_ids if i in answers}


def reverse_code(q: Questionnaire, item: Item | str, value: int | float) -> float:
    """``max + min − value`` for a reverse-coded item, ``value`` otherwise."""
    item = q.item(item) if isinstance(item, str) else item
    problem = q.scale.problem(value)
    if problem is not None:
        raise AnswerError(q.id, [f"item {item.id!r}: {problem}"])
    return float(q.scale.max + q.scale.min - value) if item.reverse_coded else float(value)


def score(q: Questionnaire, answers: Mapping[str, int | float]) -> float:
    """The mean of the reverse-coded answers (paper §5.3), on the scale's units.

    Raises ``AnswerError`` for invalid answers and ``ValueError`` when the
    questionnaire is not scored (``scoring="none"``).
    """
    if q.scoring == "none":
        raise ValueError(f"questionnaire {q.id!r} has no score (scoring='none'); use its items")
    values = validate_answers(q, answers)
    return math.fsum(reverse_code(q, q.item(i), v) for i, v in values.items()) / len(values)


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
)

#: (id, text after "What percentage of the time will this robot …", reverse-coded)
_SCHAEFER_ITEMS = [
    ("function_successfully", "function successfully", False),
    ("act_consistently", "act consistently", False),
    ("reliable", "be reliable", False),
    ("predictable", "be predictable", False),
    ("dependable", "be dependable", False),
    ("follow_directions", "follow directions", False),
    ("meet_the_needs_of_the_mission", "meet the needs of the mission", False),
    ("perform_exactly_as_instructed", "perform exactly as instructed", False),
    ("have_errors", "have errors", True),
    ("provide_appropriate_information", "provide appropriate information", False),
    ("unresponsive", "be unresponsive", True),
    ("malfunction", "malfunction", True),
    ("communicate_with_people", "communicate with people", False),
    ("provide_feedback", "provide feedback", False),
]

SCHAEFER_14 = Questionnaire(
    id="schaefer_14",
    title="Trust Perception Scale–HRI (14-item subscale)",
    participant_title="Your view of the robot",
    instructions="What percentage of the time will this robot …",
    scale=Scale(min=defaults.SCHAEFER_SCALE_MIN, max=defaults.SCHAEFER_SCALE_MAX,
                step=defaults.SCHAEFER_SCALE_STEP, unit="%"),
    items=[Item(id=i, text=text, reverse_coded=rev) for i, text, rev in _SCHAEFER_ITEMS],
    scoring="mean",
)

#: Built-in questionnaires by id, for study configurations that name them.
BUILTIN_QUESTIONNAIRES: dict[str, Questionnaire] = {q.id: q for q in (SHELF_TRUST_RELIANCE, SCHAEFER_14)}
