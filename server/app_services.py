"""``Services``: the parts of a running server, built once by ``server.main.create_app``.

Handlers reach them through ``server.deps.ServicesDep``; services and background loops are given the parts they use,
never the app.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the parts import the services package, which must not import this module back at run time
    from fastapi import FastAPI
    from sqlalchemy.engine import Engine
    from sqlalchemy.orm import Session, sessionmaker

    from server.db.units import Database
    from server.faults import FaultLog
    from server.loadmeter import LoadHistory
    from server.ratelimit import RateLimiter
    from server.services.events import EventBudget
    from server.services.fits import FitWorker
    from server.services.studies import RuntimeCache
    from server.services.teleop_log import TeleopLogWriter
    from server.settings import Settings
    from server.viewer.manager import SessionViews
    from server.world.hub import WorldHub


@dataclass(frozen=True)
class JoinLimits:
    """Joins allowed a minute, from one address and into one study (``join_rate_limit_per_ip`` / ``_per_study``)."""

    by_address: RateLimiter
    by_study: RateLimiter


@dataclass(frozen=True)
class Services:
    settings: Settings
    engine: Engine
    sessionmaker: sessionmaker[Session]  # bare sessions, for tests and tools; the server's own units use ``database``
    database: Database
    runtimes: RuntimeCache  # studies' configs compiled for running (policies solved)
    faults: FaultLog  # contained failures of the background loops (``server.faults``)
    hub: WorldHub  # the live robot worlds
    viewers: SessionViews  # the participants' 3D views: here, or in a view process (``server.launch``)
    teleop_log: TeleopLogWriter
    fits: FitWorker
    load_history: LoadHistory
    join_limits: JoinLimits
    event_budget: EventBudget


def services_of(app: FastAPI) -> Services:
    """The services of a FastAPI app made by ``create_app``."""
    services: Services = app.state.services
    return services
