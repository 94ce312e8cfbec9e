"""Domain errors raised by services, and the one mapping to HTTP status codes.

Every error a client can cause becomes a 4xx with ``{"detail": reason,
"code": kind}`` (a full study, which no client causes, a 503 in the same
shape); services raise these and never import HTTP types.
"""

from __future__ import annotations

from typing import Any

from server.i18n import N_


class AppError(Exception):
    """``detail``: the reason in English, for API clients and logs. ``message``: the catalogue key of the sentence the
    participant pages show instead (``server.i18n``; the kind's own unless a raise names a more precise one), with
    ``message_params`` for its placeholders; the answer carries both, and the page translates the key."""

    status_code = 400
    code = "bad_request"
    message = N_("errors.bad_request")

    def __init__(self, detail: str, *, message: str | None = None, message_params: dict[str, Any] | None = None,
                 **extra: Any):
        super().__init__(detail)
        self.detail = detail
        self.extra = extra
        if message is not None:
            self.message = message
        self.message_params = message_params or {}


class NotFound(AppError):
    status_code = 404
    code = "not_found"
    message = N_("errors.not_found")


class Unauthorized(AppError):
    status_code = 401
    code = "unauthorized"
    message = N_("errors.unauthorized")


class Conflict(AppError):
    """A request that does not fit the current state (out of order, repeated, wrong phase)."""

    status_code = 409
    code = "conflict"
    message = N_("errors.conflict")


class Gone(AppError):
    """The study is closed or the session is over (abandoned, withdrawn)."""

    status_code = 410
    code = "gone"
    message = N_("errors.gone")


class NotOpen(Conflict):
    """A join of a study that is still a draft: 409 (the study's state, not the participant, is the problem; it may
    open later), told apart from a closed study's 410 by its code."""

    code = "study_not_open"
    message = N_("errors.study_not_open")


class Invalid(AppError):
    status_code = 422
    code = "invalid"
    message = N_("errors.invalid")


class TooLarge(AppError):
    status_code = 413
    code = "too_large"
    message = N_("errors.too_large")


class RateLimited(AppError):
    status_code = 429
    code = "rate_limited"
    message = N_("errors.rate_limited")


class AddressBusy(RateLimited):
    """A new join under a study's cap from an address that already holds ``max_unconsented_per_address`` sessions
    that have not consented yet (429 with Retry-After: that address sent too many joins; its places free as its
    sessions consent or go quiet)."""

    code = "address_busy"
    message = N_("errors.address_busy")


class StudyFull(AppError):
    """A new join past the study's cap on active participants (``recruitment.max_active_participants``).

    503 Service Unavailable with Retry-After, not 429: the joining person sent nothing too often, the study is
    at capacity for a while, and a place frees when someone finishes. Recruitment sites and HTTP clients treat a
    503 with Retry-After as "come back later", never as a broken link or a rejection of the participant.
    """

    status_code = 503
    code = "study_full"
    message = N_("errors.study_full")
