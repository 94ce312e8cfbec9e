"""Database tables (SQLAlchemy 2). No business logic here: see ``server.services``.

Table names are singular snake_case; datetimes end in ``_at`` (UTC); foreign
keys end in ``_id``. Every participant-facing record points at the study
version it ran under.
"""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any, TypeVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    false,
)
from sqlalchemy.orm import Mapped, mapped_column

from experiment.events import KIND_LENGTH
from experiment.flow import ParticipantStatus, SceneView, Step, TrialRef, TrialStage, WindowOpener, parse_step
from experiment.lifecycle import StudyStatus
from experiment.policies import PolicyKind
from experiment.task import Complexity, Experience, HumanAction, Outcome, RobotAction
from experiment.trust_belief import Belief
from experiment.world.attempt import FailureMode
from server.db.engine import Base


def utcnow() -> datetime:
    return datetime.now(UTC)


class TZDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            raise ValueError("naive datetime; trustlab stores aware UTC datetimes")
        return value.astimezone(UTC) if value is not None else None

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class StepJSON(TypeDecorator[Step]):
    """A participant's step (``experiment.flow``), stored as its JSON dict."""

    impl = JSON
    cache_ok = True

    def process_bind_param(self, value: Step | None, dialect: Any) -> dict[str, Any] | None:
        return None if value is None else value.model_dump()

    def process_result_value(self, value: dict[str, Any] | None, dialect: Any) -> Step | None:
        return None if value is None else parse_step(value)


E = TypeVar("E", bound=StrEnum)


class StoredEnum(TypeDecorator[E]):
    """A string enum stored as its value (a VARCHAR, no database enum type), read back as the enum."""

    impl = String
    cache_ok = True

    def __init__(self, enum: type[E], length: int):
        super().__init__(length)
        self.enum = enum
        self._members = {member.value: member for member in enum}  # a dict lookup: exports read many rows

    def process_bind_param(self, value: E | str | None, dialect: Any) -> str | None:
        return None if value is None else str(value)

    def process_result_value(self, value: str | None, dialect: Any) -> E | None:
        return None if value is None else self._members[value]


class FitStatus(StrEnum):
    """Where a model fit is (``FittedModel.status``)."""

    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class AuditAction(StrEnum):
    """What an experimenter did (``AdminAudit.action``)."""

    ADMIN_ROTATE_TOKEN = "admin.rotate_token"
    STUDY_CREATE = "study.create"
    STUDY_UPDATE_CONFIG = "study.update_config"
    STUDY_OPEN = "study.open"  # study.<the new status>
    STUDY_CLOSED = "study.closed"
    STUDY_REPORT = "study.report"
    STUDY_EXPORT = "study.export"
    MODEL_FIT = "model.fit"
    MODEL_DEPLOY = "model.deploy"
    PARTICIPANT_PREVIEW = "participant.preview"
    PARTICIPANT_EXCLUDE = "participant.exclude"
    PARTICIPANT_INCLUDE = "participant.include"
    PARTICIPANT_WITHDRAW = "participant.withdraw"
    PARTICIPANT_DELETE_PREVIEW = "participant.delete_preview"
    #: A participant's data deleted (their withdrawal, or the experimenter on request): the line names no one
    #: (``server.services.erasure``).
    PARTICIPANT_DELETE = "participant.delete"
    #: Personal fields of ended sessions erased by the study's retention rule (a count, no one named).
    PERSONAL_DATA_ERASE = "participant.erase_personal"
    DATA_REPAIR = "data.repair"


def _now_column() -> Mapped[datetime]:
    return mapped_column(TZDateTime(), default=utcnow)


class Study(Base):
    __tablename__ = "study"

    id: Mapped[int] = mapped_column(primary_key=True)
    slug: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    status: Mapped[StudyStatus] = mapped_column(StoredEnum(StudyStatus, 16), default=StudyStatus.DRAFT)
    created_at: Mapped[datetime] = _now_column()


class StudyVersion(Base):
    """A study's configuration; frozen once a participant has joined under it."""

    __tablename__ = "study_version"
    __table_args__ = (UniqueConstraint("study_id", "version"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id", ondelete="CASCADE"), index=True)
    version: Mapped[int] = mapped_column(Integer)
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    config_hash: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = _now_column()
    frozen_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    author: Mapped[str | None] = mapped_column(String(120), nullable=True)  # who saved it


class Participant(Base):
    __tablename__ = "participant"
    # Not unique: an external id identifies, it is no key; a second person with a known id gets a session of their own
    # (``duplicate_of``), so the id may appear more than once.
    __table_args__ = (Index("ix_participant_study_external_id", "study_id", "external_id"),
                      Index("ix_participant_study_status", "study_id", "status"))

    id: Mapped[int] = mapped_column(primary_key=True)
    public_id: Mapped[str] = mapped_column(String(32), unique=True)  # shown in exports, not a credential
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)  # sha256 of the session token
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id", ondelete="CASCADE"))
    study_version_id: Mapped[int] = mapped_column(ForeignKey("study_version.id"))
    external_id: Mapped[str | None] = mapped_column(String(200), nullable=True)
    recruitment: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    status: Mapped[ParticipantStatus] = mapped_column(StoredEnum(ParticipantStatus, 16),
                                                      default=ParticipantStatus.ACTIVE)
    step: Mapped[Step] = mapped_column(StepJSON)  # where the participant is (experiment.flow)
    block_order: Mapped[list[str] | None] = mapped_column(JSON, nullable=True)
    assignment: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)  # counterbalancing audit
    score: Mapped[float] = mapped_column(Float, default=0.0)
    #: Kept beliefs by model (experiment.engine.StudyRuntime.initial_beliefs): P(trust high), or a K-state vector.
    beliefs: Mapped[dict[str, Belief]] = mapped_column(JSON, default=dict)
    completion_code: Mapped[str | None] = mapped_column(String(64), nullable=True)
    compensation: Mapped[float | None] = mapped_column(Float, nullable=True)
    #: Answers given so far on the questionnaire page on screen ({questionnaire, context, answers}): restored after a
    #: reload, dropped when the page is submitted. Not answers: exports never read it.
    survey_draft: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    excluded: Mapped[bool] = mapped_column(Boolean, default=False)
    #: Opened by the experimenter to try the study: left out of counterbalancing, exports, reports and fits by default.
    preview: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    exclusion_reason: Mapped[str | None] = mapped_column(Text, nullable=True)
    #: The language the participant sees (a BCP 47 tag of the study's ``languages``), chosen once at the join
    #: (``experiment.languages.resolve_language``) and used for every page and message of the session.
    language: Mapped[str] = mapped_column(String(16), default="en", server_default="en")
    created_at: Mapped[datetime] = _now_column()
    consented_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    started_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)  # first scored trial
    finished_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    last_seen_at: Mapped[datetime] = _now_column()
    #: sha256 of the resume key of the browser that joined (the page keeps it): a join with the same external id
    #: resumes this session only with it (or with the same recruitment session, e.g. Prolific's SESSION_ID).
    resume_key_hash: Mapped[str | None] = mapped_column(String(64), nullable=True)
    #: public_id of the study's first session with the same external id, when this one was joined without proof of
    #: being that session's person (a data-quality flag, ``duplicate_id``).
    duplicate_of: Mapped[str | None] = mapped_column(String(32), nullable=True)
    #: Keyed hash of the joining client's address, kept until consent (the per-address cap on unconsented sessions);
    #: never exported.
    join_address_hash: Mapped[str | None] = mapped_column(String(64), nullable=True)
    #: When the personal fields (``experiment.privacy.PERSONAL_FIELDS``) were erased: by the study's retention rule or
    #: a withdrawal that keeps the data. Null while they are kept.
    personal_data_erased_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)


class Trial(Base):
    """One trial, practice or scored; created when it starts, completed when resolved."""

    __tablename__ = "trial"
    __table_args__ = (UniqueConstraint("participant_id", "practice", "block", "trial"),
                      Index("ix_trial_stage", "stage"))

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id", ondelete="CASCADE"), index=True)
    study_version_id: Mapped[int] = mapped_column(ForeignKey("study_version.id"))
    practice: Mapped[bool] = mapped_column(Boolean, default=False)
    block: Mapped[int] = mapped_column(Integer)  # position in the participant's order (0 for practice)
    block_name: Mapped[str] = mapped_column(String(64))
    policy: Mapped[PolicyKind] = mapped_column(StoredEnum(PolicyKind, 32))
    trial: Mapped[int] = mapped_column(Integer)  # within block, from 1
    trial_overall: Mapped[int] = mapped_column(Integer)
    shelf: Mapped[int] = mapped_column(Integer)
    complexity: Mapped[Complexity] = mapped_column(StoredEnum(Complexity, 8))
    robot_action: Mapped[RobotAction] = mapped_column(StoredEnum(RobotAction, 8))
    stage: Mapped[TrialStage] = mapped_column(StoredEnum(TrialStage, 16))
    human_action: Mapped[HumanAction | None] = mapped_column(StoredEnum(HumanAction, 16), nullable=True)
    outcome: Mapped[Outcome | None] = mapped_column(StoredEnum(Outcome, 8), nullable=True)
    experience: Mapped[Experience | None] = mapped_column(StoredEnum(Experience, 8), nullable=True)
    reward: Mapped[float | None] = mapped_column(Float, nullable=True)
    score: Mapped[float | None] = mapped_column(Float, nullable=True)
    belief_before: Mapped[float] = mapped_column(Float)
    belief_after: Mapped[float | None] = mapped_column(Float, nullable=True)
    policy_belief: Mapped[float | None] = mapped_column(Float, nullable=True)
    decision_deadline_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    # The decision window opens once the page shows the trial's scene, or at scene_deadline_at without a report.
    scene_deadline_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    scene_shown_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)  # first report
    scene_shown_view: Mapped[SceneView | None] = mapped_column(StoredEnum(SceneView, 8), nullable=True)
    scene_shown_client_ms: Mapped[float | None] = mapped_column(Float, nullable=True)  # the page's performance.now()
    window_opened_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    window_opened_by: Mapped[WindowOpener | None] = mapped_column(StoredEnum(WindowOpener, 16), nullable=True)
    attempt_end_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    teleop_deadline_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    decision_time_ms: Mapped[float | None] = mapped_column(Float, nullable=True)
    teleop_time_ms: Mapped[float | None] = mapped_column(Float, nullable=True)
    # The time limit stood still this long while the page had no usable view (server.services.teleop).
    teleop_view_wait_ms: Mapped[float | None] = mapped_column(Float, nullable=True)
    teleop_success: Mapped[bool | None] = mapped_column(Boolean, nullable=True)
    # Teleoperation rules and the guided practice (set when the trial enters teleoperation).
    tutorial: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    teleop_tries: Mapped[int | None] = mapped_column(Integer, nullable=True)
    grasp_radius_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    align_radius_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    failure_mode: Mapped[FailureMode | None] = mapped_column(StoredEnum(FailureMode, 16), nullable=True)
    started_at: Mapped[datetime] = _now_column()
    decided_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    completed_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
    # Provenance (``experiment.provenance``), set when the trial starts; empty for trials of older versions.
    model_hash: Mapped[str | None] = mapped_column(String(64), nullable=True)
    policy_hash: Mapped[str | None] = mapped_column(String(64), nullable=True)
    seed: Mapped[int | None] = mapped_column(BigInteger, nullable=True)  # the study seed

    @property
    def ref(self) -> TrialRef:
        """Which of its participant's trials this is (the row's key, with ``participant_id``)."""
        return TrialRef(self.practice, self.block, self.trial)


class Answer(Base):
    """One questionnaire item answer."""

    __tablename__ = "answer"
    __table_args__ = (UniqueConstraint("participant_id", "context", "questionnaire", "item"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id", ondelete="CASCADE"), index=True)
    study_version_id: Mapped[int] = mapped_column(ForeignKey("study_version.id"))
    context: Mapped[str] = mapped_column(String(64))  # before | shelf:B:S | after:B
    block: Mapped[int | None] = mapped_column(Integer, nullable=True)
    block_name: Mapped[str | None] = mapped_column(String(64), nullable=True)
    shelf: Mapped[int | None] = mapped_column(Integer, nullable=True)
    questionnaire: Mapped[str] = mapped_column(String(64))
    item: Mapped[str] = mapped_column(String(64))
    value: Mapped[float | None] = mapped_column(Float, nullable=True)  # None for a free-text item
    scored_value: Mapped[float | None] = mapped_column(Float, nullable=True)  # reverse-coded where the item says so
    text: Mapped[str | None] = mapped_column(Text, nullable=True)  # a free-text answer, or a chosen option's value
    belief: Mapped[float | None] = mapped_column(Float, nullable=True)  # model belief when answered
    answered_at: Mapped[datetime] = _now_column()


class Event(Base):
    """Append-only fine-grained log (decision windows, presses, teleop, disconnects)."""

    __tablename__ = "event"

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id", ondelete="CASCADE"), index=True)
    participant_id: Mapped[int | None] = mapped_column(ForeignKey("participant.id", ondelete="CASCADE"), index=True,
                                                       nullable=True)
    # an experiment.events.EventKind, or client.<the page's kind>
    kind: Mapped[str] = mapped_column(String(KIND_LENGTH))
    payload: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    client_time_ms: Mapped[float | None] = mapped_column(Float, nullable=True)  # performance.now()
    server_monotonic_s: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = _now_column()


class IdempotentResponse(Base):
    """The stored response of a state-changing request, replayed when its key is seen again."""

    __tablename__ = "idempotent_response"
    __table_args__ = (UniqueConstraint("participant_id", "key"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id", ondelete="CASCADE"))
    key: Mapped[str] = mapped_column(String(128))
    request_hash: Mapped[str] = mapped_column(String(64))
    response: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = _now_column()


class AdminCredential(Base):
    __tablename__ = "admin_credential"

    id: Mapped[int] = mapped_column(primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = _now_column()
    revoked_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)


class AdminAudit(Base):
    __tablename__ = "admin_audit"

    id: Mapped[int] = mapped_column(primary_key=True)
    action: Mapped[AuditAction] = mapped_column(StoredEnum(AuditAction, 48))
    study_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    participant_public_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    detail: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = _now_column()


class AppSecret(Base):
    """Server-side secrets generated on first run (e.g. the key that derives resumable session tokens)."""

    __tablename__ = "app_secret"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    value: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[datetime] = _now_column()


class FittedModel(Base):
    """An IOHMM fitted to a study's data, with its provenance, policy thresholds and trust-agnostic baseline."""

    __tablename__ = "fitted_model"

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id", ondelete="CASCADE"), index=True)
    #: sha256 of (data_hash, restarts, seed, p_high[, states, folds]): a repeated request finds the running or done
    #: fit.
    fit_key: Mapped[str] = mapped_column(String(64), index=True)
    status: Mapped[FitStatus] = mapped_column(StoredEnum(FitStatus, 16), default=FitStatus.RUNNING)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    restarts: Mapped[int] = mapped_column(Integer)
    seed: Mapped[int] = mapped_column(BigInteger)
    p_high: Mapped[float] = mapped_column(Float)
    data_hash: Mapped[str] = mapped_column(String(64))  # of the model columns of the rows fitted on
    study_versions: Mapped[list[int]] = mapped_column(JSON)
    participants: Mapped[list[str]] = mapped_column(JSON)  # public ids, in fitting order
    n_trials: Mapped[int] = mapped_column(Integer)
    code_version: Mapped[str] = mapped_column(String(64))
    progress_done: Mapped[int] = mapped_column(Integer, default=0)  # EM iterations
    progress_total: Mapped[int] = mapped_column(Integer, default=0)
    document: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)  # the model JSON
    content_hash: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)
    loglik: Mapped[float | None] = mapped_column(Float, nullable=True)
    policy: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)  # thresholds for p_high
    agnostic: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)  # baseline from the same data
    evaluation_studies: Mapped[list[str]] = mapped_column(JSON, default=list)  # slugs deployed from it
    created_at: Mapped[datetime] = _now_column()
    finished_at: Mapped[datetime | None] = mapped_column(TZDateTime(), nullable=True)
