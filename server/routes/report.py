"""Admin API: the analysis report of a study, as a zip or as one self-contained HTML page.

Both export the study, fit the trust model and draw the figures (a few
seconds): the handlers are sync functions, so FastAPI runs them in its
thread pool, and they take no request-long database session (``SessionDep``):
participants' requests must not wait for a report.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, HTMLResponse
from starlette.background import BackgroundTask

from experiment.report.html import content_security_policy
from server.deps import AdminDep
from server.schemas import error_responses
from server.services import report as reports

router = APIRouter(prefix="/api/admin", tags=["admin"], dependencies=[AdminDep])

Restarts = Annotated[int, Query(ge=1, le=200, description="Random restarts of the model fit.")]
Seed = Annotated[int, Query(ge=0, le=2**63 - 1, description="Seed of the fit's restarts.")]
_RESPONSES = error_responses(404, 409)
_RESPONSES[409] = {**_RESPONSES[409], "description": "The study has no trials to analyse yet (the reason says why)"}


@router.get("/studies/{slug}/report", response_class=FileResponse,
            responses={200: {"content": {"application/zip": {}},
                             "description": "report.html, figures/*.png, report.json, model.json and data/ (the export)"},
                       **_RESPONSES})
def report_zip(slug: str, request: Request, restarts: Restarts = 20, seed: Seed = 0) -> FileResponse:
    """The analysis report (paper §4–§5 for this study's data) as a zip, with the data it was made from."""
    reports.start_report(request.app.state.sessionmaker, slug)
    workdir = Path(tempfile.mkdtemp(prefix="trustlab-report-"))
    try:
        archive = reports.report_zip(request.app.state.sessionmaker, slug, workdir, restarts=restarts, seed=seed)
    except BaseException:
        reports.remove(workdir)
        raise
    return FileResponse(archive, media_type="application/zip", filename=archive.name,
                        headers={"Cache-Control": "no-store"}, background=BackgroundTask(reports.remove, workdir))


# No response_class=HTMLResponse: it would document the JSON error responses as text/html too.
@router.get("/studies/{slug}/report.html",
            responses={200: {"content": {"text/html": {"schema": {"type": "string"}}},
                             "description": "One page, figures inlined as data: URIs"}, **_RESPONSES})
def report_page(slug: str, request: Request, restarts: Restarts = 20, seed: Seed = 0) -> HTMLResponse:
    """The analysis report as one self-contained HTML page that a browser can open as it is."""
    reports.start_report(request.app.state.sessionmaker, slug)
    with tempfile.TemporaryDirectory(prefix="trustlab-report-") as workdir:
        page = reports.study_report(request.app.state.sessionmaker, slug, Path(workdir), restarts=restarts,
                                    seed=seed).inline_html()
    return HTMLResponse(page, headers={"Content-Security-Policy": content_security_policy(), "Cache-Control": "no-store",
                                       "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
                                       "Content-Disposition": f'inline; filename="{slug}-report.html"'})
