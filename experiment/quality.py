"""Data-quality flags for one participant: hints for the experimenter to look closer, not exclusion rules.

The inputs are plain records (mappings) with the column names of the exports (SPEC §7), so
the same code runs on database rows (native Python values) and on ``trials.csv`` /
``surveys.csv`` / ``participants.csv`` rows read with ``csv.DictReader`` (all strings; flags
``0``/``1``, empty cells for missing values, datetimes as ISO 8601).

``participant_flags(trials, answers, *, status, last_seen_at, now=None, thresholds=THRESHOLDS) -> list[Flag]``

- ``trials``: the participant's trials, any order; read keys ``practice``, ``complexity``,
  ``robot_action``, ``human_action`` (empty while undecided), ``teleop_success``
  (empty when there was no teleoperation or it has not ended) and ``window_opened_by``
  (optional: empty or missing when no window opened).
- ``answers``: the participant's item answers; read keys ``context``, ``questionnaire``,
  ``item`` and ``value`` (the raw answer, not the reverse-coded one).
- ``status``: ``active|completed|declined|abandoned|withdrawn``; ``last_seen_at``: datetime
  or ISO string; ``now``: the time to measure idleness at (None: no idle check, e.g. for a
  finished dataset).

``flags_by_participant(trials, answers, participants, now=None)`` groups export rows by
``participant_id`` and returns ``{participant_id: [Flag, ...]}`` for every participant row
(``duplicate_of`` of those rows groups the sessions of one external id).

The flags (``Flag.code``):

- ``straight_lining``: every item of a questionnaire with at least
  ``min_straight_line_items`` items got the same raw answer in one context (reverse-coded
  items make identical answers contradictory). Two-item shelf surveys are not checked:
  equal trust and reliance answers are normal.
- ``teleop_failed``: every teleoperation (practice included), and at least
  ``min_teleops``, ended without depositing the item (failed or timed out).
- ``never_intervened``: relied on the robot in every one of at least
  ``min_high_auto`` autonomous attempts in high complexity, where the paper's participants
  intervened about one time in five (§5.1): inattentive, or fully trusting.
- ``always_intervened``: intervened in every one of at least ``min_auto`` scored
  autonomous attempts, low complexity included: not supervising as instructed.
- ``idle``: still active but not seen for ``idle_after_s`` seconds (the page sends a
  heartbeat every 10 s); the server marks the session abandoned after the study's idle timeout.
- ``attention_failed``: failed at least one attention check (instructed-response item;
  ``attention_failures``, participants.csv); whether that matters is the researcher's call
  unless the study screens out (``experiment.attention``).
- ``duplicate_id``: another session of the study joined with the same external id without
  proof of being the same person (not the first session's browser, nor its Prolific
  session): one of them is not the id's owner, or the owner started again elsewhere.
  Both (all) sessions of the id are flagged (participants.csv ``duplicate_of``).
- ``scene_not_proven``: at least one decision window (practice included) opened at the study's
  wait limit (``window_opened_by`` = ``wait_limit``) because the page never proved that the
  trial's scene was on screen: the decision may have been made without seeing the obstacles.

Answers to text and choice items (no ``value``) are ignored by the checks of ratings.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from experiment.flow import WindowOpener

Record = Mapping[str, Any]


@dataclass(frozen=True)
class Flag:
    code: str
    detail: str  # one sentence for a person, with the numbers behind the flag


@dataclass(frozen=True)
class QualityThresholds:
    min_straight_line_items: int = 5
    min_teleops: int = 2
    min_high_auto: int = 15
    min_auto: int = 10
    idle_after_s: float = 60.0


THRESHOLDS = QualityThresholds()


def participant_flags(trials: Iterable[Record], answers: Iterable[Record], *, status: str,
                      last_seen_at: datetime | str | None, now: datetime | None = None,
                      thresholds: QualityThresholds = THRESHOLDS, attention_failures: int | str | None = 0,
                      same_id_as: Iterable[str] = ()) -> list[Flag]:
    """The flags of one participant, in the order of the module docstring; ``same_id_as``: the public ids of the
    study's other sessions with this one's external id."""
    trials = list(trials)
    attempts = _scored_auto_attempts(trials)
    found = [*_straight_lining(answers, thresholds), _teleop_failed(trials, thresholds),
             _never_intervened(attempts, thresholds), _always_intervened(attempts, thresholds),
             _idle(status, last_seen_at, now, thresholds), _attention_failed(attention_failures),
             _duplicate_id(same_id_as), _scene_not_proven(trials)]
    return [flag for flag in found if flag is not None]


def same_external_id(participants: Iterable[Record]) -> dict[str, list[str]]:
    """``{participant_id: [the other participant_ids of its external id]}`` from rows with ``participant_id`` and
    ``duplicate_of`` (the first session of the id, on every later one). A first session that is not among the rows
    (its data were deleted: ``duplicate_of`` then names its marker) still counts as another."""
    rows = list(participants)
    ids = {row["participant_id"] for row in rows}
    groups: defaultdict[str, list[str]] = defaultdict(list)
    for row in rows:
        groups[row.get("duplicate_of") or row["participant_id"]].append(row["participant_id"])
    for first, members in groups.items():
        if first not in ids:
            members.append(first)
    return {row["participant_id"]: [other for other in groups[row.get("duplicate_of") or row["participant_id"]]
                                    if other != row["participant_id"]] for row in rows}


def flags_by_participant(trials: Iterable[Record], answers: Iterable[Record], participants: Iterable[Record], *,
                         now: datetime | None = None,
                         thresholds: QualityThresholds = THRESHOLDS) -> dict[str, list[Flag]]:
    """Flags of every row of ``participants`` (export rows: ``participant_id``, ``status``, ``last_seen_at``)."""
    trials_of, answers_of, participants = _group(trials), _group(answers), list(participants)
    same_id = same_external_id(participants)
    return {p["participant_id"]: participant_flags(trials_of[p["participant_id"]], answers_of[p["participant_id"]],
                                                   status=p["status"], last_seen_at=p.get("last_seen_at"), now=now,
                                                   thresholds=thresholds,
                                                   attention_failures=p.get("attention_failures"),
                                                   same_id_as=same_id[p["participant_id"]])
            for p in participants}


def _group(rows: Iterable[Record]) -> defaultdict[str, list[Record]]:
    grouped: defaultdict[str, list[Record]] = defaultdict(list)
    for row in rows:
        grouped[row["participant_id"]].append(row)
    return grouped


def _straight_lining(answers: Iterable[Record], thresholds: QualityThresholds) -> list[Flag]:
    values: defaultdict[tuple[str, str], dict[str, float]] = defaultdict(dict)
    for answer in answers:
        if answer.get("value") in (None, ""):  # a text or choice answer
            continue
        values[(str(answer["context"]), str(answer["questionnaire"]))][str(answer["item"])] = float(answer["value"])
    return [Flag("straight_lining", f"all {len(items)} items of {questionnaire} ({context}) answered "
                                    f"{_number(next(iter(items.values())))}")
            for (context, questionnaire), items in values.items()
            if len(items) >= thresholds.min_straight_line_items and len(set(items.values())) == 1]


def _teleop_failed(trials: list[Record], thresholds: QualityThresholds) -> Flag | None:
    results = [success for t in trials if (success := _flag(t.get("teleop_success"))) is not None]
    if len(results) >= thresholds.min_teleops and not any(results):
        return Flag("teleop_failed", f"all {len(results)} teleoperations failed or timed out")
    return None


def _scored_auto_attempts(trials: list[Record]) -> list[tuple[str, str]]:
    """(complexity, human action) of the decided, scored autonomous attempts."""
    return [(str(t["complexity"]), str(t["human_action"])) for t in trials
            if t.get("robot_action") == "auto" and t.get("human_action") and not _flag(t.get("practice"))]


def _never_intervened(attempts: list[tuple[str, str]], thresholds: QualityThresholds) -> Flag | None:
    high = [action for complexity, action in attempts if complexity == "high"]
    if len(high) >= thresholds.min_high_auto and "intervene" not in high:
        return Flag("never_intervened", f"relied on all {len(high)} autonomous attempts in high complexity")
    return None


def _always_intervened(attempts: list[tuple[str, str]], thresholds: QualityThresholds) -> Flag | None:
    if len(attempts) >= thresholds.min_auto and all(action == "intervene" for _, action in attempts):
        return Flag("always_intervened", f"intervened in all {len(attempts)} autonomous attempts")
    return None


def _idle(status: str, last_seen_at: datetime | str | None, now: datetime | None,
          thresholds: QualityThresholds) -> Flag | None:
    if status != "active" or now is None or not last_seen_at:
        return None
    idle_s = (now - _datetime(last_seen_at)).total_seconds()
    if idle_s >= thresholds.idle_after_s:
        return Flag("idle", f"active but not seen for {idle_s / 60:.0f} min" if idle_s >= 120
                    else f"active but not seen for {idle_s:.0f} s")
    return None


def _attention_failed(failures: int | str | None) -> Flag | None:
    count = int(failures) if failures not in (None, "") else 0
    if count > 0:
        return Flag("attention_failed", f"failed {count} attention check{'s' if count > 1 else ''}")
    return None


def _duplicate_id(same_id_as: Iterable[str]) -> Flag | None:
    others = sorted(same_id_as)
    if others:
        return Flag("duplicate_id", f"its external id also joined as {', '.join(others)} (another browser or "
                                    "recruitment session)")
    return None


def _scene_not_proven(trials: list[Record]) -> Flag | None:
    unproven = [t for t in trials if t.get("window_opened_by") == WindowOpener.WAIT_LIMIT]
    if not unproven:
        return None
    scored = sum(not _flag(t.get("practice")) for t in unproven)
    return Flag("scene_not_proven", f"{len(unproven)} decision window(s) ({scored} scored) opened at the wait limit "
                                    "without proof that the trial's scene was on screen")


def _flag(value: Any) -> bool | None:
    """A flag cell: bool, 0/1, or '0'/'1' (CSV); None or '' when missing."""
    if value is None or value == "":
        return None
    if isinstance(value, str):
        if value not in ("0", "1"):
            raise ValueError(f"a flag must be 0 or 1, not {value!r}")
        return value == "1"
    return bool(value)


def _datetime(value: datetime | str) -> datetime:
    parsed = value if isinstance(value, datetime) else datetime.fromisoformat(value)
    return parsed if parsed.tzinfo else parsed.replace(tzinfo=UTC)  # trustlab's naive times are UTC


def _number(value: float) -> str:
    return str(int(value)) if value.is_integer() else f"{value:g}"
