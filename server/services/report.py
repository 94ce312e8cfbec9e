"""The analysis report of a study (``experiment.report``) from the database: export, then build.

The study is exported with ``server.export.export_study`` into a
working directory and the report is built from those files, so the report
always reads exactly what an export contains. The study's current
configuration supplies the task (success probabilities, rewards).

The report page has a stable address, ``/api/admin/studies/{slug}/report.html``,
that a browser tab can open, reload and bookmark. A tab cannot send the admin
page's bearer header, so the admin page first exchanges its token for a
report-reading cookie (``grant_report_access``): HttpOnly (page scripts cannot
read it), SameSite=Strict (no other site can make the browser send it),
scoped to ``/api/admin/studies/``, valid for ``REPORT_ACCESS_S``, and good
for reading report pages only (every other admin request still needs the
bearer token). Its value is an expiry and an HMAC, under a server secret, of
that expiry and the hash of the admin token that asked: rotating the admin
token revokes it.
"""

from __future__ import annotations

import hmac
import json
import shutil
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig
from experiment.records import DataError
from experiment.report import Report, build_report
from server.db.units import SessionFactory
from server.errors import Conflict, NotFound, Unauthorized
from server.export import export_study
from server.models import AdminCredential, AuditAction, Study
from server.services import fits
from server.services.audit import audit
from server.services.sessions import app_secret, hash_token
from server.services.studies import current_version, get_study

DATA_DIR = "data"
#: The report-reading cookie: its name, path and lifetime (a working day; the admin page renews it).
REPORT_COOKIE = "trustlab_report_access"
REPORT_COOKIE_PATH = "/api/admin/studies/"
REPORT_ACCESS_S = 12 * 3600
_KEY = "report_access_key"


def grant_report_access(session: Session, admin_token: str, now_s: float | None = None) -> tuple[str, int]:
    """A report-reading cookie value for a verified admin token, and its expiry (Unix seconds)."""
    expires = int(now_s if now_s is not None else time.time()) + REPORT_ACCESS_S
    return f"{expires}.{_signature(session, expires, hash_token(admin_token))}", expires


def verify_report_access(session: Session, cookie: str | None, now_s: float | None = None) -> None:
    """Raise Unauthorized unless ``cookie`` is an unexpired report-reading cookie of an active admin token."""
    reason = "this browser may not open reports yet: sign in on the admin page (/admin), then reload this page"
    expires_text, _, signature = (cookie or "").partition(".")
    if not expires_text.isdigit() or not signature:
        raise Unauthorized(reason)
    expires = int(expires_text)
    if expires < (now_s if now_s is not None else time.time()):
        raise Unauthorized("the report access of this browser expired: open the admin page (/admin) and sign in "
                           "again, then reload this page")
    hashes = session.scalars(select(AdminCredential.token_hash).where(AdminCredential.active.is_(True))).all()
    if not any(hmac.compare_digest(signature, _signature(session, expires, h)) for h in hashes):
        raise Unauthorized(reason)


def _signature(session: Session, expires: int, token_hash: str) -> str:
    return hmac.new(app_secret(session, _KEY), f"{expires}:{token_hash}".encode(), "sha256").hexdigest()


def start_report(factory: SessionFactory, slug: str) -> None:
    """Check the study exists (404 otherwise) and audit the request, in a transaction of its own.

    The export and the fit that follow take seconds and open their own short
    transactions: on SQLite every transaction holds the write lock, so no
    transaction may stay open around them.
    """
    with factory.begin() as session:
        study = get_study(session, slug)
        audit(session, AuditAction.STUDY_REPORT, study_id=study.id)


def study_report(factory: SessionFactory, slug: str, workdir: Path, *, model: str | None = None,
                 restarts: int = 20, seed: int = 0, p_high: float | None = None,
                 progress: Callable[[int, int], None] | None = None, include_preview: bool = False,
                 model_id: int | None = None) -> Report:
    """Export ``slug`` into ``workdir/data`` and build its report; 404 unknown study, 409 nothing to analyse.
    Preview sessions are left out unless ``include_preview``. ``model_id``: report that fitted model of the study, of
    two to four trust states (with the comparison of numbers of trust states that chose it and the comparison with
    and without trust ratings, if any) instead of fitting one."""
    data_dir = workdir / DATA_DIR
    export_study(factory, slug, data_dir, include_preview=include_preview)
    with factory() as session:
        study = get_study(session, slug)
        config = StudyConfig.model_validate(current_version(session, study).config)
        title = f"{study.title} ({slug})" + (", preview sessions included" if include_preview else "")
        if model_id is not None:
            model = str(_fitted_model_file(session, study, model_id, workdir))
    try:
        return build_report(data_dir, model=model, restarts=restarts, seed=seed, p_high=p_high, task=config.task,
                            title=title, source=f"an export of study {slug} taken for this report", progress=progress)
    except DataError as exc:
        reason = str(exc).replace(f"{data_dir}/", "")
        raise Conflict(f"no report for study {slug!r} yet: {reason}") from None


def _fitted_model_file(session: Session, study: Study, model_id: int, workdir: Path) -> Path:
    """The document of a finished model of ``study`` (of any number of trust states), written into ``workdir`` for
    the report to read."""
    model = fits.get_model(session, model_id)
    if model.study_id != study.id:
        raise NotFound(f"study {study.slug!r} has no fitted model {model_id}")
    document = fits.model_document(model)  # 409 while it runs or when it failed
    path = workdir / f"fitted-model-{model_id}.json"
    path.write_text(json.dumps(document), encoding="utf-8")
    return path


def report_zip(factory: SessionFactory, slug: str, workdir: Path, *, restarts: int, seed: int,
               include_preview: bool = False, model_id: int | None = None) -> Path:
    """The report written into ``workdir/report`` (with the export in ``report/data``), zipped; returns the zip."""
    root = workdir / "report"
    report = study_report(factory, slug, root, restarts=restarts, seed=seed, include_preview=include_preview,
                          model_id=model_id)
    report.write(root)
    archive = workdir / f"{slug}-report.zip"
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(root.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(root).as_posix())
    return archive


def remove(workdir: Path) -> None:
    shutil.rmtree(workdir, ignore_errors=True)
