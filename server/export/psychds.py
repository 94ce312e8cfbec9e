"""A study's export as a Psych-DS 1.5 dataset, streamed as a zip or written into a directory.

What goes where, and which rules of the standard it follows, is ``experiment.psychds``; here the files are
written in one order for both sinks::

    dataset_description.json  README.md  CHANGES.md  .psychdsignore  .psychds-ignore
    data/study-<slug>_description-{trials,surveys,participants,events}_data.csv   (+ a .json sidecar each)
    analysis/README.md  documentation/codebook.csv
    materials/study_config_v<N>.json  materials/study_versions.json
    results/fitted_model_<id>.json  results/fitted_model_<id>_provenance.json   (finished fits)
    documentation/manifest.json  (last: bytes and SHA-256 of every file before it, rows of the CSV files)

The CSV files are the CSV export's (``iter_csv``), byte for byte, streamed page by page as there.
"""

from __future__ import annotations

import hashlib
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy import select

from experiment import psychds
from experiment.config import StudyConfig
from server.db.units import SessionFactory
from server.export.pages import PAGE_ROWS
from server.export.queries import ExportTarget, export_target
from server.export.writers import RowCounter, _Sink, _zip_info, iter_csv, record_export, write_file
from server.models import FitStatus, FittedModel, StudyVersion, utcnow
from server.services import fits

ZIP_NAME = "psych-ds.zip"


@dataclass
class _Entry:
    path: str
    chunks: Iterable[bytes]
    rows: RowCounter | None = None  # CSV files: counts the data rows as they stream


@dataclass
class _Written:
    """What the entries written so far were: the manifest's ``files``."""

    files: dict[str, dict[str, Any]] = field(default_factory=dict)

    def add(self, entry: _Entry, size: int, sha256: str) -> None:
        self.files[entry.path] = {"bytes": size, "sha256": sha256} | (
            {"rows": entry.rows.rows} if entry.rows is not None else {})

    def rows(self) -> dict[str, int]:
        return {path: f["rows"] for path, f in self.files.items() if "rows" in f}


@dataclass(frozen=True)
class _StudyRecords:
    """What the dataset holds besides the data files, read in one short session."""

    versions: list[dict[str, Any]]  # version, config_hash, frozen_at, config (the stored document)
    models: list[tuple[int, dict[str, Any], dict[str, Any]]]  # id, model document, ModelRead as JSON


def _records(factory: SessionFactory, target: ExportTarget) -> _StudyRecords:
    with factory() as session:
        versions = [{"version": v.version, "config_hash": v.config_hash,
                     "frozen_at": v.frozen_at.isoformat() if v.frozen_at else None, "config": v.config}
                    for v in session.scalars(select(StudyVersion).where(StudyVersion.study_id == target.study_id)
                                             .order_by(StudyVersion.version))]
        done = session.scalars(select(FittedModel).where(FittedModel.study_id == target.study_id,
                                                         FittedModel.status == FitStatus.DONE)
                               .order_by(FittedModel.id))
        models = [(m.id, fits.model_document(m), fits.model_read(session, m).model_dump(mode="json")) for m in done]
    return _StudyRecords(versions, models)


def _latest_config(records: _StudyRecords) -> StudyConfig | None:
    try:
        return StudyConfig.model_validate(records.versions[-1]["config"]) if records.versions else None
    except ValueError:  # a stored document this code no longer reads: the dataset goes without its details
        return None


def _text(path: str, text: str) -> _Entry:
    return _Entry(path, [text.encode("utf-8")])


def _entries(factory: SessionFactory, target: ExportTarget, written: _Written, exported_at: str,
             page_rows: int) -> Iterator[_Entry]:
    """Every file of the dataset, in order; the manifest last, from ``written`` (filled by the sink)."""
    records = _records(factory, target)
    config = _latest_config(records)
    yield _text(psychds.DESCRIPTION_PATH, psychds.json_text(psychds.dataset_description(
        title=target.title, study_description=config.description if config else "",
        info=config.dataset if config else None, instruments=target.instruments)))
    model_ids = [model_id for model_id, _, _ in records.models]
    yield _text("README.md", psychds.readme(title=target.title, slug=target.slug,
                                            include_preview=target.include_preview, models=model_ids))
    yield _text("CHANGES.md", psychds.changes(records.versions))
    for name in psychds.IGNORE_FILES:
        yield _text(name, psychds.psychdsignore())
    for name in psychds.DATA_FILES:
        counter = RowCounter()
        yield _Entry(psychds.data_file_path(target.slug, name),
                     iter_csv(factory, target, name, page_rows=page_rows, counter=counter), counter)
        yield _text(psychds.sidecar_path(target.slug, name),
                    psychds.json_text(psychds.sidecar(name, target.instruments)))
    yield _text(psychds.ANALYSIS_PATH, psychds.analysis_readme(target.slug, model_ids))
    counter = RowCounter()
    yield _Entry(psychds.CODEBOOK_PATH, iter_csv(factory, target, "codebook.csv", counter=counter), counter)
    for v in records.versions:
        yield _text(psychds.config_path(v["version"]), psychds.json_text(v["config"]))
    yield _text("materials/study_versions.json", psychds.json_text(
        [{k: v[k] for k in ("version", "config_hash", "frozen_at")} | {"file": psychds.config_path(v["version"])}
         for v in records.versions]))
    for model_id, document, read in records.models:
        document_path, provenance_path = psychds.model_paths(model_id)
        yield _text(document_path, psychds.json_text(document))
        yield _text(provenance_path, psychds.json_text(read))
    yield _text(psychds.MANIFEST_PATH, psychds.json_text({
        "format": "trustlab-psych-ds", "schema_version": psychds.SCHEMA_VERSION, "study": target.slug,
        "title": target.title, "include_preview": target.include_preview, "pseudonymised": target.pseudonymised,
        "exported_at": exported_at,
        "files": written.files}))


def iter_psychds_zip(factory: SessionFactory, target: ExportTarget, *, page_rows: int = PAGE_ROWS,
                     on_done: Callable[[dict[str, int]], None] | None = None) -> Iterator[bytes]:
    """The dataset as one streamed zip (its root is the dataset's root); ``on_done(rows)`` runs after the last
    byte with the data rows of each CSV file."""
    now = utcnow()
    stamp = (now.year, now.month, now.day, now.hour, now.minute, now.second)
    sink, written = _Sink(), _Written()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for entry in _entries(factory, target, written, now.isoformat(), page_rows):
            digest, size = hashlib.sha256(), 0
            with archive.open(_zip_info(entry.path, stamp), "w", force_zip64=True) as member:
                for chunk in entry.chunks:
                    member.write(chunk)
                    digest.update(chunk)
                    size += len(chunk)
                    if out := sink.drain():
                        yield out
            written.add(entry, size, digest.hexdigest())
    yield sink.drain()
    if on_done is not None:
        on_done(written.rows())


def export_psychds(factory: SessionFactory, slug: str, out_dir: str | Path, *, include_preview: bool = False,
                   pseudonymise: bool = False) -> dict[str, int]:
    """Write the dataset of study ``slug`` into ``out_dir`` (its root); returns the data rows of each CSV file (the
    recruitment ids as salted hashes with ``pseudonymise``).

    Each file is written to a temporary name and renamed when complete. Raises ``NotFound`` for an unknown study.
    Records a ``study.export`` audit line.
    """
    with factory.begin() as session:  # a first pseudonymised export makes the study's key
        target = export_target(session, slug, include_preview=include_preview, pseudonymise=pseudonymise)
    out, written = Path(out_dir), _Written()
    for entry in _entries(factory, target, written, utcnow().isoformat(), PAGE_ROWS):
        path = out / entry.path
        path.parent.mkdir(parents=True, exist_ok=True)
        sha256, size = write_file(path, entry.chunks)
        written.add(entry, size, sha256)
    rows = written.rows()
    record_export(factory, target, "psych-ds directory", rows=rows, pseudonymise=pseudonymise)
    return rows
