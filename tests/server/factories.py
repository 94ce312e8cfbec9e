"""Plain keyword-only helpers that build apps, studies and participants for tests."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from fastapi import FastAPI
from fastapi.routing import iter_route_contexts
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from experiment.config import AlwaysAutoSpec, BlockConfig, PracticeConfig, PracticeTrial, StudyConfig, TimingConfig
from experiment.engine import StudyRuntime
from experiment.schedule import CountsSchedule
from experiment.task import Complexity, RobotAction
from experiment.templates import demo, demo_fast
from server.harness.live import BOT_TELEOP_SETTINGS
from server.main import create_app
from server.models import Participant, Study
from server.services.admin import ensure_admin_token
from server.services.studies import RuntimeCache
from server.settings import Settings


def make_client(*, database_url: str, **settings: Any) -> tuple[TestClient, str]:
    """A TestClient on a fresh app (world loop off unless asked; ``BOT_TELEOP_SETTINGS`` unless given; attempts
    planned in-process unless ``planner_processes`` is given: the client may never run the app's shutdown, which
    stops the helper process) and its admin token."""
    settings = {"planner_processes": 0} | BOT_TELEOP_SETTINGS | settings
    app = create_app(Settings(database_url=database_url, world_loop=settings.pop("world_loop", False), **settings))
    with app.state.services.sessionmaker.begin() as session:
        token = ensure_admin_token(session)
    assert token is not None
    return TestClient(app), token


def fast_config(config: StudyConfig | None = None, **changes: Any) -> StudyConfig:
    """A study that runs fast (short decision window, sped-up robot) for API tests."""
    config = config or demo()
    return config.model_copy(update={"timing": demo_fast().timing, **changes})


def make_study(client: TestClient, admin_token: str, *, config: StudyConfig | None = None, slug: str = "s1",
               status: str = "open") -> dict:
    """A study created through the admin API, open to participants unless ``status`` is "draft"."""
    response = client.post("/api/admin/studies",
                           json={"status": status, "slug": slug,
                                 "config": (config or fast_config()).model_dump(mode="json")},
                           headers=auth(admin_token))
    assert response.status_code == 201, response.text
    return response.json()


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


#: ``join``'s default resume key: the client's own, as the join page sends the one its browser keeps.
BROWSER = "browser"


def browser_key(client: TestClient) -> str:
    """The client's resume key (one per client: each TestClient is one browser)."""
    if not getattr(client, "resume_key", None):
        client.resume_key = secrets.token_urlsafe(16)  # type: ignore[attr-defined]
    return client.resume_key  # type: ignore[attr-defined]


def join(client: TestClient, slug: str = "s1", *, resume_key: str | None = BROWSER, **params: str) -> dict:
    """Join with recruitment ``params`` and, unless ``resume_key`` says otherwise, the client's resume key."""
    key = browser_key(client) if resume_key == BROWSER else resume_key
    response = client.post(f"/api/studies/{slug}/join", params=params, json={"resume_key": key} if key else None)
    assert response.status_code == 200, response.text
    return response.json()


def app_routes(app: FastAPI) -> list[tuple[str, str, bool]]:
    """Every route of ``app``, however deeply included: (method or "WEBSOCKET", path, in the OpenAPI schema)."""
    routes = []
    for route in iter_route_contexts(app.routes):  # app.routes alone holds included routers, not their routes
        if route.path is None or route.path.startswith("/static"):
            continue
        for method in sorted(route.methods or {"WEBSOCKET"}):
            if method != "HEAD":
                routes.append((method, route.path, bool(getattr(route, "include_in_schema", False))))
    return routes


def add_simulated_participants(client: TestClient, slug: str, *, n: int, model: Any, seed: int = 0,
                               prefix: str | None = None, ratings: Any = None) -> list[str]:
    """``n`` completed participants whose scored trials are simulated in process from IOHMM ``model`` (with a
    ``RatingEmission``, their shelf questionnaires' trust ratings too).

    Much faster than bots (no HTTP, no pacing) and deterministic: the public ids are ``{prefix}0000``, ...
    (default prefix ``Psim{study id}-``), and the rows are the engine's records, as the server stores them.
    Returns the public ids.
    """
    import math

    from experiment.flow import DEBRIEF
    from experiment.schedule import derive_rng
    from experiment.simulate import order_names, simulate_participant
    from server.models import Answer, Participant, Trial, utcnow
    from server.services.sessions import hash_token
    from server.services.studies import current_version, freeze, get_study

    app = client.app
    ids = []
    with app.state.services.sessionmaker.begin() as session:
        version = current_version(session, get_study(session, slug))
        freeze(version)
        runtime = app.state.services.runtimes.get(version)
        orders, now = order_names(runtime.config), utcnow()
        prefix = prefix or f"Psim{version.study_id}-"
        for i in range(n):
            pid = f"{prefix}{i:04d}"
            sim = simulate_participant(runtime, model, pid, orders[i % len(orders)], derive_rng(seed, pid, "human"),
                                       ratings, derive_rng(seed, pid, "ratings"))
            participant = Participant(public_id=pid, token_hash=hash_token(f"token-{pid}"), study_id=version.study_id,
                                      study_version_id=version.id, status="completed", step=DEBRIEF,
                                      block_order=list(sim.block_order), score=sim.records[-1].score,
                                      beliefs={"": sim.records[-1].belief_after}, started_at=now, finished_at=now)
            session.add(participant)
            session.flush()
            session.add_all(Trial(
                participant_id=participant.id, study_version_id=version.id, practice=False, block=r.block,
                block_name=r.block_name, policy=r.policy, trial=r.trial, trial_overall=r.trial_overall, shelf=r.shelf,
                complexity=r.complexity.value, robot_action=r.robot_action.value, stage="done",
                human_action=r.human_action.value, outcome=r.outcome.value, experience=r.experience.value,
                reward=r.reward, score=r.score, belief_before=r.belief_before, belief_after=r.belief_after,
                policy_belief=None if math.isnan(r.policy_belief) else r.policy_belief, model_hash=r.model_hash,
                policy_hash=r.policy_hash, seed=r.seed, started_at=now, completed_at=now) for r in sim.records)
            session.add_all(Answer(
                participant_id=participant.id, study_version_id=version.id, context=f"shelf:{a.block}:{a.shelf}",
                block=a.block, block_name=a.block_name, shelf=a.shelf, questionnaire=a.questionnaire, item="trust",
                value=a.value, scored_value=a.value) for a in sim.ratings)
            ids.append(pid)
    return ids


def tiny_study(title: str, *, hint: str, n_high: int, animation_speed: float) -> StudyConfig:
    """One low-complexity practice trial (the robot tries by itself; ``hint``: "rely" or "intervene", which a bot
    follows) and one always-auto block of one low and ``n_high`` high trials, with a short decision window."""
    return StudyConfig(
        title=title, counterbalance="none", shelf_size=2,
        practice=PracticeConfig(trials=[PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.AUTO,
                                                      human_action_hint=hint)]),
        blocks=[BlockConfig(name="auto", policy=AlwaysAutoSpec(), schedule=CountsSchedule(n_low=1, n_high=n_high))],
        timing=TimingConfig(decision_window_s=0.2, animation_speed=animation_speed),
    )


@contextmanager
def memory_session() -> Iterator[Session]:
    """A session on a new in-memory SQLite database with the models' tables, for testing services without HTTP
    (one connection, so every use sees the same database); rolled back at the end."""
    from sqlalchemy.pool import StaticPool

    from server.db.engine import Base, make_engine, make_sessionmaker

    engine = make_engine("sqlite://", poolclass=StaticPool)
    try:
        Base.metadata.create_all(engine)
        with make_sessionmaker(engine)() as session:
            yield session
    finally:
        engine.dispose()


def open_study(session: Session, *, config: StudyConfig | None = None, slug: str = "s1") -> Study:
    """An open study made by the services (``fast_config()`` unless given)."""
    from server.services.studies import create_study

    return create_study(session, config or fast_config(), slug, status="open")


def at_practice(session: Session, study: Study, runtimes: RuntimeCache, **params: str
                ) -> tuple[Participant, StudyRuntime]:
    """A participant of ``study`` who joined, consented and read the instructions (the services, no HTTP), and
    their study runtime: (participant, runtime)."""
    from server.models import utcnow
    from server.services import sessions

    participant, _, _ = sessions.join(session, study, params, runtimes)
    runtime, now = sessions.runtime_of(session, runtimes, participant), utcnow()
    sessions.consent(session, participant, runtime, agree=True, now=now)
    sessions.finish_instructions(session, participant, runtime, now)
    return participant, runtime
