"""How a session ends for the recruitment platform: each outcome's completion code and redirect.

Outcomes (``SessionOutcome``), from the participant's final status:

- ``completed`` (status completed): reached the debrief;
- ``declined`` (status declined): did not consent;
- ``screened_out`` (status screened_out): an eligibility question, or failed attention checks under the study's
  ``screen_out`` rule (``experiment.attention``);
- ``timed_out`` (status abandoned): idle past the study's ``timing.idle_timeout_s``; the page shows it when the
  participant comes back;
- ``withdrawn`` (status withdrawn): the participant withdrew from the study (the page's "Withdraw from the study"),
  or the researcher withdrew them; Prolific calls it a returned submission.

An active session has no outcome.

Each outcome has a code (``code_<outcome>``) and a redirect: ``redirect_<outcome>`` when set, otherwise the shared
``redirect_url``. Codes by default: completed ``TRUSTLAB-DONE``, declined ``TRUSTLAB-NOCONSENT``, screened out
``TRUSTLAB-SCREENED``, and **timed out and withdrawn none**: a participant who went quiet gets no code and no
redirect unless the study sets ``code_timed_out`` (Prolific, for one, can take a code for timed-out returns) or
``redirect_timed_out``; the page then says the session ended because it was inactive. Likewise a withdrawal gets a
code or a redirect only from ``code_withdrawn`` / ``redirect_withdrawn``. An outcome without a code gets no redirect
from the shared ``redirect_url`` (it would carry an empty code), only from its own ``redirect_<outcome>``.

Redirect URLs are templates with these placeholders (``REDIRECT_PLACEHOLDERS``), each filled in URL-encoded:
``{code}`` (the outcome's code; empty when it has none), ``{outcome}`` (completed | declined | screened_out |
timed_out | withdrawn) and ``{external_id}`` (the recruitment id the participant joined with, e.g. PROLIFIC_PID; empty
without one). Literal braces are written ``{{`` and ``}}``. Any other placeholder is refused when the study is
configured.
"""

from __future__ import annotations

import string
from enum import StrEnum
from typing import Any
from urllib.parse import quote, urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator


class SessionOutcome(StrEnum):
    """How a session ended, for the recruitment platform (not a trial's ``experiment.task.Outcome``)."""

    COMPLETED = "completed"
    DECLINED = "declined"
    SCREENED_OUT = "screened_out"
    TIMED_OUT = "timed_out"
    WITHDRAWN = "withdrawn"


#: The outcome of each final status (a participant's ``status``); active sessions have none.
OUTCOME_OF_STATUS: dict[str, SessionOutcome] = {
    "completed": SessionOutcome.COMPLETED, "declined": SessionOutcome.DECLINED,
    "screened_out": SessionOutcome.SCREENED_OUT, "abandoned": SessionOutcome.TIMED_OUT,
    "withdrawn": SessionOutcome.WITHDRAWN}

#: What a redirect URL template may use, and what each stands for.
REDIRECT_PLACEHOLDERS = {
    "code": "the outcome's completion code (empty when it has none)",
    "outcome": "completed | declined | screened_out | timed_out | withdrawn",
    "external_id": "the recruitment id the participant joined with, e.g. PROLIFIC_PID (empty without one)",
}

SCREENED_OUT_CODE = "TRUSTLAB-SCREENED"


def outcome_of_status(status: str | None) -> str | None:
    """The outcome of a participant's status (None while active)."""
    outcome = OUTCOME_OF_STATUS.get(str(status)) if status is not None else None
    return outcome.value if outcome else None


def redirect_template_problem(template: str) -> str | None:
    """Why ``template`` is not a usable redirect URL template, or None."""
    try:
        fields = [(name, spec, conversion) for _, name, spec, conversion in string.Formatter().parse(template)
                  if name is not None]
    except ValueError as exc:
        return f"{exc} (write literal braces as {{{{ and }}}})"
    allowed = ", ".join("{" + p + "}" for p in REDIRECT_PLACEHOLDERS)
    for name, spec, conversion in fields:
        if name not in REDIRECT_PLACEHOLDERS:
            return f"unknown placeholder {{{name}}}; a redirect URL may use {allowed}"
        if spec or conversion:
            return f"placeholder {{{name}}} takes no format or conversion"
    return None


def redirect_address_problem(template: str) -> str | None:
    """Why ``template`` is not a full http(s) address, or None. The page sends the participant there: without a
    scheme and host it would be read as a path on this server (a dead end instead of the recruitment site); other
    schemes (javascript:, data:) are no redirect."""
    parts = urlsplit(template)
    if parts.scheme.lower() not in ("http", "https") or not parts.netloc:
        return ("a redirect URL must be a full web address starting with https:// (or http://), e.g. "
                "https://app.prolific.com/submissions/complete?cc={code}")
    return None


#: Validation context of a configuration received now (``experiment.config.validate_document``), as opposed to one
#: stored earlier: rules added after configurations were stored (a redirect must be a full http(s) address) apply
#: to received ones only, so that a stored study version always loads and its running sessions go on.
RECEIVED_DOCUMENT = "received_document"


def _template(value: str | None, info: ValidationInfo) -> str | None:
    if value is None:
        return value
    problem = redirect_template_problem(value)
    if problem is None and (info.context or {}).get(RECEIVED_DOCUMENT):
        problem = redirect_address_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


def _missing(value: object) -> bool:
    return value is None


_CODE: dict[str, Any] = {"min_length": 1, "max_length": 64}
_REDIRECT_DOC = "Redirect URL template for this outcome (placeholders {code}, {outcome}, {external_id}); default: " \
                "redirect_url"


class CompletionConfig(BaseModel):
    """Completion codes and redirects per outcome (module docstring). Fields added after ``redirect_url`` are left
    out of dumps at their defaults, so an older document keeps its config hash."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    code_completed: str = Field("TRUSTLAB-DONE", **_CODE, title="Code: completed",
                                description="Code shown on the debrief (completed)")
    code_declined: str = Field("TRUSTLAB-NOCONSENT", **_CODE, title="Code: consent declined",
                               description="Code shown when consent is declined")
    redirect_url: str | None = Field(None, title="Redirect URL (every outcome)", description=(
        "Redirect URL template of every outcome that has a code and no redirect of its own, e.g. "
        "https://app.prolific.com/submissions/complete?cc={code}; placeholders {code}, {outcome}, {external_id}"))
    code_screened_out: str | None = Field(SCREENED_OUT_CODE, **_CODE,
                                          exclude_if=lambda code: code == SCREENED_OUT_CODE, title="Code: screened out",
                                          description=(
        "Code shown when the session is screened out (eligibility question, attention checks); null: none"))
    code_timed_out: str | None = Field(None, **_CODE, exclude_if=_missing, title="Code: timed out", description=(
        "Code shown when a participant comes back to a session that timed out (abandoned); null (default): none"))
    redirect_completed: str | None = Field(None, exclude_if=_missing, title="Redirect URL: completed",
                                           description=_REDIRECT_DOC)
    redirect_declined: str | None = Field(None, exclude_if=_missing, title="Redirect URL: consent declined",
                                          description=_REDIRECT_DOC)
    redirect_screened_out: str | None = Field(None, exclude_if=_missing, title="Redirect URL: screened out",
                                              description=_REDIRECT_DOC)
    redirect_timed_out: str | None = Field(None, exclude_if=_missing, title="Redirect URL: timed out",
                                           description=_REDIRECT_DOC)
    code_withdrawn: str | None = Field(None, **_CODE, exclude_if=_missing, title="Code: withdrawn", description=(
        "Code shown when the participant withdraws from the study (Prolific: a returned submission) or the "
        "researcher withdraws them; null (default): none"))
    redirect_withdrawn: str | None = Field(None, exclude_if=_missing, title="Redirect URL: withdrawn",
                                           description=_REDIRECT_DOC)

    _templates_known = field_validator("redirect_url", "redirect_completed", "redirect_declined",
                                       "redirect_screened_out", "redirect_timed_out",
                                       "redirect_withdrawn")(_template)

    def code(self, outcome: SessionOutcome | str) -> str | None:
        return getattr(self, f"code_{SessionOutcome(outcome).value}")

    def redirect_template(self, outcome: SessionOutcome | str) -> str | None:
        """The outcome's own redirect, else the shared one when the outcome has a code."""
        own = getattr(self, f"redirect_{SessionOutcome(outcome).value}")
        if own is not None:
            return own
        return self.redirect_url if self.code(outcome) is not None else None


def redirect_link(template: str | None, *, outcome: SessionOutcome | str, code: str | None,
                  external_id: str | None) -> str | None:
    """The redirect URL with its placeholders filled in (URL-encoded), or None without a template."""
    if template is None:
        return None
    values = {"code": code or "", "outcome": SessionOutcome(outcome).value, "external_id": external_id or ""}
    return template.format(**{k: quote(v, safe="") for k, v in values.items()})
