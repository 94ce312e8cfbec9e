"""Attention checks and eligibility questions on a submitted questionnaire page (experiment.attention).

Every failed attention check is an ``attention_failed`` event (the count so far in its payload); the events are
what ``attention_failures`` counts, in the participants table and in participants.csv. A page that screens the
participant out ends the session at once: status and step ``screened_out``, the outcome's code, and a
``screened_out`` event saying why.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from experiment.attention import check_page, screen_out_reason
from experiment.engine import StudyRuntime
from experiment.events import EventKind
from experiment.flow import SCREENED_OUT, ParticipantStatus, QuestionnairePage
from experiment.outcomes import SessionOutcome
from experiment.questionnaires import AnswerValue, Questionnaire
from server.models import Event, Participant
from server.services.audit import log_event


def attention_failures(session: Session, participant: Participant) -> int:
    """The participant's failed attention checks so far."""
    return session.scalar(select(func.count()).select_from(Event).where(
        Event.participant_id == participant.id, Event.kind == EventKind.ATTENTION_FAILED)) or 0


def check_answers(session: Session, participant: Participant, runtime: StudyRuntime, questionnaire: Questionnaire,
                  page: QuestionnairePage, values: Mapping[str, AnswerValue], now: datetime) -> bool:
    """Record the page's failed attention checks; screen the participant out when the page says so.

    Returns whether the session ended (screened out): the caller then does not move it on.
    """
    checked = check_page(questionnaire, values)
    before = attention_failures(session, participant) if checked.attention_failures else 0
    for count, item_id in enumerate(checked.attention_failures, start=before + 1):
        item = questionnaire.item(item_id)
        log_event(session, participant.study_id, participant.id, EventKind.ATTENTION_FAILED,
                  questionnaire=questionnaire.id, context=page.context, item=item_id, answer=values[item_id],
                  instructed=item.instructed_response,
                  failures=count)
    reason = screen_out_reason(runtime.config.attention, before, checked)
    if reason is None:
        return False
    participant.step, participant.status, participant.finished_at = SCREENED_OUT, ParticipantStatus.SCREENED_OUT, now
    participant.completion_code = runtime.config.completion.code(SessionOutcome.SCREENED_OUT)
    log_event(session, participant.study_id, participant.id, EventKind.SCREENED_OUT, reason=reason.value,
              questionnaire=questionnaire.id, context=page.context,
              items=list(checked.ineligible or checked.attention_failures),
              attention_failures=before + len(checked.attention_failures))
    return True
