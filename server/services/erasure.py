"""Deleting a participant's data and erasing personal fields (the participant's rights: ``experiment.privacy``).

``delete_participant`` is the one deletion: a participant's withdrawal under a study that deletes (``privacy.
withdrawal: delete``), the researcher's withdrawal under such a study, and the dashboard's "Delete this participant's
data" all call it. It deletes the rows of every table with a foreign key to ``participant`` (found in the metadata,
so a table added later is covered too), then the participant, and unlinks what names them without a foreign key
(the admin audit lines about them, another session's ``duplicate_of``). What remains is one audit line,
``participant.delete``, that names no one: a keyed hash of the participant (``subject``) and of their session link
(``session_link``) recognise a repeated request, with who asked (participant or admin), the reason, the rows deleted per
table and when. Deleting again is no error: the caller answers "deleted 0".

Kept on purpose: a fitted model's provenance lists the public ids it was fitted on (``fitted_model.participants``
and its document, hashed into the trials of studies that deployed it). After a deletion that id points to nothing:
a random id, not personal data. Backups made before a deletion still hold the data until they expire
(docs/participants-rights.md).

``erase_personal`` clears a session's personal fields (``experiment.privacy.PERSONAL_FIELDS``) and keeps its research
data: a withdrawal that keeps the data, and the retention sweep (``erase_due``), which runs in the server's sweeper.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Literal

from sqlalchemy import Column, Table, delete, func, null, select, update
from sqlalchemy.orm import Session

from experiment.flow import ParticipantStatus
from experiment.privacy import NOTHING_DUE, PrivacyConfig, ended_before, retention_summary
from server.db.engine import Base
from server.models import AdminAudit, AuditAction, Participant, Study, StudyVersion
from server.schemas import PersonalDataRead
from server.services.audit import audit
from server.services.joining import app_secret, hash_token

#: Who asked for a deletion: the participant on their page, or the experimenter (the admin API, the dashboard).
Requester = Literal["participant", "admin"]

#: The server secret that keys the hashes of the deletion audit lines.
ERASURE_KEY = "erasure_key"


def subject_of(session: Session, study_id: int, public_id: str) -> str:
    """The keyed hash that names a deleted participant in the audit log: the same participant gives the same value
    (a repeated deletion is recognised), and without the server's key it cannot be traced back to an id."""
    return _keyed(session, f"participant:{study_id}:{public_id}")[:16]


def session_mark(session: Session, token: str) -> str:
    """The keyed hash that recognises a deleted session's link (a retried withdrawal, a reload of the page)."""
    return _keyed(session, f"session:{hash_token(token)}")[:32]


def _keyed(session: Session, text: str) -> str:
    return hmac.new(app_secret(session, ERASURE_KEY), text.encode(), "sha256").hexdigest()


def participant_tables() -> list[tuple[Table, Column[Any]]]:
    """Every table with a foreign key to ``participant.id``, with that column (children before parents)."""
    found = []
    for table in reversed(Base.metadata.sorted_tables):
        for key in table.foreign_keys:
            if key.column.table.name == Participant.__tablename__ and key.column.name == "id":
                found.append((table, key.parent))
    return found


def delete_participant(session: Session, study: Study, participant: Participant, *, by: Requester,
                       reason: str | None) -> dict[str, int]:
    """Delete every row of ``participant`` (module docstring) and write the audit line; returns rows per table."""
    subject = subject_of(session, study.id, participant.public_id)
    rows = {}
    for table, column in participant_tables():
        result = session.execute(delete(table).where(column == participant.id))
        rows[table.name] = result.rowcount  # type: ignore[attr-defined]  # a CursorResult
    _unlink(session, study, participant.public_id, subject)
    link = _keyed(session, f"session:{participant.token_hash}")[:32]
    detail: dict[str, Any] = {
        "subject": subject, "session_link": link, "by": by, "reason": reason, "status": str(participant.status),
        "preview": participant.preview, "version_id": participant.study_version_id,
        "language": getattr(participant, "language", None), "rows": rows | {Participant.__tablename__: 1}}
    session.delete(participant)
    session.flush()
    audit(session, AuditAction.PARTICIPANT_DELETE, study_id=study.id, **detail)
    return rows


def _unlink(session: Session, study: Study, public_id: str, subject: str) -> None:
    """What names the participant without a foreign key: the audit lines about them (their id becomes the
    ``subject`` hash) and the ``duplicate_of`` of later sessions with the same external id (a marker of the
    deleted session, so that the duplicate flag and its grouping stay)."""
    for line in session.scalars(select(AdminAudit).where(AdminAudit.study_id == study.id,
                                                         AdminAudit.participant_public_id == public_id)):
        line.participant_public_id, line.detail = None, {**(line.detail or {}), "subject": subject}
    session.execute(update(Participant).where(Participant.study_id == study.id, Participant.duplicate_of == public_id)
                    .values(duplicate_of=f"deleted-{subject}"))


@dataclass(frozen=True)
class Deletion:
    """A deletion's audit line, as a repeated request finds it."""

    study_id: int
    by: str
    version_id: int | None
    language: str | None
    at: datetime


def _deletions(session: Session, study_id: int | None = None) -> Iterator[AdminAudit]:
    query = select(AdminAudit).where(AdminAudit.action == AuditAction.PARTICIPANT_DELETE)
    if study_id is not None:
        query = query.where(AdminAudit.study_id == study_id)
    return iter(session.scalars(query.order_by(AdminAudit.id)))


def deleted_before(session: Session, study: Study, public_id: str) -> bool:
    """Whether participant ``public_id`` of ``study`` was deleted (a repeated delete answers "deleted 0")."""
    subject = subject_of(session, study.id, public_id)
    return any((line.detail or {}).get("subject") == subject for line in _deletions(session, study.id))


def deleted_session(session: Session, token: str) -> Deletion | None:
    """The deletion of the session behind ``token``, if its data were deleted (None: no such deletion)."""
    mark = session_mark(session, token)
    for line in _deletions(session):
        detail = line.detail or {}
        if detail.get("session_link") == mark and line.study_id is not None:
            return Deletion(line.study_id, str(detail.get("by")), detail.get("version_id"), detail.get("language"),
                            line.created_at)
    return None


# -- personal fields ---------------------------------------------------------------------------------------------

_ERASED: dict[str, Any] = {"external_id": None, "recruitment": {}, "resume_key_hash": None,
                           "join_address_hash": None, "survey_draft": None}


def erase_personal(participant: Participant, now: datetime) -> None:
    """Clear ``participant``'s personal fields (``experiment.privacy.PERSONAL_FIELDS``); the research data stay."""
    for name, value in _ERASED.items():
        setattr(participant, name, value)
    participant.personal_data_erased_at = participant.personal_data_erased_at or now


def erase_due(session: Session, now: datetime) -> int:
    """The retention sweep: erase the personal fields of every ended session whose study's rule (the current
    version's ``privacy``) says they are due; returns how many sessions. Idempotent: an erased session is not
    touched again. One audit line per study that erased any."""
    erased = 0
    for study_id, config in session.execute(_current_configs()):
        privacy = PrivacyConfig.model_validate((config or {}).get("privacy") or {})
        cutoff = ended_before(privacy, now)
        if cutoff == NOTHING_DUE:
            continue
        result = session.execute(update(Participant).where(
            Participant.study_id == study_id, Participant.status != ParticipantStatus.ACTIVE,
            Participant.personal_data_erased_at.is_(None), Participant.finished_at <= cutoff)
            .values({**_ERASED, "survey_draft": null(), "personal_data_erased_at": now})
            .execution_options(synchronize_session=False))
        count = result.rowcount  # type: ignore[attr-defined]  # a CursorResult
        if count:
            audit(session, AuditAction.PERSONAL_DATA_ERASE, study_id=study_id, sessions=count, rule="retention")
            erased += count
    return erased


def _current_configs() -> Any:
    """(study id, config) of each study's current (latest) version."""
    top = (select(StudyVersion.study_id, func.max(StudyVersion.version).label("version"))
           .group_by(StudyVersion.study_id).subquery())
    return (select(StudyVersion.study_id, StudyVersion.config)
            .join(top, (top.c.study_id == StudyVersion.study_id) & (top.c.version == StudyVersion.version)))


def personal_data(session: Session, study: Study, config: dict[str, Any]) -> PersonalDataRead:
    """The study's rules (its current ``config``'s ``privacy``) and what was erased and deleted so far, for the
    dashboard's study page."""
    privacy = PrivacyConfig.model_validate((config or {}).get("privacy") or {})
    erased, last = session.execute(select(func.count(Participant.personal_data_erased_at),
                                          func.max(Participant.personal_data_erased_at))
                                   .where(Participant.study_id == study.id, Participant.preview.is_(False))).one()
    deleted = sum(1 for line in _deletions(session, study.id) if not (line.detail or {}).get("preview"))
    return PersonalDataRead(withdrawal=privacy.withdrawal, retention=retention_summary(privacy),
                            erase_on=privacy.erase_personal_on.isoformat() if privacy.erase_personal_on else None,
                            erased_sessions=erased or 0, last_erased_at=_aware(last), deleted_participants=deleted)


def _aware(value: datetime | str | None) -> datetime | None:
    """A ``max()`` of a ``TZDateTime`` column, as a UTC datetime (SQLite returns the stored text)."""
    if value is None or isinstance(value, datetime):
        return value if value is None or value.tzinfo else value.replace(tzinfo=UTC)
    parsed = datetime.fromisoformat(value)
    return parsed if parsed.tzinfo else parsed.replace(tzinfo=UTC)
