"""Admin credentials, the participants table, exclusion, withdrawal and deletion."""

from __future__ import annotations

import hmac
import secrets
from collections import defaultdict
from datetime import datetime
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from experiment.attention import count_failures
from experiment.engine import StudyRuntime
from experiment.flow import ParticipantStatus, ShelfSurveyStep, TrialStep
from experiment.outcomes import outcome_of_status
from experiment.quality import participant_flags, same_external_id
from experiment.questionnaires import Questionnaire
from experiment.trust_belief import p_highest
from server.errors import Conflict, NotFound, Unauthorized
from server.models import (
    AdminAudit,
    AdminCredential,
    Answer,
    AuditAction,
    Participant,
    Study,
    StudyVersion,
    Trial,
)
from server.schemas import ParticipantRead, QualityFlagRead
from server.services import erasure, withdrawal
from server.services.audit import audit
from server.services.sessions import hash_token

ADMIN_TOKEN_BYTES = 32


def ensure_admin_token(session: Session) -> str | None:
    """Create the first admin token if there is none; returns it (shown once) or None."""
    if session.scalar(select(AdminCredential.id).where(AdminCredential.active.is_(True)).limit(1)) is not None:
        return None
    return _new_token(session)


def rotate_admin_token(session: Session, now: datetime) -> str:
    """Revoke every admin token and issue a new one."""
    for credential in session.scalars(select(AdminCredential).where(AdminCredential.active.is_(True))):
        credential.active, credential.revoked_at = False, now
    audit(session, AuditAction.ADMIN_ROTATE_TOKEN)
    return _new_token(session)


def _new_token(session: Session) -> str:
    token = "tla_" + secrets.token_urlsafe(ADMIN_TOKEN_BYTES)
    session.add(AdminCredential(token_hash=hash_token(token)))
    session.flush()
    return token


def verify_admin(session: Session, token: str | None) -> None:
    if not token:
        raise Unauthorized("admin API: send 'Authorization: Bearer <admin token>'")
    digest = hash_token(token)
    hashes = session.scalars(select(AdminCredential.token_hash).where(AdminCredential.active.is_(True))).all()
    if not any(hmac.compare_digest(digest, h) for h in hashes):
        raise Unauthorized("admin API: the token is not valid (rotate with 'trustlab admin-token --rotate')")


def participant_by_public_id(session: Session, study: Study, public_id: str) -> Participant:
    participant = session.scalar(select(Participant).where(Participant.study_id == study.id,
                                                           Participant.public_id == public_id))
    if participant is None:
        raise NotFound(f"no participant {public_id!r} in study {study.slug!r}")
    return participant


def list_participants(session: Session, study: Study, now: datetime) -> list[ParticipantRead]:
    """Every participant with their belief history and quality flags (one query per table for the whole study)."""
    versions = dict(session.execute(select(StudyVersion.id, StudyVersion.version)
                                    .where(StudyVersion.study_id == study.id)).all())
    rows = session.scalars(select(Participant).where(Participant.study_id == study.id).order_by(Participant.id)).all()
    trials = _study_records(session, study, Trial, _TRIAL_FIELDS)
    answers = _study_records(session, study, Answer, _ANSWER_FIELDS)
    # Counted from the answers already read, not from the events (a poll every 2 s would scan the study's events).
    questionnaires = _attention_questionnaires(session, {p.study_version_id for p in rows})
    same_id = same_external_id({"participant_id": p.public_id, "duplicate_of": p.duplicate_of} for p in rows)
    return [_participant_read(p, versions[p.study_version_id], trials[p.id], answers[p.id], now=now,
                              attention_failures=count_failures(answers[p.id], questionnaires[p.study_version_id]),
                              same_id_as=same_id[p.public_id])
            for p in rows]


_TRIAL_FIELDS = ("practice", "complexity", "robot_action", "human_action", "teleop_success", "belief_after",
                 "window_opened_by")
_ANSWER_FIELDS = ("context", "questionnaire", "item", "value", "text")


def _attention_questionnaires(session: Session, version_ids: set[int]) -> defaultdict[int, dict[str, Questionnaire]]:
    """The questionnaires with attention checks of each configuration version participants ran under, by id, as its
    stored document holds them (only those are read: the table is polled, and a study may have many versions)."""
    found: defaultdict[int, dict[str, Questionnaire]] = defaultdict(dict)
    for version_id, config in session.execute(select(StudyVersion.id, StudyVersion.config)
                                              .where(StudyVersion.id.in_(version_ids))):
        for document in (config or {}).get("questionnaires", []):
            items = document.get("items", []) if isinstance(document, dict) else []
            if not any(isinstance(item, dict) and "instructed_response" in item for item in items):
                continue
            try:
                q = Questionnaire.model_validate(document)
            except ValueError:  # a document that does not read counts no failures rather than failing the table
                continue
            found[version_id][q.id] = q
    return found


def _study_records(session: Session, study: Study, table: type[Trial] | type[Answer],
                   fields: tuple[str, ...]) -> defaultdict[int, list[dict[str, Any]]]:
    """The study's rows of ``table`` as plain dicts (the inputs of experiment.quality), grouped by participant."""
    within = (Trial.block, Trial.trial) if table is Trial else (Answer.id,)  # trials in the order they were run
    query = (select(table.participant_id, *(getattr(table, f) for f in fields)).join(Participant)
             .where(Participant.study_id == study.id).order_by(table.participant_id, *within))
    grouped: defaultdict[int, list[dict[str, Any]]] = defaultdict(list)
    for row in session.execute(query):
        grouped[row.participant_id].append(dict(zip(fields, row[1:], strict=True)))
    return grouped


def _participant_read(p: Participant, version: int, trials: list[dict[str, Any]], answers: list[dict[str, Any]], *,
                      now: datetime, attention_failures: int = 0,
                      same_id_as: list[str] | None = None) -> ParticipantRead:
    step = p.step
    block = step.block_position
    history = [round(t["belief_after"], 4) for t in trials if not t["practice"] and t["belief_after"] is not None]
    flags = participant_flags(trials, answers, status=p.status, last_seen_at=p.last_seen_at, now=now,
                              attention_failures=attention_failures, same_id_as=same_id_as or ())
    return ParticipantRead(
        public_id=p.public_id, external_id=p.external_id, status=p.status, phase=step.phase, block=block,
        block_name=p.block_order[block - 1] if block and p.block_order else None,
        trial=step.trial if isinstance(step, TrialStep | ShelfSurveyStep) else None, score=p.score,
        belief=p_highest(p.beliefs[""]) if p.beliefs and "" in p.beliefs else None, block_order=p.block_order,
        excluded=p.excluded,
        exclusion_reason=p.exclusion_reason, completion_code=p.completion_code, version=version, preview=p.preview,
        created_at=p.created_at, last_seen_at=p.last_seen_at, belief_history=history,
        flags=[QualityFlagRead(code=f.code, detail=f.detail) for f in flags], attention_failures=attention_failures,
        outcome=outcome_of_status(p.status))


def exclude(session: Session, study: Study, participant: Participant, *, reason: str, excluded: bool = True) -> None:
    participant.excluded, participant.exclusion_reason = excluded, reason if excluded else None
    audit(session, AuditAction.PARTICIPANT_EXCLUDE if excluded else AuditAction.PARTICIPANT_INCLUDE, study_id=study.id,
          participant=participant.public_id, reason=reason)


def withdraw(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, *, reason: str,
             now: datetime) -> bool:
    """Withdraw a participant on their request (``server.services.withdrawal``): their data are kept (marked
    withdrawn and excluded, personal fields erased) or deleted, as their study version's ``privacy.withdrawal``
    says; returns whether they were deleted. 409 once withdrawn."""
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(f"participant {participant.public_id} is already withdrawn")
    _, deleted = withdrawal.withdraw(session, study, participant, runtime, by="researcher", reason=reason, now=now)
    return deleted


def delete_participant(session: Session, study: Study, public_id: str, *, reason: str | None) -> int:
    """Delete participant ``public_id`` with all their rows; returns 1, or 0 when an earlier request deleted them (a
    retry is fine). A real participant's data are deleted on request with a ``reason`` (409 without one), leaving an
    audit line that names no one (``server.services.erasure``); a preview session needs no reason (its audit line
    keeps its id: it is no one's data). 404 for an id the study never had."""
    participant = session.scalar(select(Participant).where(Participant.study_id == study.id,
                                                           Participant.public_id == public_id))
    if participant is None:
        if _deleted_before(session, study, public_id) or erasure.deleted_before(session, study, public_id):
            return 0
        raise NotFound(f"no participant {public_id!r} in study {study.slug!r}")
    if participant.preview:
        _delete_rows(session, participant)
        audit(session, AuditAction.PARTICIPANT_DELETE_PREVIEW, study_id=study.id, participant=public_id)
        return 1
    if not reason or not reason.strip():
        raise Conflict(f"participant {public_id} is a real participant: give the reason their data are deleted (e.g. "
                      "'asked by email on 3 March'); it is kept in the audit log, so write no personal data in it")
    erasure.delete_participant(session, study, participant, by="admin", reason=reason.strip())
    return 1


def delete_previews(session: Session, study: Study) -> int:
    """Delete every preview session of ``study`` with their rows; returns how many (0 when there are none)."""
    previews = session.scalars(select(Participant).where(Participant.study_id == study.id,
                                                         Participant.preview.is_(True))).all()
    for participant in previews:
        _delete_rows(session, participant)
        audit(session, AuditAction.PARTICIPANT_DELETE_PREVIEW, study_id=study.id, participant=participant.public_id)
    return len(previews)


def _delete_rows(session: Session, participant: Participant) -> None:
    for table, column in erasure.participant_tables():
        session.execute(delete(table).where(column == participant.id))
    session.delete(participant)
    session.flush()


def _deleted_before(session: Session, study: Study, public_id: str) -> bool:
    return session.scalar(select(AdminAudit.id).where(
        AdminAudit.study_id == study.id, AdminAudit.action == AuditAction.PARTICIPANT_DELETE_PREVIEW,
        AdminAudit.participant_public_id == public_id).limit(1)) is not None
