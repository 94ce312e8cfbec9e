"""Admin API: the analysis report of a study, as a zip or as one self-contained HTML page.

Both export the study, fit the trust model and draw the figures (a few
seconds): the handlers are sync functions, so FastAPI runs them in its
thread pool, and they take no request-long database session (``SessionDep``):
participants' requests must not wait for a report.

The page's address is stable (a tab can reload it, an experimenter can
bookmark it): besides the bearer token it accepts the report-reading cookie
that ``POST /api/admin/report-access`` sets (see ``server.services.report``).
A browser that opens it without access, or for a study with nothing to
report yet, gets the reason as a small HTML page rather than JSON.
"""

from __future__ import annotations

import tempfile
from datetime import UTC, datetime
from html import escape
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Cookie, Depends, Query, Request, Response
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.security import HTTPAuthorizationCredentials
from starlette.background import BackgroundTask

from experiment.report.html import STYLE, content_security_policy
from server.bodies import StrictJsonRoute
from server.deps import AdminDep, ServicesDep, UnitsDep, admin_bearer
from server.errors import AppError, Unauthorized
from server.schemas import ReportAccessRead, error_responses
from server.services import admin as admin_service
from server.services import report as reports

router = APIRouter(route_class=StrictJsonRoute, prefix="/api/admin", tags=["admin"])

Restarts = Annotated[int, Query(ge=1, le=200, description="Random restarts of the model fit.")]
Seed = Annotated[int, Query(ge=0, le=2**63 - 1, description="Seed of the fit's restarts.")]
FittedModelId = Annotated[int | None, Query(ge=1, le=2**31 - 1, description=(
    "Report this fitted model of the study (GET .../models) instead of fitting one. A model of 3 or 4 trust states "
    "is reported too: its parameters, reliance by state, transitions and where on the belief simplex the robot asks. "
    "A model chosen by comparing numbers of trust states adds the section 'Which model the data support'; one fitted "
    "with trust ratings says what the ratings add."))]
IncludePreview = Annotated[bool, Query(description=(
    "Include the experimenter's preview sessions (left out by default: they are not data)."))]
_RESPONSES = error_responses(401, 404, 409)
_RESPONSES[409] = {**_RESPONSES[409], "description": "The study has no trials to analyse yet (the reason says why)"}
_PAGE_HEADERS = {"Content-Security-Policy": content_security_policy(), "Cache-Control": "no-store",
                 "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer"}


@router.post("/report-access", response_model=ReportAccessRead, responses=error_responses(401))
async def report_access(request: Request, response: Response, units: UnitsDep,
                        credentials: Annotated[HTTPAuthorizationCredentials | None,
                                               Depends(admin_bearer)]) -> ReportAccessRead:
    """Let this browser open report pages by their address for a while: sets an HttpOnly, SameSite=Strict cookie
    that authorises ``GET .../report.html`` only (every other admin request still needs the bearer token)."""
    token = credentials.credentials.strip() if credentials else None

    def grant(session):
        admin_service.verify_admin(session, token)
        assert token is not None
        return reports.grant_report_access(session, token)

    value, expires = await units.run(grant)
    response.set_cookie(reports.REPORT_COOKIE, value, max_age=reports.REPORT_ACCESS_S, path=reports.REPORT_COOKIE_PATH,
                        httponly=True, samesite="strict", secure=request.url.scheme == "https")
    response.headers["Cache-Control"] = "no-store"
    return ReportAccessRead(path=reports.REPORT_COOKIE_PATH, expires_at=datetime.fromtimestamp(expires, UTC))


async def report_reader(units: UnitsDep,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(admin_bearer)],
                        access: Annotated[str | None,
                                          Cookie(alias=reports.REPORT_COOKIE, include_in_schema=False)] = None,
                        ) -> Unauthorized | None:
    """The admin bearer token, or else the report-reading cookie; returns the refusal (the page renders it)."""
    token = credentials.credentials.strip() if credentials else None
    try:
        if token:
            await units.run(lambda session: admin_service.verify_admin(session, token))
        else:
            await units.run(lambda session: reports.verify_report_access(session, access))
    except Unauthorized as refusal:
        return refusal
    return None


@router.get("/studies/{slug}/report", response_class=FileResponse, dependencies=[AdminDep],
            responses={200: {"content": {"application/zip": {}},
                             "description": "report.html, figures/*.png, report.json, model.json and data/ "
                                            "(the export)"},
                       **_RESPONSES})
def report_zip(slug: str, services: ServicesDep, restarts: Restarts = 20, seed: Seed = 0,
               include_preview: IncludePreview = False, model: FittedModelId = None) -> FileResponse:
    """The analysis report (paper §4–§5 for this study's data) as a zip, with the data it was made from."""
    reports.start_report(services.database, slug)
    workdir = Path(tempfile.mkdtemp(prefix="trustlab-report-"))
    try:
        archive = reports.report_zip(services.database, slug, workdir, restarts=restarts, seed=seed,
                                     include_preview=include_preview, model_id=model)
    except BaseException:
        reports.remove(workdir)
        raise
    return FileResponse(archive, media_type="application/zip", filename=archive.name,
                        headers={"Cache-Control": "no-store"}, background=BackgroundTask(reports.remove, workdir))


# No response_class=HTMLResponse: it would document the JSON error responses as text/html too.
@router.get("/studies/{slug}/report.html",
            responses={200: {"content": {"text/html": {"schema": {"type": "string"}}},
                             "description": "One page, figures inlined as data: URIs"}, **_RESPONSES})
def report_page(slug: str, request: Request, services: ServicesDep,
                refusal: Annotated[Unauthorized | None, Depends(report_reader)],
                restarts: Restarts = 20, seed: Seed = 0, include_preview: IncludePreview = False,
                model: FittedModelId = None) -> HTMLResponse:
    """The analysis report as one self-contained HTML page that a browser can open as it is, at this address.

    Authorised by the admin bearer token or by the cookie of ``POST /api/admin/report-access``. Errors are JSON,
    or a short HTML page for a browser (a request that accepts text/html)."""
    try:
        if refusal is not None:
            raise refusal
        reports.start_report(services.database, slug)
        with tempfile.TemporaryDirectory(prefix="trustlab-report-") as workdir:
            page = reports.study_report(services.database, slug, Path(workdir), restarts=restarts, seed=seed,
                                        include_preview=include_preview, model_id=model).inline_html()
    except AppError as exc:
        if "text/html" not in request.headers.get("accept", ""):
            raise
        return HTMLResponse(_error_page(slug, exc), status_code=exc.status_code, headers=_PAGE_HEADERS)
    return HTMLResponse(page,
                        headers={**_PAGE_HEADERS, "Content-Disposition": f'inline; filename="{slug}-report.html"'})


def _error_page(slug: str, exc: AppError) -> str:
    reason = exc.detail[0].upper() + exc.detail[1:] if exc.detail else "The report cannot be shown"
    return (f"<!doctype html><html lang=en><head><meta charset=utf-8><title>Report of {escape(slug)}: not available"
            f"</title><meta name=viewport content='width=device-width,initial-scale=1'><style>{STYLE}</style></head>"
            f"<body><h1>Analysis report of study {escape(slug)}</h1><p>{escape(reason)}.</p>"
            "<p><a href='/admin'>Open the admin page</a></p></body></html>")
