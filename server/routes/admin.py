"""Admin API (bearer token): studies, versions, participants, exclusion, withdrawal, deletion."""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query

from experiment.languages import TAG_PATTERN
from experiment.templates import TEMPLATES
from server.bodies import StrictJsonRoute
from server.deps import AdminDep, RuntimesDep, ServicesDep, SessionDep, SettingsDep, StudyDep
from server.errors import Invalid
from server.loadmeter import load_status
from server.models import Study, StudyVersion, utcnow
from server.schemas import (
    DeletedRead,
    OkRead,
    ParticipantDelete,
    ParticipantRead,
    ParticipantUpdate,
    PreviewRead,
    ServerLoadRead,
    StudyConfigUpdate,
    StudyCreate,
    StudyDetailRead,
    StudyRead,
    TemplateRead,
    error_responses,
)
from server.services import admin, erasure, sessions, studies

router = APIRouter(route_class=StrictJsonRoute, prefix="/api/admin", tags=["admin"], dependencies=[AdminDep])


def _study_fields(session, study: Study, settings, version: StudyVersion) -> dict[str, Any]:
    cap, refused = studies.admission(session, study, version)
    return dict(slug=study.slug, title=study.title, status=study.status, version=version.version,
                config_hash=version.config_hash, join_url=f"{settings.base_url()}/join/{study.slug}",
                participants=studies.participant_counts(session, study),
                preview_sessions=studies.preview_count(session, study), max_active_participants=cap,
                refused_joins=refused, created_at=study.created_at,
                personal_data=erasure.personal_data(session, study, version.config))


def study_read(session, study: Study, settings) -> StudyRead:
    return StudyRead(**_study_fields(session, study, settings, studies.current_version(session, study)))


def study_detail(session, study: Study, settings) -> StudyDetailRead:
    """``study_read`` with the current config."""
    version = studies.current_version(session, study)
    return StudyDetailRead(**_study_fields(session, study, settings, version), config=version.config)


@router.get("/templates", response_model=list[TemplateRead])
def list_templates() -> list[TemplateRead]:
    return [TemplateRead(name=name, config=make().model_dump(mode="json")) for name, make in TEMPLATES.items()]


@router.get("/studies", response_model=list[StudyRead])
def list_studies(session: SessionDep, settings: SettingsDep) -> list[StudyRead]:
    return [study_read(session, s, settings) for s in session.query(Study).order_by(Study.id)]


@router.post("/studies", response_model=StudyDetailRead, status_code=201, responses=error_responses(409))
def create_study(body: StudyCreate, session: SessionDep, settings: SettingsDep,
                 runtimes: RuntimesDep) -> StudyDetailRead:
    """Create a study from a template name or a full config document: a draft unless ``status`` is "open"."""
    if body.template is not None and body.config is None:
        config = studies.template_config(body.template)
    elif body.config is not None and body.template is None:
        config = body.config
    else:
        raise Invalid("give exactly one of 'template' (a template name) or 'config' (a study config document)")
    study = studies.create_study(session, config, body.slug, body.author, status=body.status)
    runtimes.get(studies.current_version(session, study))  # its policies must solve, or 422 and nothing is created
    return study_detail(session, study, settings)


@router.get("/studies/{slug}", response_model=StudyDetailRead, responses=error_responses(404))
def get_study(study: StudyDep, session: SessionDep, settings: SettingsDep) -> StudyDetailRead:
    return study_detail(session, study, settings)


@router.put("/studies/{slug}/config", response_model=StudyDetailRead, responses=error_responses(404))
def update_config(study: StudyDep, body: StudyConfigUpdate, session: SessionDep, settings: SettingsDep,
                  runtimes: RuntimesDep) -> StudyDetailRead:
    """Save a config: a new version (records keep theirs); the current config again changes nothing."""
    runtimes.get(studies.update_config(session, study, body.config, body.author))
    return study_detail(session, study, settings)


@router.post("/studies/{slug}/open", response_model=StudyRead, responses=error_responses(404))
def open_study(study: StudyDep, session: SessionDep, settings: SettingsDep) -> StudyRead:
    """Open a draft to participants, or reopen a closed study; opening an open study changes nothing."""
    return study_read(session, studies.set_status(session, study, "open"), settings)


@router.post("/studies/{slug}/close", response_model=StudyRead, responses=error_responses(404, 409))
def close_study(study: StudyDep, session: SessionDep, settings: SettingsDep) -> StudyRead:
    """Stop new joins (running sessions go on to their end); closing a closed study changes nothing, a draft
    cannot be closed (409)."""
    return study_read(session, studies.set_status(session, study, "closed"), settings)


@router.get("/studies/{slug}/participants", response_model=list[ParticipantRead], responses=error_responses(404))
def participants(study: StudyDep, session: SessionDep) -> list[ParticipantRead]:
    """Live progress: phase, block, trial, score, current belief and its history, last seen, quality flags."""
    return admin.list_participants(session, study, utcnow())


@router.post("/studies/{slug}/participants/{public_id}/exclude", response_model=OkRead,
             responses=error_responses(404))
def exclude(study: StudyDep, public_id: str, body: ParticipantUpdate, session: SessionDep) -> OkRead:
    admin.exclude(session, study, admin.participant_by_public_id(session, study, public_id), reason=body.reason)
    return OkRead()


@router.post("/studies/{slug}/participants/{public_id}/include", response_model=OkRead,
             responses=error_responses(404))
def include(study: StudyDep, public_id: str, body: ParticipantUpdate, session: SessionDep) -> OkRead:
    admin.exclude(session, study, admin.participant_by_public_id(session, study, public_id), reason=body.reason,
                excluded=False)
    return OkRead()


@router.post("/studies/{slug}/participants/{public_id}/withdraw", response_model=OkRead,
             responses=error_responses(404, 409))
def withdraw(study: StudyDep, public_id: str, body: ParticipantUpdate, session: SessionDep,
             runtimes: RuntimesDep) -> OkRead:
    """Withdraw the participant on their request (the reason is kept in the audit log): the session ends as
    withdrawn and their data are kept (marked withdrawn and excluded, personal fields erased) or deleted, as their
    study version's ``privacy.withdrawal`` says. 409 when already withdrawn."""
    participant = admin.participant_by_public_id(session, study, public_id)
    admin.withdraw(session, study, participant, sessions.runtime_of(session, runtimes, participant),
                   reason=body.reason, now=utcnow())
    return OkRead()


@router.post("/studies/{slug}/preview", response_model=PreviewRead, status_code=201, responses=error_responses(404))
def start_preview(study: StudyDep, session: SessionDep, settings: SettingsDep, runtimes: RuntimesDep,
                  language: Annotated[str | None, Query(max_length=16, pattern=TAG_PATTERN)] = None) -> PreviewRead:
    """Start a preview session: go through the study as a participant would, whatever its status (draft, open,
    closed) and cap. It is marked preview: left out of counterbalancing, the cap, exports, reports and fits unless
    asked for (``include_preview``), and can be deleted. Each request starts a new one, in ``language`` when the
    study offers it (else the study's default language)."""
    participant, token = sessions.start_preview(session, study, runtimes, language)
    return PreviewRead(public_id=participant.public_id, token=token, participant_url=f"{settings.base_url()}/p/{token}")


@router.delete("/studies/{slug}/participants/{public_id}", response_model=DeletedRead,
               responses=error_responses(404, 409))
def delete_participant(study: StudyDep, public_id: str, session: SessionDep,
                       body: Annotated[ParticipantDelete | None, Body()] = None) -> DeletedRead:
    """Delete a participant with every row of theirs (trials, answers, events, teleoperation logs, stored
    responses): a real participant on request, with the ``reason`` in the body (409 without one), leaving an audit
    line that names no one; a preview session without a reason. Deleting again is fine (``deleted`` 0)."""
    return DeletedRead(deleted=admin.delete_participant(session, study, public_id,
                                                        reason=body.reason if body else None))


@router.delete("/studies/{slug}/previews", response_model=DeletedRead, responses=error_responses(404))
def delete_previews(study: StudyDep, session: SessionDep) -> DeletedRead:
    """Delete every preview session of the study with their rows (audited); real participants are untouched."""
    return DeletedRead(deleted=admin.delete_previews(session, study))


@router.get("/server/load", response_model=ServerLoadRead)
async def server_load(services: ServicesDep) -> ServerLoadRead:
    """How this server process is keeping up over the last minute: the world loop's rate, how often it started
    late, what the 3D views skipped, and a status in words (``server.loadmeter``)."""
    figures = services.load_history.figures()
    world_hz = services.settings.world_hz
    faults = services.faults.recent()
    status, message = load_status(figures, world_hz, world_loop=services.settings.world_loop, faults=faults)
    attempts, arms = services.hub.moving(time.monotonic())
    viewers = services.viewers
    return ServerLoadRead(
        status=status, message=message, window_s=round(figures.window_s, 1) if figures else 0.0, world_hz=world_hz,
        world_ticks_per_s=round(figures.ticks_per_s, 2) if figures else None,
        late_tick_share=round(figures.late_share, 4) if figures else None,
        longest_tick_delay_ms=round(1000 * figures.latest_start_s, 1) if figures else None,
        view_skipped_share=round(figures.skipped_share, 4) if figures else None,
        viewers=viewers.viewer_count(), attempts_playing=attempts,
        arms_teleoperated=arms, faults_recent=len(faults))
