"""Admin API: streamed study exports (CSV files, codebook, zip with manifest, the Psych-DS dataset as a zip)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from enum import StrEnum
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse
from sqlalchemy.exc import SQLAlchemyError

from server import export
from server.bodies import StrictJsonRoute
from server.deps import AdminDep, ServicesDep, SessionDep
from server.export.psychds import ZIP_NAME, iter_psychds_zip
from server.models import AuditAction
from server.schemas import error_responses
from server.services.audit import audit

log = logging.getLogger("trustlab")

router = APIRouter(route_class=StrictJsonRoute, prefix="/api/admin", tags=["admin"], dependencies=[AdminDep],
                   responses=error_responses(404))

ExportFile = StrEnum(  # type: ignore[misc]  # its members: the names in EXPORT_FILES, at run time
    "ExportFile", {name.removesuffix(".csv"): name for name in export.EXPORT_FILES})

_NO_STORE = {"Cache-Control": "no-store"}

IncludePreview = Annotated[bool, Query(description=(
    "Include the experimenter's preview sessions (left out by default: they are not data); participants.csv "
    "marks them in its preview column."))]
Pseudonymise = Annotated[bool, Query(description=(
    "Write the recruitment ids (participants.csv external_id and the values of recruitment, but STUDY_ID) as "
    "salted hashes keyed per study: the same id gives the same value in every export of the study, another in "
    "another study's (codebook.csv says so)."))]


def _abort_on_failure(chunks: Iterator[bytes], slug: str, file: str) -> Iterator[bytes]:
    """``chunks``, and if they fail part way, a logged error and the exception passed on: the server then drops
    the connection without the body's last chunk, so the client sees an incomplete transfer (curl: exit 18,
    browsers: a failed download), never a 200 that ends cleanly on a truncated file."""
    sent = 0
    try:
        for chunk in chunks:
            sent += len(chunk)
            yield chunk
    except Exception:
        log.exception("export %s of study %s failed after %d bytes were sent: the download is aborted", file, slug,
                      sent)
        raise


def _attachment(filename: str) -> dict[str, str]:
    return {"Content-Disposition": f'attachment; filename="{filename}"', **_NO_STORE}


@router.get("/studies/{slug}/export.zip", response_class=StreamingResponse,
            responses={200: {"content": {"application/zip": {}},
                             "description": "A zip of every file and manifest.json"}})
def export_zip(slug: str, services: ServicesDep, session: SessionDep,
               include_preview: IncludePreview = False, pseudonymise: Pseudonymise = False) -> StreamingResponse:
    """Every export file plus ``manifest.json`` (rows, bytes and SHA-256 of each), streamed as one zip.

    The audit log gets a line when the download starts and one with the row counts when it completes.
    """
    target = export.export_target(session, slug, include_preview=include_preview, pseudonymise=pseudonymise)
    audit(session, AuditAction.STUDY_EXPORT, study_id=target.study_id, file="export.zip",
          include_preview=include_preview, pseudonymise=pseudonymise)
    factory = services.database

    def done(manifest: dict[str, Any]) -> None:
        try:
            export.record_export(factory, target, "export.zip", completed=True,
                                 rows={name: f["rows"] for name, f in manifest["files"].items()},
                                 sha256={name: f["sha256"] for name, f in manifest["files"].items()})
        except SQLAlchemyError:  # every byte is sent; the start of the download is audited already
            log.exception("could not record the completed export of study %s", target.slug)

    return StreamingResponse(_abort_on_failure(export.iter_zip(factory, target, on_done=done), target.slug,
                                               "export.zip"),
                             media_type="application/zip",
                             headers=_attachment(f"{target.slug}-export.zip"))


# Before export/{name}, which would take psych-ds.zip for an unknown file name.
@router.get(f"/studies/{{slug}}/export/{ZIP_NAME}", response_class=StreamingResponse,
            responses={200: {"content": {"application/zip": {}},
                             "description": "The study's data as a Psych-DS 1.5 dataset, zipped"}})
def export_psychds_zip(slug: str, services: ServicesDep, session: SessionDep, include_preview: IncludePreview = False,
                       pseudonymise: Pseudonymise = False) -> StreamingResponse:
    """The data as a Psych-DS 1.5 dataset (``dataset_description.json``, the CSV files under ``data/`` with keyword
    names and a sidecar each, the codebook, the configuration versions and the fitted models), streamed as one zip
    whose root is the dataset's root.

    The audit log gets a line when the download starts and one with the row counts when it completes.
    """
    target = export.export_target(session, slug, include_preview=include_preview, pseudonymise=pseudonymise)
    audit(session, AuditAction.STUDY_EXPORT, study_id=target.study_id, file=ZIP_NAME, include_preview=include_preview,
          pseudonymise=pseudonymise)
    factory = services.database

    def done(rows: dict[str, int]) -> None:
        try:
            export.record_export(factory, target, ZIP_NAME, completed=True, rows=rows)
        except SQLAlchemyError:  # every byte is sent; the start of the download is audited already
            log.exception("could not record the completed Psych-DS export of study %s", target.slug)

    return StreamingResponse(_abort_on_failure(iter_psychds_zip(factory, target, on_done=done), target.slug, ZIP_NAME),
                             media_type="application/zip", headers=_attachment(f"{target.slug}-{ZIP_NAME}"))


@router.get("/studies/{slug}/export/{name}", response_class=StreamingResponse,
            responses={200: {"content": {"text/csv": {}}, "description": "The file, streamed (UTF-8, one header row)"}})
def export_file(slug: str, name: ExportFile, services: ServicesDep, session: SessionDep,
                include_preview: IncludePreview = False, pseudonymise: Pseudonymise = False) -> StreamingResponse:
    """One export file (``trials.csv``, ``surveys.csv``, ``participants.csv``, ``events.csv``, ``codebook.csv``).

    Columns, types and units are described in ``codebook.csv``.
    """
    target = export.export_target(session, slug, include_preview=include_preview, pseudonymise=pseudonymise)
    audit(session, AuditAction.STUDY_EXPORT, study_id=target.study_id, file=name.value,
          include_preview=include_preview, pseudonymise=pseudonymise)
    # The request's session is closed before the body streams: the stream opens its own (one per page).
    chunks = _abort_on_failure(export.iter_csv(services.database, target, name.value), target.slug, name.value)
    return StreamingResponse(chunks, media_type=export.CSV_MEDIA_TYPE,
                             headers=_attachment(f"{target.slug}-{name.value}"))
