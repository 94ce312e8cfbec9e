"""Idempotent participant steps: a request repeated with the same ``Idempotency-Key`` returns the stored response."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.errors import Invalid
from server.models import IdempotentResponse


def idempotent(session: Session, participant_id: int, *, key: str | None, body: Any, produce: Callable[[], Any]) -> Any:
    """Run ``produce`` once per key: a repeat with the same key and body returns the stored response."""
    if key is None:
        return produce()
    body_json = json.dumps(body.model_dump(mode="json") if hasattr(body, "model_dump") else body, sort_keys=True)
    digest = hashlib.sha256(body_json.encode()).hexdigest()
    stored = session.scalar(select(IdempotentResponse).where(IdempotentResponse.participant_id == participant_id,
                                                             IdempotentResponse.key == key))
    if stored is not None:
        if stored.request_hash != digest:
            raise Invalid(f"Idempotency-Key {key!r} was already used for a different request")
        return stored.response
    response = produce()
    payload = response.model_dump(mode="json") if hasattr(response, "model_dump") else response
    session.add(IdempotentResponse(participant_id=participant_id, key=key, request_hash=digest, response=payload))
    return response
