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

Columns, their types and the decimal places numbers are rounded to are
declared once in ``experiment.codebook``, whose ``TableWriter`` formats and
writes every file (the simulator's ``trials.csv`` too): see there for the
cell format.

Rows are ordered by participant (database id, i.e. join order), then by
record id (trials and answers in the order they happened); events by id.

``factory`` is the app's ``server.units.Database`` (a ``sessionmaker`` in tests), or any callable returning a context
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

import hashlib
import io
import json
import os
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import DateTime, Select, TypeDecorator, select, tuple_, type_coerce
from sqlalchemy.orm import Session

from experiment.codebook import (
    CODEBOOK,
    EXPORT_FILES,
    FORMULA_TRIGGERS,
    NUMERIC_TYPES,
    TYPES,
    Column,
    TableWriter,
    codebook_rows,
    columns,
    format_cell,
    format_number,
    formatters,
    neutralise,
)
from server.models import Answer, Event, Participant, StudyVersion, Trial, utcnow
from server.services.audit import audit
from server.services.studies import get_study
from server.units import SessionFactory

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

CSV_MEDIA_TYPE = "text/csv; charset=utf-8"


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
                   t.teleop_tries, t.grasp_radius_m, t.align_radius_m, _dt(t.window_opened_at), t.window_opened_by,
                   _dt(t.scene_shown_at))
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


def _pages(factory: SessionFactory, query: Select[Any], keys: tuple[Any, ...],
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


def _participant_pages(factory: SessionFactory, target: ExportTarget, query: Select[Any],
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


def _raw_pages(factory: SessionFactory, target: ExportTarget, name: str,
               page_rows: int) -> Iterator[Sequence[Sequence[Any]]]:
    if name == "codebook.csv":
        yield codebook_rows()
        return
    source = _SOURCES[name]
    query, keys = source.query(target), source.keys()
    if source.per_participant:
        yield from _participant_pages(factory, target, query, keys, page_rows)
    else:
        yield from _pages(factory, query, keys, page_rows)


def iter_values(factory: SessionFactory, target: ExportTarget, name: str,
                page_rows: int = PAGE_ROWS) -> Iterator[list[tuple[Any, ...]]]:
    """Pages of one file's rows as raw values in the file's column order (formatted by ``TableWriter``)."""
    if name not in CODEBOOK:
        raise KeyError(f"unknown export file {name!r}; files: {', '.join(EXPORT_FILES)}")
    source = _SOURCES.get(name)
    slug_at, convert = (source.slug_at, source.convert) if source else (None, {})
    width = len(CODEBOOK[name]) - (slug_at is not None)
    for page in _raw_pages(factory, target, name, page_rows):
        raw = list(zip(*page))[:width]  # without the keyset keys the query appends
        if slug_at is not None:
            raw.insert(slug_at, (target.slug,) * len(page))
        for i, f in convert.items():
            raw[i] = list(map(f, raw[i]))
        yield list(zip(*raw))


class RowCounter:
    def __init__(self) -> None:
        self.rows = 0


def iter_csv(factory: SessionFactory, target: ExportTarget, name: str, *, page_rows: int = PAGE_ROWS,
             counter: RowCounter | None = None) -> Iterator[bytes]:
    """One file as UTF-8 chunks (header first); ``counter.rows`` counts the data rows written."""
    counter = counter or RowCounter()
    buffer = io.StringIO()
    table = TableWriter(name, buffer)
    for page in iter_values(factory, target, name, page_rows):
        for start in range(0, len(page), _ROWS_PER_WRITE):
            table.write(page[start:start + _ROWS_PER_WRITE])
            if buffer.tell() >= CHUNK_BYTES:
                yield _take(buffer)
        counter.rows += len(page)
    if buffer.tell():
        yield _take(buffer)


_ROWS_PER_WRITE = 200


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


def _versions(factory: SessionFactory, target: ExportTarget) -> list[dict[str, Any]]:
    with factory() as session:
        rows = session.execute(select(StudyVersion.version, StudyVersion.config_hash, StudyVersion.frozen_at)
                               .where(StudyVersion.study_id == target.study_id).order_by(StudyVersion.version)).all()
    return [{"version": v, "config_hash": h, "frozen_at": f.isoformat() if f else None} for v, h, f in rows]


def manifest(factory: SessionFactory, target: ExportTarget, files: dict[str, FileSummary],
             exported_at: datetime) -> dict[str, Any]:
    return {"format": "trustlab-export", "format_version": FORMAT_VERSION, "study": target.slug,
            "title": target.title, "exported_at": exported_at.isoformat(), "versions": _versions(factory, target),
            "files": {name: {"rows": s.rows, "bytes": s.bytes, "sha256": s.sha256} for name, s in files.items()}}


def iter_zip(factory: SessionFactory, target: ExportTarget, *, page_rows: int = PAGE_ROWS,
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


def export_study(factory: SessionFactory, slug: str, out_dir: str | Path) -> dict[str, int]:
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


def record_export(factory: SessionFactory, target: ExportTarget, file: str, **detail: Any) -> None:
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
    "iter_values",
    "iter_zip",
    "manifest",
    "neutralise",
    "NUMERIC_TYPES",
    "TYPES",
    "codebook_rows",
    "format_number",
    "formatters",
    "record_export",
]
