"""Participant sessions: opening one by its token, consent, instructions, questionnaires, abandonment."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from experiment.events import EventKind
from experiment.flow import DECLINED, TERMINAL_STATUSES, ParticipantStatus, Step, next_step
from experiment.outcomes import SessionOutcome
from experiment.questionnaires import AnswerError, answer_columns, validate_answers
from experiment.trust_belief import p_highest
from server.errors import Conflict, Gone, Invalid, NotFound
from server.i18n import N_
from server.models import Answer, Participant, Study, StudyVersion, utcnow
from server.services import screening
from server.services.audit import log_event

# Joining lives in server.services.joining; these names stay importable from here.
from server.services.joining import (  # noqa: F401 -- re-exported
    EXTERNAL_ID_PARAMS,
    MAX_PARAM_LENGTH,
    RECRUITMENT_PARAMS,
    STUDY_FULL_REASON,
    STUDY_FULL_RETRY_AFTER_S,
    TOKEN_BYTES,
    Admission,
    JoinRequest,
    active_count,
    app_secret,
    hash_token,
    join,
    lock_study,
    new_resume_key,
    recruitment_params,
    start_preview,
)
from server.services.studies import RuntimeCache

#: How often (at most) a session's last-seen time is written; far below any idle timeout (>= 30 s).
TOUCH_INTERVAL_S = 5.0

# Built once: the lookups every participant request makes (building and keying a statement per call costs more
# CPU than SQLite spends running it).
_BY_TOKEN = select(Participant).where(Participant.token_hash == bindparam("token_hash"))
_WITH_STUDY = (select(Participant, Study, StudyVersion.config_hash)
               .join(Study, Study.id == Participant.study_id)
               .join(StudyVersion, StudyVersion.id == Participant.study_version_id)
               .where(Participant.token_hash == bindparam("token_hash")))
_UNKNOWN_TOKEN = "unknown session link; please use the link you were given"


def participant_by_token(session: Session, token: str, *, lock: bool = False) -> Participant:
    query = _BY_TOKEN.with_for_update() if lock else _BY_TOKEN
    participant = session.scalar(query, {"token_hash": hash_token(token)})
    if participant is None:
        raise NotFound(_UNKNOWN_TOKEN, message=N_("errors.unknown_link"))
    return participant


def open_session(session: Session, runtimes: RuntimeCache, token: str, *, lock: bool = False
                 ) -> tuple[Participant, Study, StudyRuntime]:
    """The participant behind ``token`` (row-locked with ``lock``), their study and compiled version, in one query
    when the version is compiled already."""
    query = _WITH_STUDY.with_for_update(of=Participant) if lock else _WITH_STUDY
    row = session.execute(query, {"token_hash": hash_token(token)}).one_or_none()
    if row is None:
        raise NotFound(_UNKNOWN_TOKEN, message=N_("errors.unknown_link"))
    participant, study, version_hash = row
    return participant, study, runtimes.for_version(session, participant.study_version_id, version_hash)


def require_not_ended(participant: Participant) -> None:
    """410 once a session ended unfinished (abandoned or withdrawn): it records nothing more."""
    if participant.status == ParticipantStatus.ABANDONED:
        raise Gone("this session ended because it was inactive for too long", message=N_("errors.session_abandoned"))
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Gone("this session was withdrawn", message=N_("errors.session_withdrawn"))


def require_active(participant: Participant) -> None:
    require_not_ended(participant)
    if participant.status in (ParticipantStatus.COMPLETED, ParticipantStatus.DECLINED, ParticipantStatus.SCREENED_OUT):
        raise Conflict(f"this session is already finished; the session is at {describe(participant.step)}",
                       message=N_("errors.session_finished"), step=participant.step)


def require_phase(participant: Participant, phase: str) -> None:
    require_active(participant)
    step = participant.step
    if step.phase != phase:
        raise Conflict(f"this request is for {phase}, but the session is at {describe(step)}", step=step)


def describe(step: Step) -> str:
    details = " ".join(f"{k}={v}" for k, v in step.model_dump().items() if k != "phase")
    return f"{step.phase} {details}".strip()


def advance_step(session: Session, participant: Participant, runtime: StudyRuntime, now: datetime) -> None:
    """Move to the next step; reaching the debrief completes the session (same transaction)."""
    step = next_step(runtime.config, participant.step, participant.block_order)
    participant.step = step
    if step.phase == "debrief":
        complete(participant, runtime, now)
    log_event(session, participant.study_id, participant.id, EventKind.STEP, payload=step.model_dump())


def complete(participant: Participant, runtime: StudyRuntime, now: datetime) -> None:
    participant.status, participant.finished_at = ParticipantStatus.COMPLETED, now
    participant.completion_code = runtime.config.completion.code(SessionOutcome.COMPLETED)
    participant.compensation = runtime.config.compensation.amount(participant.score)


def abandon(session: Session, participant: Participant, now: datetime, runtime: StudyRuntime | None = None) -> None:
    """End a session that went quiet past the idle timeout; ``finished_at`` is when it was judged so (``now``).

    The timed-out outcome's code (if the study has one) is kept as the code shown should the participant come back.
    """
    participant.status, participant.finished_at = ParticipantStatus.ABANDONED, now
    if runtime is not None:
        participant.completion_code = runtime.config.completion.code(SessionOutcome.TIMED_OUT)
    log_event(session, participant.study_id, participant.id, EventKind.ABANDONED, step=participant.step.model_dump())


def consent(session: Session, participant: Participant, runtime: StudyRuntime, *, agree: bool, now: datetime) -> None:
    require_phase(participant, "consent")
    log_event(session, participant.study_id, participant.id, EventKind.CONSENT, agree=agree)
    if agree:
        participant.consented_at, participant.join_address_hash = now, None  # the address counted until consent only
        advance_step(session, participant, runtime, now)
    else:
        participant.step, participant.status, participant.finished_at = DECLINED, ParticipantStatus.DECLINED, now
        participant.completion_code = runtime.config.completion.code(SessionOutcome.DECLINED)


def finish_instructions(session: Session, participant: Participant, runtime: StudyRuntime, now: datetime) -> None:
    require_phase(participant, "instructions")
    advance_step(session, participant, runtime, now)


def finish_practice(session: Session, participant: Participant, runtime: StudyRuntime, now: datetime) -> None:
    """The participant has read that the practice is over (phase ``practice_done``): on to the scored part."""
    require_phase(participant, "practice_done")
    advance_step(session, participant, runtime, now)


def answer(session: Session, participant: Participant, runtime: StudyRuntime, *, questionnaire_id: str,
           answers: dict[str, Any], now: datetime, context: str | None = None) -> None:
    """Record a whole questionnaire page (all items at once) and move on.

    ``context`` names the page answered; without it the answers go to whichever page of this questionnaire is
    asked now (the demo asks the same questionnaire after each block and after each shelf).
    """
    step = participant.step
    require_active(participant)
    page = step.questionnaire_page(runtime.config)
    if page is None or page.questionnaire != questionnaire_id:
        raise Conflict(f"questionnaire {questionnaire_id!r} is not asked now; the session is at {describe(step)}",
                       step=step)
    if context is not None and context != page.context:
        raise Conflict(f"these answers are for page {context!r}, but the session is at {describe(step)}", step=step)
    questionnaire = runtime.config.questionnaire(questionnaire_id)
    try:
        values = validate_answers(questionnaire, answers)
    except AnswerError as exc:
        raise Invalid(str(exc), problems=getattr(exc, "problems", [str(exc)])) from None
    block = page.block
    block_name = participant.block_order[block - 1] if block and participant.block_order else None
    belief = p_highest(participant.beliefs[""]) if participant.beliefs and "" in participant.beliefs else None
    for item in questionnaire.items:
        if item.id in values:  # an optional item left blank has no row
            session.add(Answer(participant_id=participant.id, study_version_id=participant.study_version_id,
                               context=page.context, block=block, block_name=block_name, shelf=page.shelf,
                               questionnaire=questionnaire_id, item=item.id, belief=belief, answered_at=now,
                               **answer_columns(questionnaire, item, values[item.id])))
    if not screening.check_answers(session, participant, runtime, questionnaire, page, values, now):
        advance_step(session, participant, runtime, now)


def runtime_of(session: Session, runtimes: RuntimeCache, participant: Participant) -> StudyRuntime:
    """The compiled study version the participant runs under."""
    return runtimes.for_version(session, participant.study_version_id)


def touch(participant: Participant, now: datetime | None = None) -> None:
    """Note that the participant was seen ``now`` (an ended session keeps its last time: reading it is not activity).

    Written at most every ``TOUCH_INTERVAL_S``: the time is only compared with
    idle timeouts of minutes, and writing it on every request would turn every
    read (the page's state polls) into a write.
    """
    if participant.status in TERMINAL_STATUSES:
        return
    now = now or utcnow()
    last = participant.last_seen_at
    if last is None or (now - last).total_seconds() >= TOUCH_INTERVAL_S or now < last:
        participant.last_seen_at = now
