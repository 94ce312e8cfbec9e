"""Questionnaire pages: the draft kept while a page is being filled in, and submitting the page.

A draft is the answers given so far on the page the session is at; it lives on the participant row (never
in the answers table, so exports and analyses never see it), is returned with the page's state so a reload
restores it, and is dropped when the page is submitted.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from experiment.flow import QuestionnairePage
from experiment.questionnaires import AnswerError, validate_answers
from server.errors import Conflict, Invalid
from server.models import Answer, Participant
from server.services import sessions


def current_page(participant: Participant, runtime: StudyRuntime) -> QuestionnairePage | None:
    """The questionnaire page the session is at, or None."""
    return participant.step.questionnaire_page(runtime.config)


def save_draft(session: Session, participant: Participant, runtime: StudyRuntime, *, questionnaire_id: str,
               context: str, answers: dict[str, Any]) -> dict[str, Any]:
    """Keep the answers given so far on the page on screen (replacing the previous draft: idempotent).

    A draft for a page the session is not at (a stale tab's) is refused like a stale page's answers.
    """
    sessions.require_active(participant)
    page = current_page(participant, runtime)
    if page is None or (page.questionnaire, page.context) != (questionnaire_id, context):
        raise _stale(session, participant, questionnaire_id=questionnaire_id, context=context,
                     detail=f"this draft is for page {context!r}, but the session is at "
                            f"{sessions.describe(participant.step)}",
                     step=participant.step)
    try:
        values = validate_answers(runtime.config.questionnaire(questionnaire_id), answers, partial=True)
    except AnswerError as exc:
        raise Invalid(str(exc), problems=exc.problems) from None
    participant.survey_draft = {"questionnaire": questionnaire_id, "context": context, "answers": values}
    return participant.survey_draft


def draft_answers(participant: Participant, questionnaire_id: str, context: str) -> dict[str, float | str]:
    """The draft of this page ({} when there is none, or it belongs to another page)."""
    draft = participant.survey_draft
    if not draft or (draft.get("questionnaire"), draft.get("context")) != (questionnaire_id, context):
        return {}
    return dict(draft["answers"])


def submit(session: Session, participant: Participant, runtime: StudyRuntime, *, questionnaire_id: str,
           answers: dict[str, Any], now: datetime, context: str | None) -> None:
    """Record the page's answers and move on; the draft goes.

    A page the session is no longer at (a stale tab's) is refused with a 409 that says whether that page was
    already answered (``answered_elsewhere``: in another tab or window; those answers stand), so the page can
    tell the participant what became of the answers on it.
    """
    try:
        sessions.answer(session, participant, runtime, questionnaire_id=questionnaire_id, answers=answers, now=now,
                        context=context)
    except Conflict as exc:
        if context is None:
            raise
        raise _stale(session, participant, questionnaire_id=questionnaire_id, context=context, detail=exc.detail,
                     **exc.extra) from None
    participant.survey_draft = None


def _stale(session: Session, participant: Participant, *, questionnaire_id: str, context: str, detail: str,
           **extra: Any) -> Conflict:
    """The 409 for a page the session is no longer at, saying whether that page was answered (elsewhere)."""
    answered = session.scalar(select(Answer.id).where(
        Answer.participant_id == participant.id, Answer.context == context,
        Answer.questionnaire == questionnaire_id).limit(1)) is not None
    reason = ("this page was already answered in another tab or window; those answers were kept"
              if answered else "this page is out of date")
    return Conflict(f"{reason} ({detail})", answered_elsewhere=answered, **extra)
