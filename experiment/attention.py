"""Attention checks and eligibility questions: what a questionnaire page's answers say about the participant.

An attention check is an instructed-response item (``Item.instructed_response``: "select 'Strongly agree' for
this item"); any other answer is a failure. A study's rule (``AttentionConfig``, config ``attention``) says what
failures do: ``flag`` (the default) only records and counts them, for the researcher to judge, because
recruitment platforms discourage rejecting a participant for a single failure; ``screen_out`` ends the session
(status ``screened_out``) at the answer that brings the participant's failures to ``max_failures``.

An eligibility question is a choice item with ``screen_out_options``: choosing one of them ends the session at
once, whatever the rule, since it is the study's stated eligibility.

Everything here is pure: the server records the failures as events and counts them per participant.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from experiment import defaults
from experiment.questionnaires import AnswerValue, Item, Questionnaire


class AttentionConfig(BaseModel):
    """What failed attention checks do (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    rule: Literal["flag", "screen_out"] = Field("flag", title="On failed attention checks", description=(
        "flag: record and count failures (a quality flag in the participants table, attention_failures in "
        "participants.csv); screen_out: also end the session as screened out when the failures reach max_failures"))
    max_failures: int = Field(defaults.ATTENTION_MAX_FAILURES, ge=1, le=100, title="Failures that screen out",
                              description=(
        "screen_out only: the number of failed attention checks that ends the session"))


class ScreenOutReason(StrEnum):
    ATTENTION = "attention"  # failed attention checks reached the study's max_failures
    ELIGIBILITY = "eligibility"  # an eligibility question answered with a screen-out option


@dataclass(frozen=True)
class PageCheck:
    """What one page's answers say: the attention checks failed and the eligibility questions failed on it."""

    attention_failures: tuple[str, ...] = ()  # item ids
    ineligible: tuple[str, ...] = ()  # item ids


def attention_passed(item: Item, value: AnswerValue | None) -> bool | None:
    """Whether the answer is the one an attention check instructed (None: the item is no attention check)."""
    if not item.is_attention_check:
        return None
    if item.kind == "rating":
        instructed = item.instructed_response  # a number: a rating item's is validated as one
        return (isinstance(value, int | float) and isinstance(instructed, int | float)
                and float(value) == float(instructed))
    return value == item.instructed_response


def attention_failed(item: Item, value: AnswerValue | None) -> bool:
    """The one definition of a failure, whoever counts it (the live check that records ``attention_failed`` events,
    the participants table, the exports): an attention check answered otherwise than instructed. An item without an
    answer is no failure (an attention check is a required item: a page is not accepted without it)."""
    return value is not None and attention_passed(item, value) is False


def stored_answer(item: Item, record: Mapping[str, Any]) -> AnswerValue | None:
    """The answer as validated, from a stored record (``Answer.value``/``text``, or surveys.csv's cells as strings):
    a rating's number, a text or choice item's text; None when the record holds none."""
    raw = record.get("value") if item.kind == "rating" else record.get("text")
    if raw is None or raw == "":
        return None
    return float(raw) if item.kind == "rating" else str(raw)


def check_page(q: Questionnaire, answers: Mapping[str, AnswerValue]) -> PageCheck:
    """The attention checks failed and the eligibility questions failed by a page's validated answers."""
    failed = tuple(item.id for item in q.items if attention_failed(item, answers.get(item.id)))
    ineligible = tuple(item.id for item in q.items
                       if item.screen_out_options and answers.get(item.id) in item.screen_out_options)
    return PageCheck(failed, ineligible)


def screen_out_reason(rule: AttentionConfig, failures_before: int, page: PageCheck) -> ScreenOutReason | None:
    """Whether a page ends the session, and why: an eligibility question answered with a screen-out option
    always does; under ``screen_out``, so does a page whose failures bring the total to ``max_failures``."""
    if page.ineligible:
        return ScreenOutReason.ELIGIBILITY
    if rule.rule == "screen_out" and page.attention_failures and (
            failures_before + len(page.attention_failures) >= rule.max_failures):
        return ScreenOutReason.ATTENTION
    return None


def has_attention_checks(questionnaires: list[Questionnaire]) -> bool:
    return any(item.is_attention_check for q in questionnaires for item in q.items)


def count_failures(answers: Iterable[Mapping[str, Any]], questionnaires: Mapping[str, Questionnaire]) -> int:
    """Failed attention checks among stored answers (records with ``questionnaire``, ``item``, ``value`` and ``text``,
    as the answer table and surveys.csv hold them) of one participant, whose configuration version defines
    ``questionnaires`` (by id). The server records each failure ``check_page`` finds as an event; this counts the
    same failures (``attention_failed``) from the answers, for readers that hold those already."""
    failures = 0
    for answer in answers:
        q = questionnaires.get(str(answer["questionnaire"]))
        item = next((i for i in q.items if i.id == answer["item"]), None) if q is not None else None
        if item is not None and item.is_attention_check:
            failures += attention_failed(item, stored_answer(item, answer))
    return failures
