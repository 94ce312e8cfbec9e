"""Admin API for the study designer: the config's JSON Schema, live checks with a summary and warnings, the
instrument library, versions and their diff, duplicating a study."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query

from experiment.config import StudyConfig
from experiment.config_schema import form_schema
from experiment.instruments import BUILTIN_QUESTIONNAIRES
from experiment.questionnaire_translations import language_statuses
from server.bodies import StrictJsonRoute
from server.deps import AdminDep, RuntimesDep, SessionDep, SettingsDep, StudyDep
from server.routes.admin import study_detail
from server.schemas import (
    ConfigChangeRead,
    ConfigCheckCreate,
    ConfigCheckRead,
    ConfigDiffRead,
    ConfigProblemRead,
    InstrumentLanguageRead,
    InstrumentRead,
    StudyDetailRead,
    StudyDuplicateCreate,
    StudySummaryRead,
    StudyVersionRead,
    error_responses,
)
from server.services import designer, studies

router = APIRouter(route_class=StrictJsonRoute, prefix="/api/admin", tags=["admin"], dependencies=[AdminDep])

#: Versions are database integers: a larger number is refused as input (422) rather than overflowing the query (500).
_MAX_VERSION = 2**31 - 1


@router.get("/study-config-schema")
def study_config_schema() -> dict[str, Any]:
    """The study config's JSON Schema for a form: references inlined, union options titled, every field required
    except those a document may leave out (the typed bodies' schema is ``StudyConfig`` in ``/openapi.json``)."""
    return form_schema()


@router.post("/study-config/check", response_model=ConfigCheckRead)
def check_config(body: ConfigCheckCreate) -> ConfigCheckRead:
    """Validate a document without saving it: 200 with every problem (path and message), or the summary and the
    warnings (e.g. a questionnaire without a translation for a language the study offers)."""
    problems, summary, warnings = designer.check(body.config)
    return ConfigCheckRead(valid=not problems, problems=[ConfigProblemRead(**asdict(p)) for p in problems],
                           warnings=[ConfigProblemRead(**asdict(w)) for w in warnings],
                           summary=StudySummaryRead.model_validate(asdict(summary)) if summary else None)


@router.get("/instruments", response_model=list[InstrumentRead])
def list_instruments() -> list[InstrumentRead]:
    """The instrument library: each built-in questionnaire a study can name by id, with its citation and, per
    language, whether its texts are the original, a published translation or the lab's own (not validated)."""
    return [InstrumentRead(id=q.id, title=q.title, version=q.version, items=len(q.items), about_robot=q.about_robot,
                           citation=q.citation, doi=q.doi,
                           languages=[InstrumentLanguageRead(language=tag, status=status, citation=citation)
                                      for tag, status, citation in language_statuses(q)])
            for q in BUILTIN_QUESTIONNAIRES.values()]


@router.get("/studies/{slug}/summary", response_model=StudySummaryRead, responses=error_responses(404))
def study_summary(study: StudyDep, session: SessionDep) -> StudySummaryRead:
    """The current version's summary: trials, duration, block orders, policies in words, questionnaires, pay."""
    config = StudyConfig.model_validate(studies.current_version(session, study).config)
    return StudySummaryRead.model_validate(asdict(designer.summary(config)))


@router.get("/studies/{slug}/versions", response_model=list[StudyVersionRead], responses=error_responses(404))
def list_versions(study: StudyDep, session: SessionDep) -> list[StudyVersionRead]:
    """Every config version, oldest first: when, who, its hash and how many participants ran under it."""
    return [StudyVersionRead(version=row.version, created_at=row.created_at,
                             author=row.author or studies.DEFAULT_AUTHOR, config_hash=row.config_hash,
                             participants=count)
            for row, count in designer.versions(session, study)]


@router.get("/studies/{slug}/versions/diff", response_model=ConfigDiffRead, responses=error_responses(404))
def diff_versions(study: StudyDep, session: SessionDep,
                  before: Annotated[int, Query(alias="from", ge=1, le=_MAX_VERSION,
                                               description="The version compared from (either order works)")],
                  after: Annotated[int, Query(alias="to", ge=1, le=_MAX_VERSION,
                                              description="The version compared to")]) -> ConfigDiffRead:
    """What changed from one config version to another, field by field (from > to shows the change undone)."""
    changes = designer.version_diff(session, study, before, after)
    return ConfigDiffRead(from_version=before, to_version=after,
                          changes=[ConfigChangeRead(path=c.path, kind=c.kind, before=c.before, after=c.after)
                                   for c in changes])


@router.post("/studies/{slug}/duplicate", response_model=StudyDetailRead, status_code=201,
             responses=error_responses(404, 409))
def duplicate_study(study: StudyDep, session: SessionDep, settings: SettingsDep, runtimes: RuntimesDep,
                    body: Annotated[StudyDuplicateCreate | None, Body()] = None) -> StudyDetailRead:
    """A new study with this one's current configuration (e.g. the next wave); its slug must be free (409). The
    body may be left out: every field has a default."""
    body = body or StudyDuplicateCreate()
    copy = designer.duplicate(session, study, slug=body.slug, title=body.title, author=body.author)
    runtimes.get(studies.current_version(session, copy))
    return study_detail(session, copy, settings)
