"""The study designer's services: live check with summary, config versions and their diff, duplicating a study."""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig
from experiment.config_diff import Change, diff
from experiment.config_problems import ConfigProblem, check_document, language_gaps, place
from experiment.engine import StudyRuntime
from experiment.iohmm import ModelError
from experiment.summary import StudySummary, summarize
from server.errors import Invalid, NotFound
from server.models import Participant, Study, StudyVersion
from server.services import studies

#: A copy's slug when the request names none: the original's with this suffix (fits in the 63 characters).
COPY_SUFFIX = "-copy"


def check(document: Any) -> tuple[list[ConfigProblem], StudySummary | None, list[ConfigProblem]]:
    """Every problem of a config document (``experiment.config_problems``) and, when it has none, its summary and
    its warnings (``language_gaps``)."""
    config, problems = check_document(document)
    if config is None:
        return problems, None, []
    try:
        StudyRuntime(config)  # compiled as a save compiles it, so what the check passes a save accepts
        return [], summarize(config), language_gaps(config)
    except (ModelError, ValueError) as exc:  # e.g. a trust-aware block whose model lacks an estimate it needs
        return [place(document, (), f"the study cannot run: {exc}")], None, []


def summary(config: StudyConfig) -> StudySummary:
    try:
        return summarize(config)
    except (ModelError, ValueError) as exc:
        raise Invalid(f"the study cannot run: {exc}") from None


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
