"""Writing exports: one file as a CSV stream, every file as a streamed zip or into a directory, with a manifest.

Cells are formatted and rows written by ``experiment.codebook.TableWriter``;
pages come from ``server.export.pages``, so memory stays bounded by one page
plus one encoded chunk (``CHUNK_BYTES``).

The zip is streamed too: ``zipfile`` writes to an unseekable sink (entries use
data descriptors and ZIP64 headers), which is drained after every chunk, so
its memory bound is the same page plus the deflate window — no temporary file.
``manifest.json`` comes last, with each file's row count, size and SHA-256.

Every stored row is written: a value that is not standard JSON or UTF-8 (stored before requests were read
strictly) is written in the repaired form ``experiment.writable`` documents, never refused mid-stream.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import select

from experiment.codebook import EXPORT_FILES, TableWriter
from experiment.writable import repair_text
from server.db.units import SessionFactory, SessionOpener
from server.export.pages import PAGE_ROWS, iter_values
from server.export.queries import ExportTarget, export_target
from server.models import AuditAction, StudyVersion, utcnow
from server.services.audit import audit

#: An encoded chunk is yielded once it reaches this many bytes (and at the end of every page).
CHUNK_BYTES = 64 * 1024
#: Bumped when a column changes meaning or is removed (adding columns at the end does not).
FORMAT_VERSION = 1

CSV_MEDIA_TYPE = "text/csv; charset=utf-8"

_ROWS_PER_WRITE = 200


class RowCounter:
    def __init__(self) -> None:
        self.rows = 0


def iter_csv(factory: SessionOpener, target: ExportTarget, name: str, *, page_rows: int = PAGE_ROWS,
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


def _take(buffer: io.StringIO) -> bytes:
    text = buffer.getvalue()
    try:
        data = text.encode("utf-8")
    except UnicodeEncodeError:  # a stored text with a lone surrogate: written as U+FFFD (experiment.writable)
        data = repair_text(text).encode("utf-8")
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

    def close(self) -> None:  # zipfile closes only the files it opened itself
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
            "title": target.title, "include_preview": target.include_preview, "pseudonymised": target.pseudonymised,
            "exported_at": exported_at.isoformat(),
            "versions": _versions(factory, target),
            "files": {name: {"rows": s.rows, "bytes": s.bytes, "sha256": s.sha256} for name, s in files.items()},
            "instruments": _instruments(target)}


def _instruments(target: ExportTarget) -> list[dict[str, Any]]:
    """Every questionnaire of every configuration version, whole (citation, items with their texts and kinds,
    scale, reverse-coded items, attention checks, scoring rule): what surveys.csv's provenance columns point at."""
    return [{"config_version": version, **q.model_dump(mode="json")}
            for (version, _), q in sorted(target.instruments.items())]


def iter_zip(factory: SessionFactory, target: ExportTarget, *, page_rows: int = PAGE_ROWS,
             on_done: Callable[[dict[str, Any]], None] | None = None) -> Iterator[bytes]:
    """All files and ``manifest.json`` as one streamed zip; ``on_done(manifest)`` runs after the last byte."""
    exported_at = utcnow()
    t = exported_at
    stamp = (t.year, t.month, t.day, t.hour, t.minute, t.second)
    sink = _Sink()
    summaries: dict[str, FileSummary] = {}
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_DEFLATED) as archive:
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


def _zip_info(name: str, stamp: tuple[int, int, int, int, int, int]) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=stamp)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def export_study(factory: SessionFactory, slug: str, out_dir: str | Path, *, include_preview: bool = False,
                 pseudonymise: bool = False) -> dict[str, int]:
    """Write every file and ``manifest.json`` of study ``slug`` into ``out_dir``; returns rows per file
    (the experimenter's preview sessions only with ``include_preview``; the recruitment ids as salted hashes with
    ``pseudonymise``).

    Each file is written to a temporary name and renamed when complete. Raises
    ``NotFound`` for an unknown study. Records a ``study.export`` audit line.
    """
    with factory.begin() as session:  # a first pseudonymised export makes the study's key
        target = export_target(session, slug, include_preview=include_preview, pseudonymise=pseudonymise)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    exported_at = utcnow()
    summaries: dict[str, FileSummary] = {}
    for name in EXPORT_FILES:
        counter = RowCounter()
        sha256, size = write_file(out / name, iter_csv(factory, target, name, counter=counter))
        summaries[name] = FileSummary(counter.rows, size, sha256)
    document = manifest(factory, target, summaries, exported_at)
    (out / "manifest.json").write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    counts = {name: s.rows for name, s in summaries.items()}
    record_export(factory, target, "directory", rows=counts, pseudonymise=pseudonymise)
    return counts


def record_export(factory: SessionFactory, target: ExportTarget, file: str, **detail: Any) -> None:
    """An admin audit line for an export, in its own transaction."""
    with factory.begin() as session:
        audit(session, AuditAction.STUDY_EXPORT, study_id=target.study_id, file=file, **detail)


def write_file(path: Path, chunks: Iterable[bytes]) -> tuple[str, int]:
    """Write ``chunks`` to ``path`` whole or not at all (a ``.partial`` file renamed at the end); its SHA-256 (hex)
    and size in bytes."""
    digest, size = hashlib.sha256(), 0
    partial = path.with_name(f".{path.name}.partial")
    try:
        with partial.open("wb") as handle:
            for chunk in chunks:
                handle.write(chunk)
                digest.update(chunk)
                size += len(chunk)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    os.replace(partial, path)
    return digest.hexdigest(), size
