"""The participant's rights over their data, as a study configures them (``StudyConfig.privacy``).

- **Withdrawal** (``withdrawal``): what a participant's "Withdraw from the study" (or the researcher's withdrawal)
  does to their data. ``keep``: the session ends as withdrawn, its research data (trials, answers, events) stay,
  marked excluded with the reason "withdrawn" (left out of fits and reports by default), and its personal fields
  (``PERSONAL_FIELDS``) are erased at once. ``delete``: every row of the participant is deleted; an audit line
  without personal data remains (``server.services.erasure``).
- **The confirmation** (``withdrawal_text``): what the page's confirmation says happens to the data; the study's own
  words, as its consent text promised. Without one the page says what ``withdrawal`` does, in the participant's
  language.
- **Retention** (``erase_personal_after_days``, ``erase_personal_on``): when the personal fields of ended sessions
  are erased by the server's sweeper; the research data stay.
- **Pseudonymised exports** (``pseudonym``): an export may write the recruitment ids as salted hashes, keyed per
  study.

Pure: no web, no database.
"""

from __future__ import annotations

import hmac
from datetime import UTC, date, datetime, time, timedelta
from typing import Annotated, Any, Final, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

#: What withdrawing does to the participant's data.
WithdrawalData = Literal["keep", "delete"]

#: The participant's fields that identify a person or link a session to one (the recruitment id and parameters, the
#: browser's resume key, the keyed address hash, a questionnaire draft's unsent answers): erased by retention and by
#: a withdrawal that keeps the data. The research data (trials, answers, events, scores) are not among them.
PERSONAL_FIELDS: Final = ("external_id", "recruitment", "resume_key_hash", "join_address_hash", "survey_draft")

#: The longest confirmation text a study may give.
MAX_WITHDRAWAL_TEXT = 2000
#: The longest retention a study may set (ten years).
MAX_RETENTION_DAYS = 3650


def _date_from_text(value: Any) -> Any:
    """A date as JSON writes it ("2030-06-01"): a received document is read strictly, and strict JSON takes no
    string for a date."""
    if isinstance(value, str):
        try:
            return date.fromisoformat(value)
        except ValueError:
            raise ValueError(f"a date is written YYYY-MM-DD, e.g. 2030-06-01 (got {value!r})") from None
    return value


#: A date, written in JSON as "YYYY-MM-DD".
JsonDate = Annotated[date, BeforeValidator(_date_from_text)]


class PrivacyConfig(BaseModel):
    """Withdrawal and retention (module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    withdrawal: WithdrawalData = Field("keep", title="What withdrawal does to the data", description=(
        'When a participant withdraws (the "Withdraw from the study" link on every page) or the researcher '
        'withdraws them: "keep" (default) keeps their research data, marked withdrawn and excluded (left out of '
        "fits and reports by default), and erases their recruitment id and other personal fields; \"delete\" "
        "deletes every row of theirs (trials, answers, events, logs), leaving only an audit line without personal "
        "data. Say the same in the consent text"))
    withdrawal_text: str | None = Field(None, min_length=1, max_length=MAX_WITHDRAWAL_TEXT,
                                        title="Withdrawal confirmation text", description=(
        "What the withdrawal confirmation tells the participant happens to their data, in the study's own words "
        "(as the consent text promised); null (default): a sentence saying what the withdrawal setting does"))
    erase_personal_after_days: int | None = Field(None, ge=0, le=MAX_RETENTION_DAYS,
                                                  title="Erase personal data after (days)", description=(
        "Days after a session ends (completed, declined, screened out, timed out or withdrawn) after which its "
        "personal fields (recruitment id such as PROLIFIC_PID, recruitment parameters, resume key, address hash) "
        "are erased by the server; the research data stay. 0: as soon as the session ends; null (default): kept "
        "until a date below, a deletion, or for good"))
    erase_personal_on: JsonDate | None = Field(None, title="Erase personal data on (date)", description=(
        "A date (YYYY-MM-DD, UTC) from which the personal fields of every ended session are erased; sessions "
        "still running then are erased when they end. null (default): no date"))

    @property
    def retains(self) -> bool:
        """Whether the study sets a retention rule."""
        return self.erase_personal_after_days is not None or self.erase_personal_on is not None

    def erase_due(self, finished_at: datetime, now: datetime) -> bool:
        """Whether the personal fields of a session that ended at ``finished_at`` are due for erasure at ``now``."""
        return finished_at <= ended_before(self, now)


def start_of(day: date) -> datetime:
    """Midnight UTC at the start of ``day``."""
    return datetime.combine(day, time(0), tzinfo=UTC)


#: ``ended_before`` when no session is due.
NOTHING_DUE: Final = datetime.min.replace(tzinfo=UTC)


def ended_before(privacy: PrivacyConfig, now: datetime) -> datetime:
    """Sessions that ended at or before this time have their personal fields erased at ``now`` (``NOTHING_DUE``
    when nothing is): ``now`` on and after the date ``erase_personal_on``, else ``now`` less
    ``erase_personal_after_days``."""
    if privacy.erase_personal_on is not None and now >= start_of(privacy.erase_personal_on):
        return now
    if privacy.erase_personal_after_days is not None:
        return now - timedelta(days=privacy.erase_personal_after_days)
    return NOTHING_DUE


def retention_summary(privacy: PrivacyConfig) -> str:
    """The retention rule in words, for the dashboard and the docs: "30 days after each session ends", "on
    2027-03-01", both, or "kept (no retention set)"."""
    parts = []
    if privacy.erase_personal_after_days is not None:
        days = privacy.erase_personal_after_days
        parts.append("when each session ends" if days == 0 else
                     f"{days} day{'s' if days != 1 else ''} after each session ends")
    if privacy.erase_personal_on is not None:
        parts.append(f"on {privacy.erase_personal_on.isoformat()} (sessions ended by then)")
    return "erased " + ", or ".join(parts) if parts else "kept (no retention set)"


#: Recruitment parameters that name no person (Prolific's STUDY_ID names the study): kept as they are when an export
#: pseudonymises the others.
NOT_PERSONAL_PARAMS: Final = frozenset({"STUDY_ID"})
#: Hex digits of a pseudonym (96 bits: no two ids of a study share one in practice).
PSEUDONYM_HEX = 24


def pseudonym(key: bytes, value: str) -> str:
    """A recruitment id as a pseudonymised export writes it: HMAC-SHA256 under the study's own key (a random key the
    server keeps), its first ``PSEUDONYM_HEX`` hex digits. The same id gives the same pseudonym in every export of
    the study, another in another study's, and without the key it cannot be traced back to the id."""
    return hmac.new(key, value.encode(), "sha256").hexdigest()[:PSEUDONYM_HEX]


def pseudonymised_parameters(key: bytes, parameters: dict[str, Any]) -> dict[str, Any]:
    """Recruitment parameters with every value that may name a person (all but ``NOT_PERSONAL_PARAMS``)
    pseudonymised."""
    return {name: value if name in NOT_PERSONAL_PARAMS or not isinstance(value, str) or not value
            else pseudonym(key, value) for name, value in parameters.items()}
