"""Studies and their versioned configurations."""

from __future__ import annotations

import hashlib
import json
import re
import secrets
from collections import OrderedDict
from datetime import datetime
from threading import Lock

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from experiment.config import RecruitmentConfig, StudyConfig
from experiment.engine import StudyRuntime
from experiment.events import EventKind
from experiment.iohmm import ModelError
from experiment.lifecycle import INITIAL_STATUSES, StudyStatus, TransitionError, transition
from experiment.templates import TEMPLATES, template
from server.errors import Conflict, Invalid, NotFound
from server.models import AuditAction, Event, Participant, Study, StudyVersion, utcnow
from server.schemas import SLUG_REGEX
from server.services.audit import audit
from server.services.completion_codes import with_private_codes

SLUG_PATTERN = re.compile(SLUG_REGEX)
#: Who saved a version when the request named nobody.
DEFAULT_AUTHOR = "admin"


def config_hash(config: StudyConfig) -> str:
    # Not experiment.provenance.content_hash: that keeps non-ASCII characters, this escapes them, and every stored
    # version (and the export's manifest) carries this hash, so changing it would make equal configs look different.
    canonical = json.dumps(config.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def template_config(name: str) -> StudyConfig:
    try:
        return template(name)
    except KeyError:
        raise NotFound(f"unknown template {name!r}; templates: {', '.join(TEMPLATES)}") from None


def create_study(session: Session, config: StudyConfig, slug: str | None = None, author: str | None = None, *,
                 status: str = StudyStatus.DRAFT) -> Study:
    """A new study, a draft unless ``status`` is "open" (create and open in one step)."""
    if status not in INITIAL_STATUSES:
        raise Invalid(f"a study is created as 'draft' or 'open', not {status!r}")
    slug = slug or _slug_from(config.title)
    if not SLUG_PATTERN.fullmatch(slug):  # not match: "$" would let a trailing newline through
        raise Invalid(f"study slug {slug!r} must be 2-63 characters: lower-case letters, digits and '-'")
    if session.scalar(select(Study.id).where(Study.slug == slug)) is not None:
        raise Conflict(f"a study with slug {slug!r} already exists")
    config = with_private_codes(config)  # never the public default codes (server.services.completion_codes)
    study = Study(slug=slug, title=config.title, status=StudyStatus(status))
    session.add(study)
    session.flush()
    _add_version(session, study, config, 1, author)
    audit(session, AuditAction.STUDY_CREATE, study_id=study.id, slug=slug, status=str(status))
    return study


def _slug_from(title: str) -> str:
    base = re.sub(r"[^a-z0-9]+", "-", title.lower()).strip("-")[:40] or "study"
    return f"{base}-{secrets.token_hex(3)}"


def _add_version(session: Session, study: Study, config: StudyConfig, version: int,
                 author: str | None = None) -> StudyVersion:
    row = StudyVersion(study_id=study.id, version=version, config=config.model_dump(mode="json"),
                       config_hash=config_hash(config), author=author or DEFAULT_AUTHOR)
    session.add(row)
    session.flush()
    return row


def get_study(session: Session, slug: str) -> Study:
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None:
        raise NotFound(f"no study {slug!r}")
    return study


def current_version(session: Session, study: Study) -> StudyVersion:
    return session.scalars(select(StudyVersion).where(StudyVersion.study_id == study.id)
                           .order_by(StudyVersion.version.desc()).limit(1)).one()


def update_config(session: Session, study: Study, config: StudyConfig, author: str | None = None) -> StudyVersion:
    """A new version with ``config``, so that every saved configuration stays readable (and records keep theirs);
    the same configuration again changes nothing and returns the current version (a retried save is a no-op)."""
    version = current_version(session, study)
    config = with_private_codes(config, version.config)  # the study's own codes, kept from version to version
    if version.config_hash == config_hash(config):
        return version
    version = _add_version(session, study, config, version.version + 1, author)
    study.title = config.title
    audit(session, AuditAction.STUDY_UPDATE_CONFIG, study_id=study.id, version=version.version)
    return version


def set_status(session: Session, study: Study, status: str) -> Study:
    """Move the study along its lifecycle (``experiment.lifecycle``); its current status again is a no-op (a
    retried request changes nothing and adds no audit line); a change the lifecycle forbids is a 409."""
    try:
        changed = transition(study.status, status)
    except TransitionError as exc:
        raise Conflict(f"study {study.slug!r} is {study.status}: {exc}", status=study.status) from None
    if changed:
        study.status = StudyStatus(status)
        audit(session, AuditAction(f"study.{status}"), study_id=study.id)
    return study


def freeze(version: StudyVersion, now: datetime | None = None) -> None:
    if version.frozen_at is None:
        version.frozen_at = now or utcnow()


def participant_counts(session: Session, study: Study) -> dict[str, int]:
    """Participants per status, preview sessions left out."""
    rows = session.execute(select(Participant.status, func.count()).where(
        Participant.study_id == study.id, Participant.preview.is_(False)).group_by(Participant.status))
    return {status: count for status, count in rows}


def preview_count(session: Session, study: Study) -> int:
    return session.scalar(select(func.count()).select_from(Participant).where(
        Participant.study_id == study.id, Participant.preview.is_(True))) or 0


def admission(session: Session, study: Study, version: StudyVersion) -> tuple[int | None, int]:
    """The current version's cap on active participants (None: no cap) and how many joins the cap has refused."""
    cap = RecruitmentConfig.model_validate(version.config.get("recruitment", {})).max_active_participants
    # Refusals are study-level events (no participant), a handful among the study's events: "+ 0" keeps SQLite's
    # planner off ix_event_study_id (every event of the study: 0.3 s at 800,000) and on ix_event_participant_id.
    refused = session.scalar(select(func.count()).select_from(Event).where(
        Event.participant_id.is_(None), Event.study_id + 0 == study.id, Event.kind == EventKind.JOIN_REFUSED)) or 0
    return cap, refused


class RuntimeCache:
    """Compiled study versions (policies solved once), keyed by config hash."""

    def __init__(self, capacity: int = 64):
        self._items: OrderedDict[str, StudyRuntime] = OrderedDict()
        self._capacity, self._lock = capacity, Lock()

    def for_version(self, session: Session, version_id: int, config_hash: str | None = None) -> StudyRuntime:
        """The runtime of a version by id: reads only its config hash (unless given) when that is cached (a
        version's config, a large JSON document, need not be loaded and parsed on every request)."""
        if config_hash is None:
            config_hash = session.scalar(select(StudyVersion.config_hash).where(StudyVersion.id == version_id))
        with self._lock:
            if config_hash is not None and (runtime := self._items.get(config_hash)) is not None:
                self._items.move_to_end(config_hash)
                return runtime
        version = session.get(StudyVersion, version_id)
        if version is None:
            raise NotFound(f"study version {version_id} does not exist")
        return self.get(version)

    def get(self, version: StudyVersion) -> StudyRuntime:
        with self._lock:
            runtime = self._items.get(version.config_hash)
            if runtime is not None:
                self._items.move_to_end(version.config_hash)
                return runtime
        try:
            runtime = StudyRuntime(StudyConfig.model_validate(version.config))
        except (ModelError, ValueError) as exc:  # e.g. a model missing an estimate the policy needs
            raise Invalid(f"study version {version.version} cannot run: {exc}") from None
        with self._lock:
            self._items[version.config_hash] = runtime
            if len(self._items) > self._capacity:
                self._items.popitem(last=False)
        return runtime
