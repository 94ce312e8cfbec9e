"""The analysis report of a study (``experiment.report``) from the database: export, then build.

The study is exported with ``server.services.exports.export_study`` into a
working directory and the report is built from those files, so the report
always reads exactly what an export contains. The study's current
configuration supplies the task (success probabilities, rewards).
"""

from __future__ import annotations

import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from experiment.config import StudyConfig
from experiment.records import DataError
from experiment.report import Report, build_report
from server.errors import Conflict
from server.services.audit import audit
from server.services.exports import export_study
from server.services.studies import current_version, get_study

DATA_DIR = "data"


def start_report(factory: sessionmaker[Session], slug: str) -> None:
    """Check the study exists (404 otherwise) and audit the request, in a transaction of its own.

    The export and the fit that follow take seconds and open their own short
    transactions: on SQLite every transaction holds the write lock, so no
    transaction may stay open around them.
    """
    with factory.begin() as session:
        study = get_study(session, slug)
        audit(session, "study.report", study_id=study.id)


def study_report(factory: sessionmaker[Session], slug: str, workdir: Path, *, model: str | None = None,
                 restarts: int = 20, seed: int = 0, p_high: float | None = None,
                 progress: Callable[[int, int], None] | None = None) -> Report:
    """Export ``slug`` into ``workdir/data`` and build its report; 404 unknown study, 409 nothing to analyse."""
    data_dir = workdir / DATA_DIR
    export_study(factory, slug, data_dir)
    with factory() as session:
        study = get_study(session, slug)
        config = StudyConfig.model_validate(current_version(session, study).config)
        title = f"{study.title} ({slug})"
    try:
        return build_report(data_dir, model=model, restarts=restarts, seed=seed, p_high=p_high, task=config.task,
                            title=title, source=f"study {slug}, exported to {data_dir}", progress=progress)
    except DataError as exc:
        reason = str(exc).replace(f"{data_dir}/", "")
        raise Conflict(f"no report for study {slug!r} yet: {reason}") from None


def report_zip(factory: sessionmaker[Session], slug: str, workdir: Path, *, restarts: int, seed: int) -> Path:
    """The report written into ``workdir/report`` (with the export in ``report/data``), zipped; returns the zip."""
    root = workdir / "report"
    report = study_report(factory, slug, root, restarts=restarts, seed=seed)
    report.write(root)
    archive = workdir / f"{slug}-report.zip"
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(root.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(root).as_posix())
    return archive


def remove(workdir: Path) -> None:
    shutil.rmtree(workdir, ignore_errors=True)
