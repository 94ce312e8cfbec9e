"""Study exports (SPEC §7, §10): streamed CSV files, their codebook, a zip with a manifest.

Files (UTF-8 without BOM, one header row, ``\\n`` line ends, RFC 4180 quoting):

- ``trials.csv``: one row per completed trial (practice included, ``practice=1``).
  The leading columns are ``experiment.records.MODEL_COLUMNS`` exactly, so
  ``experiment.records.read_sequences`` reads the file as it is.
- ``surveys.csv``: one row per questionnaire item answer.
- ``participants.csv``: one row per participant (withdrawn ones as tombstones).
- ``events.csv``: the fine-grained event log, in the order it was written.
- ``codebook.csv``: one row per column of every file (this one included), from
  the hand-written :data:`CODEBOOK` table below.

Every cell is formatted by its column's codebook type, never by sniffing the
value: numbers (``integer``, ``number``, ``flag``) are written as numbers
(a reward of -4 stays ``-4``; integral floats lose their ``.0``; other floats
are the shortest round-trip ``repr``; missing values and NaN are empty cells),
datetimes as ``YYYY-MM-DDTHH:MM:SS.ffffffZ`` (UTC), and text, category and
JSON cells are neutralised against spreadsheet formula injection: a cell
starting with ``=``, ``+``, ``-``, ``@``, tab or CR gets a leading ``'`` (so a
free-text ``-4`` becomes ``'-4``, while the number -4 stays ``-4``).

Rows are ordered by participant (database id, i.e. join order), then by
record id (trials and answers in the order they happened); events by id.

``factory`` is a ``sessionmaker``, or any callable returning a context
manager that yields a session (``lambda: nullcontext(session)`` reads within
a transaction that is already open, as the model fit does).

Memory: rows are read by keyset pagination (``PAGE_ROWS`` rows per query,
ordered by an indexed key; trials and answers ``PARTICIPANT_BATCH``
participants per query so that no query sorts a whole study), each page in its own short read-only session that
is closed before the page is formatted and yielded. Memory is bounded by one
page plus one encoded chunk, whatever the number of rows. On SQLite every
transaction takes the write lock (``BEGIN IMMEDIATE``, see ``server.db``), so a
single long read transaction would stall participants while a slow client
downloads; short per-page transactions hold it for milliseconds. The price is
that an export taken while a study runs is not one snapshot: rows committed
during the export may or may not appear, but no row appears twice or half
written, and each row is internally consistent.

The zip is streamed too: ``zipfile`` writes to an unseekable sink (entries use
data descriptors and ZIP64 headers), which is drained after every chunk, so
its memory bound is the same page plus the deflate window — no temporary file.
``manifest.json`` comes last, with each file's row count, size and SHA-256.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import DateTime, Select, TypeDecorator, select, tuple_, type_coerce
from sqlalchemy.orm import Session, sessionmaker

from experiment.records import MODEL_COLUMNS
from server.models import Answer, Event, Participant, StudyVersion, Trial, utcnow
from server.services.audit import audit
from server.services.studies import get_study

#: Rows fetched per query (one short transaction each: on SQLite it holds the write lock, so keep it small).
PAGE_ROWS = 1000
#: Participants whose trials (or answers) one query covers (then paged by ``PAGE_ROWS``).
PARTICIPANT_BATCH = 5
#: Participant ids fetched per query to form those batches.
ID_PAGE = 1000
#: An encoded chunk is yielded once it reaches this many bytes (and at the end of every page).
CHUNK_BYTES = 64 * 1024
#: Bumped when a column changes meaning or is removed (adding columns at the end does not).
FORMAT_VERSION = 1

FORMULA_TRIGGERS = ("=", "+", "-", "@", "\t", "\r")
#: Codebook types written as numbers (never neutralised).
NUMERIC_TYPES = frozenset({"integer", "number", "flag"})
TYPES = NUMERIC_TYPES | {"category", "text", "datetime", "json"}


@dataclass(frozen=True)
class Column:
    """One codebook row."""

    name: str
    type: str  # integer | number | flag (0/1) | category | text | datetime (ISO 8601, UTC) | json
    meaning: str
    allowed: str = ""  # allowed values ("a|b") or range
    unit: str = ""


def _values(name: str) -> str:
    allowed = MODEL_COLUMNS[name]
    assert allowed is not None
    return "|".join(allowed)


_UTC = "ISO 8601, UTC"
_P_HIGH = "probability P(trust = high)"
_POLICIES = "practice|trust_aware|trust_agnostic|random_assist|always_auto|always_ask"

#: The codebook: every column of every exported file, in file order. Written by hand; a test checks
#: that it matches the files exactly.
CODEBOOK: dict[str, tuple[Column, ...]] = {
    "trials.csv": (
        Column("participant_id", "text", "Participant's public id (not a credential); joins all files."),
        Column("block", "integer", "Position of the block in the participant's block order, from 1; 0 for practice.",
               "0, 1, 2, ..."),
        Column("trial", "integer", "Index of the trial within its block (or within practice), from 1.", "1, 2, ..."),
        Column("complexity", "category", "Complexity of the item to collect.", _values("complexity")),
        Column("robot_action", "category", "What the robot did: auto = attempt autonomously (a+), ask = ask the "
               "human for help (a-).", _values("robot_action")),
        Column("human_action", "category", "What the human did: rely = let the robot attempt (o+), intervene = "
               "teleoperate (o-; always the case after ask).", _values("human_action")),
        Column("outcome", "category", "Outcome of the autonomous attempt; none when the robot did not attempt "
               "(it asked, or the human intervened).", _values("outcome")),
        Column("experience", "category", "Experience E_{t+1} the trial gave the human (model input).",
               _values("experience")),
        Column("practice", "flag", "1 for a practice trial (not used for model fitting).", _values("practice")),
        Column("excluded", "flag", "1 if the participant is excluded from analysis (participant's flag at "
               "export time; reason in participants.csv).", _values("excluded")),
        Column("study", "text", "Study slug."),
        Column("version", "integer", "Study configuration version the participant ran under.", "1, 2, ..."),
        Column("block_name", "category", "Name of the block in the study configuration; practice for practice "
               "trials."),
        Column("policy", "category", "Robot policy of the block.", _POLICIES),
        Column("trial_overall", "integer", "Index of the trial over all scored blocks, from 1 (practice: index "
               "within practice).", "1, 2, ..."),
        Column("shelf", "integer", "Shelf number within the block, from 1 (a shelf survey follows its last "
               "trial); 1 for practice.", "1, 2, ..."),
        Column("reward", "number", "Reward of the trial R^a_{o,E} (eq. 1 of the paper; study's reward table).",
               unit="points"),
        Column("score", "number", "Running score after the trial (practice trials do not change it).",
               unit="points"),
        Column("belief_before", "number", "Belief that trust is high before the trial, under the study's model "
               "and belief update.", "[0, 1]", _P_HIGH),
        Column("belief_after", "number", "Belief that trust is high after the trial (belief_before updated with "
               "this trial); equals belief_before for practice.", "[0, 1]", _P_HIGH),
        Column("policy_belief", "number", "Belief the block's policy acted on (differs from belief_before when "
               "the block's policy uses its own model); empty for practice.", "[0, 1]", _P_HIGH),
        Column("decision_time_ms", "number", "Time from the decision window opening to the Intervene press "
               "(browser clock); empty when the human relied, the robot asked or the client sent no times.",
               unit="ms"),
        Column("teleop_time_ms", "number", "Duration of the teleoperation (the time limit when it timed out); "
               "empty without teleoperation.", unit="ms"),
        Column("teleop_success", "flag", "1 if teleoperation deposited the item; empty without teleoperation.",
               "0|1"),
        Column("failure_mode", "category", "How an autonomous attempt failed; empty unless outcome is failure.",
               "collision|drop"),
        Column("started_at", "datetime", "When the trial started (server clock).", unit=_UTC),
        Column("decided_at", "datetime", "When the decision was made (Intervene pressed, or the decision window "
               "closed for rely); empty when the robot asked.", unit=_UTC),
        Column("completed_at", "datetime", "When the trial was resolved (server clock).", unit=_UTC),
        Column("model_hash", "text", "SHA-256 of the canonical JSON of the model document the trial ran under: "
               "the trust-aware block's own model, otherwise the study's belief model (the word paper stands for "
               "the paper's parameters as a model document); equals the content_hash of a fitted model deployed "
               "by trustlab. Empty for trials recorded before provenance was kept.", "64 hex digits"),
        Column("policy_hash", "text", "SHA-256 of the canonical JSON of the block's resolved policy: its spec with "
               "the schedule's p_high filled in and the model replaced by its hash, plus the study's task (rewards); "
               "practice trials hash the practice list. Empty for trials recorded before provenance was kept.",
               "64 hex digits"),
        Column("seed", "integer", "Study seed. With participant_id, block_name and trial it determines every random "
               "draw of the trial (complexity schedule, the policy's randomness, the autonomous outcome). Empty for "
               "trials recorded before provenance was kept.", "0 ... 2^63 - 1"),
        Column("tutorial", "flag", "1 if the trial's teleoperation was the guided practice (study config "
               "practice.tutorial: every practice teleoperation until the participant's first deposit; a try that "
               "runs out of time starts over from the ready pose).", "0|1"),
        Column("teleop_tries", "integer", "Tries of the teleoperation (more than 1 only for the guided practice); "
               "empty without teleoperation.", "1 ... practice.tutorial.max_tries"),
        Column("grasp_radius_m", "number", "Teleoperation rule the trial ran under (study config "
               "teleop.grasp_radius_m): closing grasps when the gripper centre is this close to the item's grasp "
               "point; empty without teleoperation.", "(0, 0.2]", unit="m"),
        Column("align_radius_m", "number", "Teleoperation assistance the trial ran under (study config "
               "teleop.align_radius_m): closing within this distance first moves the gripper onto the grasp point; "
               "0 = no assistance; empty without teleoperation.", "[0, 0.3]", unit="m"),
    ),
    "surveys.csv": (
        Column("participant_id", "text", "Participant's public id."),
        Column("study", "text", "Study slug."),
        Column("version", "integer", "Study configuration version.", "1, 2, ..."),
        Column("context", "category", "When the questionnaire was asked: before (before the first block), "
               "shelf:B:S (after shelf S of block position B), after:B (after block position B).",
               "before|shelf:B:S|after:B"),
        Column("block", "integer", "Block position the answer follows, from 1; empty for before.", "1, 2, ..."),
        Column("block_name", "category", "Name of that block in the study configuration; empty for before."),
        Column("shelf", "integer", "Shelf within the block for shelf surveys, from 1; empty otherwise.", "1, 2, ..."),
        Column("questionnaire", "category", "Questionnaire id in the study configuration.",
               "e.g. shelf_trust_reliance|schaefer_14"),
        Column("item", "category", "Item id within the questionnaire."),
        Column("value", "number", "The answer as given on the questionnaire's scale.",
               unit="scale points (see the questionnaire's scale, e.g. % for schaefer_14)"),
        Column("scored_value", "number", "The answer with reverse-coded items reversed (scale min + max - value); "
               "equals value otherwise.", unit="scale points"),
        Column("belief", "number", "Model belief that trust is high when the answer was given.", "[0, 1]", _P_HIGH),
        Column("answered_at", "datetime", "When the answer was recorded (server clock).", unit=_UTC),
        Column("excluded", "flag", "1 if the participant is excluded from analysis.", "0|1"),
    ),
    "participants.csv": (
        Column("participant_id", "text", "Participant's public id."),
        Column("external_id", "text", "Recruitment platform id (e.g. PROLIFIC_PID); empty if none or withdrawn."),
        Column("study", "text", "Study slug."),
        Column("version", "integer", "Study configuration version the participant ran under.", "1, 2, ..."),
        Column("status", "category", "Session status.", "active|completed|declined|abandoned|withdrawn"),
        Column("block_order", "text", "Block names in the order the participant did them, separated by |; "
               "empty until the first scored trial.", "e.g. trust_aware|trust_agnostic"),
        Column("joined_at", "datetime", "When the participant opened the study link.", unit=_UTC),
        Column("consented_at", "datetime", "When consent was given; empty if not (yet).", unit=_UTC),
        Column("started_at", "datetime", "Start of the first scored trial.", unit=_UTC),
        Column("finished_at", "datetime", "When the session ended (completed, declined, abandoned or withdrawn).",
               unit=_UTC),
        Column("last_seen_at", "datetime", "Last request from the participant (written at most every 5 s).", unit=_UTC),
        Column("score", "number", "Total score.", unit="points"),
        Column("compensation", "number", "Payment: base plus score bonus (capped); empty until completed.",
               unit="study currency (config compensation.currency)"),
        Column("completion_code", "text", "Code shown at the end (completed or declined)."),
        Column("excluded", "flag", "1 if excluded from analysis.", "0|1"),
        Column("exclusion_reason", "text", "Why the participant was excluded (withdrawn for withdrawals)."),
        Column("recruitment", "json", "Recruitment parameters of the join link (e.g. PROLIFIC_PID, STUDY_ID, "
               "SESSION_ID), as a JSON object."),
    ),
    "events.csv": (
        Column("participant_id", "text", "Participant's public id; empty for study-level events."),
        Column("kind", "category", "Event kind (client events are prefixed client.).",
               "e.g. joined|consent|step|trial_started|intervene|trial_completed|teleop_log|teleop_timeout|"
               "teleop_retry|block_order_assigned|abandoned|client.*. teleop_log's payload holds entries, each with "
               "server_ms (since the teleoperation began) and either an input the participant started to hold "
               "(client_ms, seq, input: ee_velocity m/s | joint_velocity rad/s | gripper) or a world event "
               "(grasped, aligned, dropped, item_reset, deposited, blocked, deadman_stop, resumed, disconnect_stop): the arm "
               "moves on the server's clock from the held input, so the inputs and their times reconstruct the "
               "teleoperation."),
        Column("client_time_ms", "number", "Browser performance.now() when the client reported the event; empty "
               "for server events.", unit="ms"),
        Column("server_monotonic_s", "number", "Server monotonic clock when written (comparable only within one "
               "server process run).", unit="s"),
        Column("created_at", "datetime", "When the event was written (server clock).", unit=_UTC),
        Column("payload", "json", "Event details as a JSON object."),
    ),
    "codebook.csv": (
        Column("file", "category", "Exported file the column belongs to.",
               "trials.csv|surveys.csv|participants.csv|events.csv|codebook.csv"),
        Column("column", "text", "Column name (header cell) in that file."),
        Column("type", "category", "How cells are written: integer, number (decimal), flag (0/1), category "
               "(one of a set), text, datetime (ISO 8601 UTC) or json. Empty cells mean missing.",
               "|".join(sorted(TYPES))),
        Column("allowed_values", "text", "Allowed values (a|b) or range, when restricted."),
        Column("unit", "text", "Unit of measurement or format."),
        Column("meaning", "text", "What the column holds."),
    ),
}

EXPORT_FILES: tuple[str, ...] = tuple(CODEBOOK)
CSV_MEDIA_TYPE = "text/csv; charset=utf-8"


def columns(name: str) -> list[str]:
    return [c.name for c in CODEBOOK[name]]


# -- cells ---------------------------------------------------------------------------------------

_TRIGGER_CHARS = frozenset(FORMULA_TRIGGERS)


def neutralise(text: str) -> str:
    """Prefix ``'`` to a text cell a spreadsheet would read as a formula (SPEC §10)."""
    return "'" + text if text and text[0] in _TRIGGER_CHARS else text


def format_number(value: Any) -> str:
    """A number cell: integral values without ``.0``, others as the shortest round-trip repr; NaN empty."""
    if type(value) is float:
        if math.isnan(value):
            return ""
        if value.is_integer() and -1e15 < value < 1e15:
            return str(int(value))
        return repr(value)
    if value is None:
        return ""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, int):
        return str(value)
    return format_number(float(value))


def _format_integer(value: Any) -> str:
    return str(value) if type(value) is int else format_number(value)


def _format_flag(value: Any) -> str:
    return "" if value is None else ("1" if value else "0")


def _format_text(value: Any) -> str:
    if value is None:
        return ""
    text = value if type(value) is str else str(value)
    return "'" + text if text and text[0] in _TRIGGER_CHARS else text


def _format_datetime(value: datetime | str | None) -> str:
    """``YYYY-MM-DDTHH:MM:SS.ffffffZ`` (UTC); ``value`` is a datetime or SQLite's stored UTC text."""
    if value is None:
        return ""
    if type(value) is str:
        if len(value) == 26 and value[10] == " ":  # SQLAlchemy's SQLite storage format, in UTC (TZDateTime)
            return value[:10] + "T" + value[11:] + "Z"
        value = datetime.fromisoformat(value)
    if value.tzinfo is None:  # naive values are UTC in trustlab
        value = value.replace(tzinfo=UTC)
    return value.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _format_json(value: Any) -> str:
    if value is None:
        return ""
    return _format_text(json.dumps(value, sort_keys=True, ensure_ascii=False, separators=(",", ":")))


_FORMATTERS: dict[str, Callable[[Any], str]] = {
    "integer": _format_integer, "number": format_number, "flag": _format_flag, "category": _format_text,
    "text": _format_text, "datetime": _format_datetime, "json": _format_json,
}


def format_cell(column_type: str, value: Any) -> str:
    """A cell as written for a column of ``column_type`` (a codebook type), never sniffed from the value."""
    return _FORMATTERS[column_type](value)


def formatters(name: str) -> list[Callable[[Any], str]]:
    return [_FORMATTERS[c.type] for c in CODEBOOK[name]]


# -- queries -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ExportTarget:
    """The study an export is for (resolved once, before streaming)."""

    study_id: int
    slug: str
    title: str


def export_target(session: Session, slug: str) -> ExportTarget:
    """The study with ``slug``; raises ``NotFound`` (404) naming it otherwise."""
    study = get_study(session, slug)
    return ExportTarget(study.id, study.slug, study.title)


class _StoredDateTime(TypeDecorator[Any]):
    """A ``TZDateTime`` column read as SQLite stores it (UTC text), skipping the parse to ``datetime``
    that ``_format_datetime`` would undo; other backends return datetimes as usual."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def result_processor(self, dialect: Any, coltype: Any) -> Any:
        if dialect.name == "sqlite":
            return None
        return super().result_processor(dialect, coltype)


def _dt(column: Any) -> Any:
    return type_coerce(column, _StoredDateTime()).label(column.key)


@dataclass(frozen=True)
class _Source:
    """How one file is read: a query selecting the file's columns in order, and its keyset key."""

    query: Callable[[ExportTarget], Select[Any]]
    keys: Callable[[], tuple[Any, ...]]  # ordered, indexed, unique; appended to the select
    #: Read participant by participant (``keys[0]`` is the participant id): see ``_participant_pages``.
    per_participant: bool = False
    #: Output position of the ``study`` column (the slug, filled in here rather than selected).
    slug_at: int | None = None
    #: Values to convert before formatting, by output position.
    convert: dict[int, Callable[[Any], Any]] = field(default_factory=dict)


def _trials_query(target: ExportTarget) -> Select[Any]:
    p, t = Participant, Trial
    # ``stage`` through an expression, so that no planner prefers ix_trial_stage (every finished trial
    # of the database) to the participant index.
    return (select(p.public_id, t.block, t.trial, t.complexity, t.robot_action, t.human_action, t.outcome,
                   t.experience, t.practice, p.excluded, StudyVersion.version, t.block_name, t.policy,
                   t.trial_overall, t.shelf, t.reward, t.score, t.belief_before, t.belief_after, t.policy_belief,
                   t.decision_time_ms, t.teleop_time_ms, t.teleop_success, t.failure_mode, _dt(t.started_at),
                   _dt(t.decided_at), _dt(t.completed_at), t.model_hash, t.policy_hash, t.seed, t.tutorial,
                   t.teleop_tries, t.grasp_radius_m, t.align_radius_m)
            .join(p, p.id == t.participant_id).join(StudyVersion, StudyVersion.id == t.study_version_id)
            .where(p.study_id == target.study_id, (t.stage + "") == "done"))


def _surveys_query(target: ExportTarget) -> Select[Any]:
    p, a = Participant, Answer
    return (select(p.public_id, StudyVersion.version, a.context, a.block, a.block_name, a.shelf,
                   a.questionnaire, a.item, a.value, a.scored_value, a.belief, _dt(a.answered_at), p.excluded)
            .join(p, p.id == a.participant_id).join(StudyVersion, StudyVersion.id == a.study_version_id)
            .where(p.study_id == target.study_id))


def _participants_query(target: ExportTarget) -> Select[Any]:
    p = Participant
    return (select(p.public_id, p.external_id, StudyVersion.version, p.status, p.block_order, _dt(p.created_at),
                   _dt(p.consented_at), _dt(p.started_at), _dt(p.finished_at), _dt(p.last_seen_at), p.score,
                   p.compensation, p.completion_code, p.excluded, p.exclusion_reason, p.recruitment)
            .join(StudyVersion, StudyVersion.id == p.study_version_id)
            .where(p.study_id == target.study_id))


def _block_order(order: list[str] | None) -> str | None:
    return "|".join(order) if order else None


def _events_query(target: ExportTarget) -> Select[Any]:
    e = Event
    return (select(Participant.public_id, e.kind, e.client_time_ms, e.server_monotonic_s, _dt(e.created_at),
                   e.payload)
            .outerjoin(Participant, Participant.id == e.participant_id)
            .where(e.study_id == target.study_id))


_SOURCES: dict[str, _Source] = {
    "trials.csv": _Source(_trials_query, lambda: (Trial.participant_id, Trial.id), per_participant=True, slug_at=10),
    "surveys.csv": _Source(_surveys_query, lambda: (Answer.participant_id, Answer.id), per_participant=True,
                           slug_at=1),
    "participants.csv": _Source(_participants_query, lambda: (Participant.id,), slug_at=2, convert={5: _block_order}),
    "events.csv": _Source(_events_query, lambda: (Event.id,)),  # ix_event_study_id is (study_id, id)
}


def _pages(factory: sessionmaker[Session], query: Select[Any], keys: tuple[Any, ...],
           page_rows: int) -> Iterator[list[Any]]:
    """Keyset pagination: each page in its own short session, closed before the page is used."""
    n_keys, last = len(keys), None
    query = query.add_columns(*keys).order_by(*keys).limit(page_rows)
    while True:
        page_query = query
        if last is not None:
            page_query = query.where(tuple_(*keys) > tuple_(*last) if n_keys > 1 else keys[0] > last[0])
        with factory() as session:  # read only: nothing is added, the transaction is rolled back on close
            rows = session.connection().execute(page_query).all()
        if rows:
            yield rows
        if len(rows) < page_rows:
            return
        last = tuple(rows[-1][-n_keys:])


def _participant_pages(factory: sessionmaker[Session], target: ExportTarget, query: Select[Any],
                       keys: tuple[Any, ...], page_rows: int) -> Iterator[list[Any]]:
    """Keyset pages of per-participant rows, ``PARTICIPANT_BATCH`` participants per query.

    Ordering all of a study's trials by (participant, id) in one query makes the database sort
    every row of the study for each page (quadratic); restricting each query to a small batch of
    participant ids keeps every page's work (and the time it holds SQLite's lock) proportional to
    the batch.
    """
    last_id = 0
    while True:
        with factory() as session:
            ids = session.scalars(select(Participant.id).where(Participant.study_id == target.study_id,
                                                               Participant.id > last_id)
                                  .order_by(Participant.id).limit(ID_PAGE)).all()
        for start in range(0, len(ids), PARTICIPANT_BATCH):
            batch = ids[start:start + PARTICIPANT_BATCH]
            yield from _pages(factory, query.where(Participant.id.in_(batch), keys[0].in_(batch)), keys, page_rows)
        if len(ids) < ID_PAGE:
            return
        last_id = ids[-1]


def codebook_rows() -> Iterator[tuple[str, ...]]:
    for file, cols in CODEBOOK.items():
        for c in cols:
            yield (file, c.name, c.type, c.allowed, c.unit, c.meaning)


def _raw_pages(factory: sessionmaker[Session], target: ExportTarget, name: str,
               page_rows: int) -> Iterator[Sequence[Sequence[Any]]]:
    if name == "codebook.csv":
        yield list(codebook_rows())
        return
    source = _SOURCES[name]
    query, keys = source.query(target), source.keys()
    if source.per_participant:
        yield from _participant_pages(factory, target, query, keys, page_rows)
    else:
        yield from _pages(factory, query, keys, page_rows)


def iter_rows(factory: sessionmaker[Session], target: ExportTarget, name: str,
              page_rows: int = PAGE_ROWS) -> Iterator[list[tuple[str, ...]]]:
    """Pages of one file's rows as formatted cells (without the header)."""
    if name not in CODEBOOK:
        raise KeyError(f"unknown export file {name!r}; files: {', '.join(EXPORT_FILES)}")
    source = _SOURCES.get(name)
    slug_at, convert = (source.slug_at, source.convert) if source else (None, {})
    width, cells = len(CODEBOOK[name]) - (slug_at is not None), formatters(name)
    for page in _raw_pages(factory, target, name, page_rows):
        # Column by column: one ``map`` per column is much faster than a call per cell from Python.
        raw = list(zip(*page))[:width]
        if slug_at is not None:
            raw.insert(slug_at, (target.slug,) * len(page))
        for i, f in convert.items():
            raw[i] = list(map(f, raw[i]))
        yield list(zip(*(map(f, column) for f, column in zip(cells, raw, strict=True))))


class RowCounter:
    def __init__(self) -> None:
        self.rows = 0


def iter_csv(factory: sessionmaker[Session], target: ExportTarget, name: str, *, page_rows: int = PAGE_ROWS,
             counter: RowCounter | None = None) -> Iterator[bytes]:
    """One file as UTF-8 chunks (header first); ``counter.rows`` counts the data rows written."""
    counter = counter or RowCounter()
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(neutralise(c) for c in columns(name))
    for page in iter_rows(factory, target, name, page_rows):
        for start in range(0, len(page), _ROWS_PER_WRITE):
            _write_rows(writer, buffer, page[start:start + _ROWS_PER_WRITE])
            if buffer.tell() >= CHUNK_BYTES:
                yield _take(buffer)
        counter.rows += len(page)
    if buffer.tell():
        yield _take(buffer)


_ROWS_PER_WRITE = 200


def _write_rows(writer: Any, buffer: io.StringIO, rows: list[tuple[str, ...]]) -> None:
    """RFC 4180 rows. ``csv`` quotes a cell holding a line feed but not one holding a lone CR (our line end is
    ``\n``), which readers take as a line break: rows with a CR in a cell are written here instead (they are rare)."""
    if "\r" not in "".join(map("".join, rows)):
        writer.writerows(rows)
        return
    for row in rows:
        buffer.write(",".join(_rfc4180_cell(cell) for cell in row) + "\n")


def _rfc4180_cell(cell: str) -> str:
    return '"' + cell.replace('"', '""') + '"' if any(c in cell for c in ',"\r\n') else cell


def _take(buffer: io.StringIO) -> bytes:
    data = buffer.getvalue().encode("utf-8")
    buffer.seek(0)
    buffer.truncate()
    return data


# -- zip, directory --------------------------------------------------------------------------------

@dataclass
class FileSummary:
    rows: int = 0
    bytes: int = 0
    sha256: str = ""


class _Sink:
    """An unseekable file for ``zipfile``: collects what it writes until drained."""

    def __init__(self) -> None:
        self._chunks: list[bytes] = []

    def write(self, data: bytes) -> int:
        self._chunks.append(bytes(data))
        return len(data)

    def flush(self) -> None:
        pass

    def drain(self) -> bytes:
        data = b"".join(self._chunks)
        self._chunks.clear()
        return data


def _versions(factory: sessionmaker[Session], target: ExportTarget) -> list[dict[str, Any]]:
    with factory() as session:
        rows = session.execute(select(StudyVersion.version, StudyVersion.config_hash, StudyVersion.frozen_at)
                               .where(StudyVersion.study_id == target.study_id).order_by(StudyVersion.version)).all()
    return [{"version": v, "config_hash": h, "frozen_at": f.isoformat() if f else None} for v, h, f in rows]


def manifest(factory: sessionmaker[Session], target: ExportTarget, files: dict[str, FileSummary],
             exported_at: datetime) -> dict[str, Any]:
    return {"format": "trustlab-export", "format_version": FORMAT_VERSION, "study": target.slug,
            "title": target.title, "exported_at": exported_at.isoformat(), "versions": _versions(factory, target),
            "files": {name: {"rows": s.rows, "bytes": s.bytes, "sha256": s.sha256} for name, s in files.items()}}


def iter_zip(factory: sessionmaker[Session], target: ExportTarget, *, page_rows: int = PAGE_ROWS,
             on_done: Callable[[dict[str, Any]], None] | None = None) -> Iterator[bytes]:
    """All files and ``manifest.json`` as one streamed zip; ``on_done(manifest)`` runs after the last byte."""
    exported_at = utcnow()
    stamp = exported_at.timetuple()[:6]
    sink = _Sink()
    summaries: dict[str, FileSummary] = {}
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_DEFLATED) as archive:  # type: ignore[arg-type]
        for name in EXPORT_FILES:
            counter, digest, size = RowCounter(), hashlib.sha256(), 0
            with archive.open(_zip_info(name, stamp), "w", force_zip64=True) as entry:
                for chunk in iter_csv(factory, target, name, page_rows=page_rows, counter=counter):
                    entry.write(chunk)
                    digest.update(chunk)
                    size += len(chunk)
                    if out := sink.drain():
                        yield out
            summaries[name] = FileSummary(counter.rows, size, digest.hexdigest())
        document = manifest(factory, target, summaries, exported_at)
        archive.writestr(_zip_info("manifest.json", stamp), json.dumps(document, indent=2) + "\n")
    yield sink.drain()
    if on_done is not None:
        on_done(document)


def _zip_info(name: str, stamp: tuple[int, ...]) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=stamp)  # type: ignore[arg-type]
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def export_study(factory: sessionmaker[Session], slug: str, out_dir: str | Path) -> dict[str, int]:
    """Write every file and ``manifest.json`` of study ``slug`` into ``out_dir``; returns rows per file.

    Each file is written to a temporary name and renamed when complete. Raises
    ``NotFound`` for an unknown study. Records a ``study.export`` audit line.
    """
    with factory() as session:
        target = export_target(session, slug)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    exported_at = utcnow()
    summaries: dict[str, FileSummary] = {}
    for name in EXPORT_FILES:
        counter, digest, size = RowCounter(), hashlib.sha256(), 0
        partial = out / f".{name}.partial"
        try:
            with partial.open("wb") as handle:
                for chunk in iter_csv(factory, target, name, counter=counter):
                    handle.write(chunk)
                    digest.update(chunk)
                    size += len(chunk)
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
        os.replace(partial, out / name)
        summaries[name] = FileSummary(counter.rows, size, digest.hexdigest())
    document = manifest(factory, target, summaries, exported_at)
    (out / "manifest.json").write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    counts = {name: s.rows for name, s in summaries.items()}
    record_export(factory, target, "directory", rows=counts)
    return counts


def record_export(factory: sessionmaker[Session], target: ExportTarget, file: str, **detail: Any) -> None:
    """An admin audit line for an export, in its own transaction."""
    with factory.begin() as session:
        audit(session, "study.export", study_id=target.study_id, file=file, **detail)


__all__ = [
    "CODEBOOK",
    "CSV_MEDIA_TYPE",
    "EXPORT_FILES",
    "FORMULA_TRIGGERS",
    "Column",
    "ExportTarget",
    "RowCounter",
    "columns",
    "export_study",
    "export_target",
    "format_cell",
    "iter_csv",
    "iter_rows",
    "iter_zip",
    "manifest",
    "neutralise",
    "record_export",
]
