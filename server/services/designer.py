"""The study designer's services: live check with summary, config versions and their diff, duplicating a study."""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig, validate_document
from experiment.config_diff import Change, diff
from experiment.iohmm import ModelError
from experiment.summary import StudySummary, summarize
from server.errors import Invalid, NotFound
from server.models import Participant, Study, StudyVersion
from server.services import studies

#: A copy's slug when the request names none: the original's with this suffix (fits in the 63 characters).
COPY_SUFFIX = "-copy"


def check(document: Any) -> tuple[list[dict[str, Any]], StudySummary | None]:
    """Every problem of a config document (path, loc, message) and, when it has none, its summary."""
    try:
        config = validate_document(document)
    except ValidationError as exc:
        return [problem(document, e["loc"], e["msg"]) for e in exc.errors()], None
    try:
        return [], summarize(config)
    except (ModelError, ValueError) as exc:  # e.g. a trust-aware block whose model lacks an estimate it needs
        return [problem(document, (), f"the study cannot run: {exc}")], None


def summary(config: StudyConfig) -> StudySummary:
    try:
        return summarize(config)
    except (ModelError, ValueError) as exc:
        raise Invalid(f"the study cannot run: {exc}") from None


def problem(document: Any, loc: tuple[Any, ...], message: str) -> dict[str, Any]:
    """A validation error's place in the document: pydantic's ``loc`` without the union tags it adds (a policy's
    ``trust_aware``, ``literal['paper']``), as keys and indices and as a path a person reads."""
    path: list[str | int] = []
    node = document
    for segment in loc:
        if isinstance(node, list) and isinstance(segment, int):
            path.append(segment)
            node = node[segment] if segment < len(node) else None
        elif isinstance(node, dict) and segment in node:
            path.append(segment)
            node = node[segment]
        elif isinstance(segment, str) and _is_union_tag(node, segment):
            continue
        else:  # a missing field: its name is the place
            path.append(segment)
            node = None
    return {"path": readable(path), "loc": path, "message": message}


def _is_union_tag(node: Any, segment: str) -> bool:
    return (isinstance(node, dict) and node.get("kind") == segment) or "[" in segment


def readable(path: list[str | int]) -> str:
    """["blocks", 1, "policy", "kind"] → "blocks[1].policy.kind"."""
    text = ""
    for segment in path:
        text += f"[{segment}]" if isinstance(segment, int) else (f".{segment}" if text else str(segment))
    return text


def versions(session: Session, study: Study) -> list[tuple[StudyVersion, int]]:
    """Every version of the study, oldest first, with the number of (non-preview) participants under it."""
    counts = dict(session.execute(
        select(Participant.study_version_id, func.count()).where(Participant.study_id == study.id,
                                                                 Participant.preview.is_(False))
        .group_by(Participant.study_version_id)).all())
    rows = session.scalars(select(StudyVersion).where(StudyVersion.study_id == study.id).order_by(StudyVersion.version))
    return [(row, counts.get(row.id, 0)) for row in rows]


def version(session: Session, study: Study, number: int) -> StudyVersion:
    row = session.scalar(select(StudyVersion).where(StudyVersion.study_id == study.id, StudyVersion.version == number))
    if row is None:
        raise NotFound(f"study {study.slug!r} has no version {number}")
    return row


def version_diff(session: Session, study: Study, before: int, after: int) -> list[Change]:
    return diff(version(session, study, before).config, version(session, study, after).config)


def duplicate(session: Session, study: Study, *, slug: str | None, title: str | None,
              author: str | None) -> Study:
    """A new study (created as any new study is) with ``study``'s current configuration, retitled."""
    config = StudyConfig.model_validate(studies.current_version(session, study).config)
    title = title or f"{config.title} (copy)"[:200]
    config = StudyConfig.model_validate(config.model_dump(mode="json") | {"title": title})
    return studies.create_study(session, config, slug or study.slug[:63 - len(COPY_SUFFIX)] + COPY_SUFFIX, author)
