"""Joining a study: who gets a new session and who resumes which, and admission under a study's cap.

An external recruitment id (PROLIFIC_PID, pid, ...) identifies a participant; it is not a key to a session. A join
with a known id resumes only with proof of being that session's person (``_proves``); anyone else gets a session of
their own marked ``duplicate_of`` the first, so an id claimed first can neither capture nor lock out its owner.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import math
import secrets
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import func, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from experiment.events import EventKind
from experiment.flow import ParticipantStatus, first_step
from experiment.languages import resolve_language
from experiment.lifecycle import StudyStatus
from server.errors import AddressBusy, Gone, Invalid, NotOpen, StudyFull
from server.i18n import N_
from server.models import AppSecret, AuditAction, Participant, Study, utcnow
from server.services.audit import audit, log_event
from server.services.studies import RuntimeCache, current_version, freeze

TOKEN_BYTES = 24  # 192 bits
#: Recruitment parameters kept with the participant; the first present one is the external id.
RECRUITMENT_PARAMS = ("PROLIFIC_PID", "STUDY_ID", "SESSION_ID", "participant", "pid", "workerId", "assignmentId")
EXTERNAL_ID_PARAMS = ("PROLIFIC_PID", "participant", "pid", "workerId")
MAX_PARAM_LENGTH = 200
#: The join link's parameter that chooses the session's language among the study's (/join/SLUG?lang=de).
LANGUAGE_PARAM = "lang"
#: What a join past the study's cap (``recruitment.max_active_participants``) is told, and when to come back: a
#: place frees when a session ends, and sessions last minutes.
STUDY_FULL_REASON = "This study is full right now. Please try again in a few minutes."
STUDY_FULL_RETRY_AFTER_S = 120


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def app_secret(session: Session, name: str) -> bytes:
    """The server secret ``name`` (32 random bytes, made on first use and kept in the database)."""
    row = session.get(AppSecret, name)
    if row is None:
        try:
            with session.begin_nested():  # the first joins may come at once: one creates it, the others read it
                session.add(AppSecret(name=name, value=secrets.token_hex(32)))
        except IntegrityError:
            pass
        row = session.get(AppSecret, name)
        assert row is not None
    return bytes.fromhex(row.value)


def _session_token(session: Session, study: Study, name: str) -> str:
    """A session's token, derived from its public id (``name``) with this installation's secret: a join that proves
    to be the session's person (``_proves``) gets it again, though only its hash is stored. Sessions joined before
    revision 0008 have theirs derived from their external id."""
    digest = hmac.new(app_secret(session, "session_token_key"), f"{study.id}:{name}".encode(), "sha256").digest()
    return base64.urlsafe_b64encode(digest[:TOKEN_BYTES]).decode().rstrip("=")


def _token_of(session: Session, study: Study, participant: Participant) -> str:
    token = _session_token(session, study, participant.public_id)
    if hash_token(token) != participant.token_hash and participant.external_id is not None:
        token = _session_token(session, study, participant.external_id)  # joined before revision 0008
    return token


def recruitment_params(params: dict[str, str]) -> tuple[dict[str, str], str | None]:
    kept = {k: v for k, v in params.items() if k in RECRUITMENT_PARAMS and v}
    for key, value in kept.items():
        if len(value) > MAX_PARAM_LENGTH or not value.isprintable():
            raise Invalid(f"recruitment parameter {key} must be printable text of at most {MAX_PARAM_LENGTH} "
                          "characters", message=N_("errors.bad_link"))
    external_id = next((kept[k] for k in EXTERNAL_ID_PARAMS if k in kept), None)
    return kept, external_id


@dataclass(frozen=True)
class JoinRequest:
    """What a join brings besides its recruitment parameters: the browser's resume key (None: the server mints one),
    the client's address, when, and the browser's preferred languages."""

    resume_key: str | None = None
    address: str | None = None
    now: datetime | None = None
    #: The browser's Accept-Language header: picks the session's language among the study's, after the link's
    #: ``lang`` parameter (``experiment.languages.resolve_language``).
    accept_language: str | None = None


@dataclass(frozen=True)
class Admission:
    """Settings of admission under a study's cap (``Settings.unconsented_place_hold_s``,
    ``max_unconsented_per_address``)."""

    unconsented_hold_s: float = 120.0
    max_unconsented_per_address: int = 20


def join(session: Session, study: Study, params: dict[str, str], runtimes: RuntimeCache,
         request: JoinRequest = JoinRequest(), admission: Admission = Admission()
         ) -> tuple[Participant, str, bool]:
    """Start a session, or resume the one this person started. Returns (participant, token, created).

    A known external id resumes its session only with proof (``_proves``): the resume key of the browser that
    joined, or the same recruitment session (Prolific SESSION_ID, MTurk assignmentId). Without it, the joiner gets a
    session of their own marked ``duplicate_of`` the first one (whatever that one's status): never its token, and
    never a refusal, so someone who claimed an id first cannot lock its owner out.

    Raises ``StudyFull`` (503) past the study's cap and ``AddressBusy`` (429) past the per-address cap on unconsented
    sessions, after logging a ``join_refused`` event (the caller commits it); a returning participant is never refused.
    """
    recruitment, external_id = recruitment_params(params)
    key = request.resume_key or new_resume_key()  # the caller that wants to keep it passes it
    if external_id is not None and (mine := _resumable(session, study, external_id, key, recruitment)) is not None:
        return mine, _token_of(session, study, mine), False
    if study.status == StudyStatus.DRAFT:
        raise NotOpen("this study has not opened yet; please try again later or check the link you were given")
    if study.status != StudyStatus.OPEN:
        raise Gone("this study is closed and is not taking new participants", message=N_("errors.study_closed"))
    version = current_version(session, study)
    runtime = runtimes.get(version)
    now = request.now or utcnow()
    cap = runtime.config.recruitment.max_active_participants
    # kept only where it is used: under a cap, until consent
    address_hash = _address_hash(session, request.address) if request.address and cap is not None else None
    if external_id is not None or cap is not None:
        lock_study(session, study)  # joins one at a time per study: two cannot both take the last place or an id
    if external_id is not None and (mine := _resumable(session, study, external_id, key, recruitment)) is not None:
        return mine, _token_of(session, study, mine), False  # the same person's other join got in meanwhile
    if cap is not None:
        _require_place(session, study, cap, now, admission, address_hash)
    freeze(version)
    first = _first_with_id(session, study, external_id) if external_id is not None else None
    public_id = "P" + secrets.token_hex(6)
    token = _session_token(session, study, public_id)
    language = resolve_language(runtime.config.languages, requested=params.get(LANGUAGE_PARAM),
                                accept_language=request.accept_language)
    participant = Participant(public_id=public_id, token_hash=hash_token(token), study_id=study.id,
                              study_version_id=version.id, external_id=external_id, recruitment=recruitment,
                              language=language,
                              step=first_step(), beliefs=runtime.initial_beliefs(), resume_key_hash=hash_token(key),
                              duplicate_of=first.public_id if first is not None else None,
                              join_address_hash=address_hash, created_at=now, last_seen_at=now)
    session.add(participant)
    session.flush()
    log_event(session, study.id, participant.id, EventKind.JOINED, external_id=external_id is not None,
              duplicate=first is not None)
    return participant, token, True


def new_resume_key() -> str:
    return secrets.token_urlsafe(RESUME_KEY_BYTES)


#: Recruitment parameters that name one sitting of one person, with the id parameter they belong to: the same value
#: again is the same person coming back (from another browser too). MTurk's preview value names nobody.
RECRUITMENT_SESSION_PARAMS = {"SESSION_ID": "PROLIFIC_PID", "assignmentId": "workerId"}
NO_ASSIGNMENT = "ASSIGNMENT_ID_NOT_AVAILABLE"
RESUME_KEY_BYTES = 16  # 128 bits


def _proves(participant: Participant, key: str, recruitment: dict[str, str]) -> bool:
    """Whether a join is by ``participant``'s person: their browser's resume key, or their recruitment session."""
    if participant.resume_key_hash and hmac.compare_digest(participant.resume_key_hash, hash_token(key)):
        return True
    stored = participant.recruitment or {}
    return any(recruitment.get(sitting) not in (None, NO_ASSIGNMENT) and recruitment.get(sitting) == stored.get(sitting)
               and recruitment.get(owner) == stored.get(owner)
               for sitting, owner in RECRUITMENT_SESSION_PARAMS.items())


def _resumable(session: Session, study: Study, external_id: str, key: str,
               recruitment: dict[str, str]) -> Participant | None:
    """The latest session of ``external_id`` this join proves to be its person's (any status: an ended session
    shows its end again)."""
    rows = session.scalars(select(Participant).where(Participant.study_id == study.id,
                                                     Participant.external_id == external_id)
                           .order_by(Participant.id.desc())).all()
    return next((p for p in rows if _proves(p, key, recruitment)), None)


def _first_with_id(session: Session, study: Study, external_id: str) -> Participant | None:
    return session.scalar(select(Participant).where(Participant.study_id == study.id,
                                                    Participant.external_id == external_id)
                          .order_by(Participant.id).limit(1))


def _address_hash(session: Session, address: str) -> str:
    """A keyed hash of a client address: counts sessions per address without storing addresses."""
    return hmac.new(app_secret(session, "address_key"), address.encode(), "sha256").hexdigest()


def start_preview(session: Session, study: Study, runtimes: RuntimeCache, language: str | None = None
                  ) -> tuple[Participant, str]:
    """A preview session of ``study`` for the experimenter (draft, open or closed; no cap): (participant, token), in
    ``language`` when the study offers it (else its default).

    Marked ``preview``: left out of the cap, counterbalancing, exports, reports and fits. Each call starts a new
    session (a retried request leaves at most an extra preview, which changes no data and can be deleted).
    """
    version = current_version(session, study)
    runtime = runtimes.get(version)
    token = secrets.token_urlsafe(TOKEN_BYTES)
    freeze(version)  # a preview runs the version it shows: its records point at it, as real participants' do
    participant = Participant(public_id="P" + secrets.token_hex(6), token_hash=hash_token(token), study_id=study.id,
                              study_version_id=version.id, recruitment={}, step=first_step(),
                              language=resolve_language(runtime.config.languages, requested=language),
                              beliefs=runtime.initial_beliefs(), preview=True)
    session.add(participant)
    session.flush()
    log_event(session, study.id, participant.id, EventKind.JOINED, external_id=False, preview=True)
    audit(session, AuditAction.PARTICIPANT_PREVIEW, study_id=study.id, participant=participant.public_id)
    return participant, token


def lock_study(session: Session, study: Study) -> None:
    """Serialise this transaction with the others that lock ``study`` (PostgreSQL row lock; on SQLite every
    transaction already holds the write lock, ``server.db.engine``)."""
    session.execute(select(Study.id).where(Study.id == study.id).with_for_update())


def _holding(study: Study, now: datetime, admission: Admission):
    """Sessions of ``study`` that hold a place: active and consented, or active, unconsented and seen within
    ``unconsented_hold_s`` (a bare join does not hold one for the idle timeout); previews hold none."""
    fresh = now - timedelta(seconds=admission.unconsented_hold_s)
    return (Participant.study_id == study.id, Participant.status == ParticipantStatus.ACTIVE,
            Participant.preview.is_(False),
            or_(Participant.consented_at.is_not(None), Participant.last_seen_at >= fresh))


def active_count(session: Session, study: Study, now: datetime | None = None,
                 admission: Admission = Admission()) -> int:
    """Sessions of ``study`` that hold a place under its cap (ix_participant_study_status)."""
    return session.scalar(select(func.count()).select_from(Participant)
                          .where(*_holding(study, now or utcnow(), admission))) or 0


def _require_place(session: Session, study: Study, cap: int, now: datetime, admission: Admission,
                   address_hash: str | None) -> None:
    active = active_count(session, study, now, admission)
    if active >= cap:
        log_event(session, study.id, None, EventKind.JOIN_REFUSED, reason=StudyFull.code, active=active, cap=cap)
        raise StudyFull(STUDY_FULL_REASON, retry_after_s=STUDY_FULL_RETRY_AFTER_S)
    if address_hash is None:
        return
    mine = (*_holding(study, now, admission), Participant.consented_at.is_(None),
            Participant.join_address_hash == address_hash)
    held, oldest = session.execute(select(func.count(), func.min(Participant.last_seen_at)).where(*mine)).one()
    if held >= admission.max_unconsented_per_address:
        wait = max(1, math.ceil(admission.unconsented_hold_s - (now - oldest).total_seconds()))
        log_event(session, study.id, None, EventKind.JOIN_REFUSED, reason=AddressBusy.code, unconsented=held,
                  limit=admission.max_unconsented_per_address)
        raise AddressBusy(f"{held} sessions joined from your network have not given consent yet (at most "
                          f"{admission.max_unconsented_per_address}); please try again in {wait} s",
                          retry_after_s=wait, message_params={"seconds": wait})
