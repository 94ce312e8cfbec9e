"""Typed request and response bodies of the HTTP API (they make /openapi.json)."""

from __future__ import annotations

import json
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

MAX_EVENT_PAYLOAD_BYTES = 4096


class _In(BaseModel):
    """Request bodies: unknown fields and non-finite numbers (NaN, Infinity) are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# --- participant -------------------------------------------------------------------------

class JoinRequest(_In):
    """Recruitment parameters (also accepted as query parameters of the join link)."""

    params: dict[str, str] = Field(default_factory=dict, max_length=16)


class ConsentRequest(_In):
    agree: bool


class TrialRef(_In):
    practice: bool = False
    block: int = Field(ge=0, le=100)
    trial: int = Field(ge=1, le=100_000)


class InterveneRequest(TrialRef):
    window_opened_ms: float | None = Field(None, description="performance.now() when the decision window opened")
    pressed_ms: float | None = Field(None, description="performance.now() when Intervene was pressed")


class AnswersRequest(_In):
    questionnaire: str = Field(min_length=1, max_length=64)
    answers: dict[str, float] = Field(max_length=200)


class ClientEvent(_In):
    kind: str = Field(min_length=1, max_length=48, pattern=r"^[a-z0-9_.\-]+$")
    client_time_ms: float | None = None
    payload: dict[str, Any] = Field(default_factory=dict)

    @field_validator("payload")
    @classmethod
    def _plain_json(cls, payload: dict[str, Any]) -> dict[str, Any]:
        try:
            text = json.dumps(payload, allow_nan=False)
        except ValueError:
            raise ValueError("payload must not contain NaN or Infinity") from None
        if len(text) > MAX_EVENT_PAYLOAD_BYTES:
            raise ValueError(f"payload larger than {MAX_EVENT_PAYLOAD_BYTES} bytes")
        return payload


class EventsRequest(_In):
    events: list[ClientEvent] = Field(max_length=100)


class HeartbeatRequest(_In):
    client_time_ms: float | None = None


class ScaleRead(BaseModel):
    min: float
    max: float
    step: float
    anchors: dict[int, str] | None = None
    unit: str | None = None


class ItemRead(BaseModel):
    id: str
    text: str


class QuestionnaireRead(BaseModel):
    id: str
    title: str
    instructions: str
    scale: ScaleRead
    items: list[ItemRead]
    context: str


class TrialView(BaseModel):
    """What the page shows for the current trial; the outcome only once it has happened."""

    practice: bool
    block: int
    block_label: str
    trial: int
    n_trials: int
    shelf: int
    complexity: Literal["low", "high"]
    robot_action: Literal["auto", "ask"]
    message: str
    stage: Literal["decision", "attempt", "teleop", "done"]
    human_action: Literal["rely", "intervene"] | None = None
    decision_window_s: float | None = None
    decision_ms_left: float | None = None
    attempt_ms_left: float | None = None
    teleop_ms_left: float | None = None
    hint: str | None = None


class TrialResultView(BaseModel):
    practice: bool
    block: int
    trial: int
    complexity: str
    robot_action: str
    human_action: str
    outcome: str
    experience: str
    reward: float
    score: float
    teleop_success: bool | None = None
    failure_mode: str | None = None


class CompletionView(BaseModel):
    code: str
    redirect_url: str | None = None
    compensation: float | None = None
    currency: str | None = None


class StateRead(BaseModel):
    """Everything the participant page needs to render the current step."""

    token_valid: bool = True
    status: str
    phase: str
    step: dict[str, Any]
    progress: float
    score: float
    study_title: str
    text: str | None = None
    video_url: str | None = None
    ready_to_start: dict[str, Any] | None = None
    trial: TrialView | None = None
    last_trial: TrialResultView | None = None
    questionnaire: QuestionnaireRead | None = None
    completion: CompletionView | None = None
    timing: dict[str, float]
    server_time: datetime


class JoinResponse(BaseModel):
    token: str
    participant_url: str
    created: bool
    state: StateRead


class OkResponse(BaseModel):
    ok: bool = True


# --- admin -------------------------------------------------------------------------------

class StudyCreate(_In):
    slug: str | None = Field(None, min_length=2, max_length=63)
    template: str | None = None
    config: dict[str, Any] | None = None


class StudyConfigUpdate(_In):
    config: dict[str, Any]


class StudyRead(BaseModel):
    slug: str
    title: str
    status: str
    version: int
    config_hash: str
    join_url: str
    participants: dict[str, int]
    created_at: datetime


class StudyDetail(StudyRead):
    config: dict[str, Any]


class ParticipantRead(BaseModel):
    public_id: str
    external_id: str | None
    status: str
    phase: str
    block: int | None
    block_name: str | None
    trial: int | None
    score: float
    belief: float | None
    block_order: list[str] | None
    excluded: bool
    exclusion_reason: str | None
    completion_code: str | None
    version: int
    created_at: datetime
    last_seen_at: datetime


class ReasonRequest(_In):
    reason: str = Field(min_length=1, max_length=2000)


class TemplateRead(BaseModel):
    name: str
    config: dict[str, Any]
