"""FastAPI dependencies: one lookup each, so handlers stay short."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Header, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from server.models import Participant, Study, utcnow
from server.services import admin as admin_service
from server.services.idempotency import idempotent
from server.services.sessions import open_session, touch
from server.services.studies import RuntimeCache, get_study
from server.services.trials import AttemptPlanner, advance
from server.settings import Settings
from server.units import database_turn, durable_transaction, run_unit


async def _turn_dependency(request: Request) -> AsyncIterator[None]:
    async with database_turn(request.app, request.state):
        yield


def get_session(request: Request, _turn: Annotated[None, Depends(_turn_dependency, scope="function")]) -> Iterator[Session]:
    """One unit of work per request, committed (and on disk) before the response is sent."""
    with durable_transaction(request.app) as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session, scope="function")]


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_runtimes(request: Request) -> RuntimeCache:
    return request.app.state.runtimes


RuntimesDep = Annotated[RuntimeCache, Depends(get_runtimes)]


def get_planner(request: Request) -> AttemptPlanner:
    return request.app.state.world


PlannerDep = Annotated[AttemptPlanner, Depends(get_planner)]


def study_dependency(slug: str, session: SessionDep) -> Study:
    """The study named in the path, read in the request's own session (``SessionDep`` is cached per request, so
    the route that also takes ``SessionDep`` gets the same session); 404 for an unknown slug."""
    return get_study(session, slug)


StudyDep = Annotated[Study, Depends(study_dependency)]


Token = Annotated[str, Path(min_length=16, max_length=128, description="The participant's session token")]
T = TypeVar("T")


async def unit_of_work(request: Request, work: Callable[[Session], T]) -> T:
    """``run_unit`` for a request: one transaction, one trip, instead of ``SessionDep``'s dependency, handler and
    commit each taking a separate trip between the event loop and the worker threads."""
    return await run_unit(request.app, work, request.state)


async def in_participant_session(request: Request, token: str, work: Callable[[ParticipantContext], T]) -> T:
    """``unit_of_work`` for the session behind ``token`` (see ``open_participant``)."""
    app = request.app
    return await unit_of_work(request, lambda session: work(open_participant(session, app.state.runtimes,
                                                                             app.state.world, token)))


@dataclass
class ParticipantContext:
    session: Session
    study: Study
    participant: Participant
    runtime: StudyRuntime
    planner: AttemptPlanner
    now: datetime


def open_participant(session: Session, runtimes: RuntimeCache, planner: AttemptPlanner, token: str) -> ParticipantContext:
    """The session behind a token, with its due time-based transitions applied."""
    participant, study, runtime = open_session(session, runtimes, token, lock=True)
    now = utcnow()
    touch(participant, now)
    advance(session, participant, runtime, now=now, planner=planner)
    return ParticipantContext(session, study, participant, runtime, planner, now)


def participant_context(session: SessionDep, runtimes: RuntimesDep, planner: PlannerDep, token: Token) -> ParticipantContext:
    return open_participant(session, runtimes, planner, token)


ParticipantDep = Annotated[ParticipantContext, Depends(participant_context)]


#: Documents the admin API's bearer token in the OpenAPI schema; a missing or malformed header is a 401 with a reason.
_admin_bearer = HTTPBearer(auto_error=False, scheme_name="adminToken",
                           description="The admin token printed by 'trustlab serve' or 'trustlab admin-token'")
#: The same, for routes that accept other credentials too (the report page: ``server.routes.report``).
admin_bearer = _admin_bearer


async def require_admin(request: Request,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_admin_bearer)]) -> None:
    """Checks the token in a short transaction of its own: a long admin request (a report, an export) must not
    keep the database from participants."""
    token = credentials.credentials.strip() if credentials else None
    await unit_of_work(request, lambda session: admin_service.verify_admin(session, token))


AdminDep = Depends(require_admin)

IdempotencyKey = Annotated[str | None, Header(alias="Idempotency-Key", min_length=1, max_length=128,
                                              description="Repeat a request safely: the same key returns the stored response.")]


async def idempotent_step(request: Request, token: str, key: str | None, body: Any,
                          act: Callable[[ParticipantContext], T]) -> T:
    """``act`` on the session behind ``token``, once per Idempotency-Key (``in_participant_session`` + ``idempotent``)."""
    return await in_participant_session(request, token, lambda ctx: idempotent(ctx.session, ctx.participant.id, key=key,
                                                                             body=body, produce=lambda: act(ctx)))
