"""The admin audit log and the participant event log (both append-only)."""

from __future__ import annotations

import time
from typing import Any

from sqlalchemy.orm import Session

from experiment.events import EventKind, client_kind
from server.models import AdminAudit, AuditAction, Event


def audit(session: Session, action: AuditAction, *, study_id: int | None = None, participant: str | None = None,
          **detail: Any) -> None:
    session.add(AdminAudit(action=action, study_id=study_id, participant_public_id=participant, detail=detail))


def log_event(session: Session, study_id: int, participant_id: int | None, kind: EventKind, *,
              client_time_ms: float | None = None, payload: dict[str, Any] | None = None, **fields: Any) -> None:
    """Append one event the server writes; ``payload`` and ``fields`` are stored together."""
    _append(session, study_id, participant_id, kind, client_time_ms, {**(payload or {}), **fields})


def log_client_event(session: Session, study_id: int, participant_id: int, kind: str, *,
                     client_time_ms: float | None, payload: dict[str, Any]) -> None:
    """Append one event a page posted (its own ``kind``, stored as ``client.<kind>``)."""
    _append(session, study_id, participant_id, client_kind(kind), client_time_ms, payload)


def _append(session: Session, study_id: int, participant_id: int | None, kind: str, client_time_ms: float | None,
            payload: dict[str, Any]) -> None:
    session.add(Event(study_id=study_id, participant_id=participant_id, kind=kind, payload=payload,
                      client_time_ms=client_time_ms, server_monotonic_s=time.monotonic()))
