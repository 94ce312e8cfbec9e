"""FastAPI dependencies: one lookup each, so handlers stay short.

Two ways a handler reaches the database (``server.db.units``): ``UnitsDep`` runs units of work on the event loop,
one trip each (every participant request: ``Units.participant`` opens the session behind the token, applies its due
transitions and, given an Idempotency-Key, answers a repeat with the stored response); ``SessionDep`` is one
request-long session in a worker thread (the admin API, whose requests may read much).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Header, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from server.app_services import Services, services_of
from server.bodies import refuse_unknown_query
from server.models import Participant, Study, utcnow
from server.services import admin as admin_service
from server.services.idempotency import idempotent
from server.services.sessions import open_session, touch
from server.services.studies import RuntimeCache, get_study
from server.services.trials import AttemptPlanner, advance
from server.settings import Settings

T = TypeVar("T")


def get_services(request: Request) -> Services:
    return services_of(request.app)


ServicesDep = Annotated[Services, Depends(get_services)]


def get_settings(request: Request) -> Settings:
    return services_of(request.app).settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_runtimes(request: Request) -> RuntimeCache:
    return services_of(request.app).runtimes


RuntimesDep = Annotated[RuntimeCache, Depends(get_runtimes)]


async def _turn_dependency(request: Request) -> AsyncIterator[None]:
    async with services_of(request.app).database.turn(request.state):
        yield


def get_session(request: Request, _turn: Annotated[None, Depends(_turn_dependency, scope="function")]
                ) -> Iterator[Session]:
    """One unit of work per request, committed (and on disk) before the response is sent."""
    with services_of(request.app).database.begin() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session, scope="function")]


def study_dependency(slug: str, session: SessionDep) -> Study:
    """The study named in the path, read in the request's own session (``SessionDep`` is cached per request, so
    the route that also takes ``SessionDep`` gets the same session); 404 for an unknown slug."""
    return get_study(session, slug)


StudyDep = Annotated[Study, Depends(study_dependency)]


Token = Annotated[str, Path(min_length=16, max_length=128, description="The participant's session token")]


@dataclass
class ParticipantContext:
    session: Session
    study: Study
    participant: Participant
    runtime: StudyRuntime
    planner: AttemptPlanner
    now: datetime


def open_participant(session: Session, runtimes: RuntimeCache, planner: AttemptPlanner,
                     token: str) -> ParticipantContext:
    """The session behind a token, with its due time-based transitions applied."""
    participant, study, runtime = open_session(session, runtimes, token, lock=True)
    now = utcnow()
    touch(participant, now)
    advance(session, participant, runtime, now=now, planner=planner)
    return ParticipantContext(session, study, participant, runtime, planner, now)


_NO_BODY = object()


@dataclass(frozen=True)
class Units:
    """A request's units of work (``server.db.units.Database.run``): one transaction, one trip, each."""

    services: Services
    request: Request

    async def run(self, work: Callable[[Session], T]) -> T:
        return await self.services.database.run(work, self.request.state)

    async def participant(self, token: str, act: Callable[[ParticipantContext], T], *, key: str | None = None,
                          body: Any = _NO_BODY) -> T:
        """``act`` on the session behind ``token`` (``open_participant``) in one unit; with a ``body``, once per
        Idempotency-Key ``key`` (a repeat with the same key and body gets the stored response)."""
        services = self.services

        def work(session: Session) -> T:
            ctx = open_participant(session, services.runtimes, services.hub, token)
            if body is _NO_BODY:
                return act(ctx)
            return idempotent(session, ctx.participant.id, key=key, body=body, produce=lambda: act(ctx))

        return await self.run(work)


def get_units(request: Request) -> Units:
    return Units(services_of(request.app), request)


UnitsDep = Annotated[Units, Depends(get_units)]


#: Documents the admin API's bearer token in the OpenAPI schema; a missing or malformed header is a 401 with a reason.
_admin_bearer = HTTPBearer(auto_error=False, scheme_name="adminToken",
                           description="The admin token printed by 'trustlab serve' or 'trustlab admin-token'")
#: The same, for routes that accept other credentials too (the report page: ``server.routes.report``).
admin_bearer = _admin_bearer


async def require_admin(units: UnitsDep,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_admin_bearer)]) -> None:
    """Checks the token in a short transaction of its own (a long admin request, a report or an export, must not
    keep the database from participants), then that the query names only parameters the route takes."""
    token = credentials.credentials.strip() if credentials else None
    await units.run(lambda session: admin_service.verify_admin(session, token))
    refuse_unknown_query(units.request)


AdminDep = Depends(require_admin)

IdempotencyKey = Annotated[str | None, Header(alias="Idempotency-Key", min_length=1, max_length=128,
                                              description="Repeat a request safely: the same key returns the stored "
                                                          "response.")]
