"""The browser pages: plain HTML files from ``static/`` (no templating, no build step).

The participant pages only render what the participant API says (``GET /api/p/{token}/state``)
and the experimenter's dashboard what the admin API says, so these handlers just serve files.
A participant's token or recruitment parameters stay in the URL and are read by the page's
script (the admin token only in the tab's sessionStorage); the headers keep them from leaking
(no referrer, no caching) and forbid any request to another origin.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from experiment.report.html import content_security_policy as report_policy
from server.bodies import StrictJsonRoute

router = APIRouter(route_class=StrictJsonRoute, tags=["pages"], include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"


def _directive(policy: str, name: str) -> str:
    """The sources of one directive of a Content-Security-Policy."""
    parts = (part.strip() for part in policy.split(";"))
    return next(part.removeprefix(name).strip() for part in parts if part.startswith(name + " "))


#: Same-origin only: scripts, styles, fetch/websocket and the 3D view's iframe.
PAGE_HEADERS = {
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Content-Security-Policy": ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
                                "connect-src 'self'; frame-src 'self'; media-src 'self'; object-src 'none'; "
                                "base-uri 'none'; form-action 'self'; frame-ancestors 'self'"),
}


#: The dashboard opens the HTML report from a Blob URL, and a Blob URL's page inherits the policy of the page
#: that made it: so the dashboard also allows the report's one inline style sheet (by its hash, nothing else).
ADMIN_PAGE_HEADERS = {**PAGE_HEADERS, "Content-Security-Policy": PAGE_HEADERS["Content-Security-Policy"].replace(
    "style-src 'self'", "style-src 'self' " + _directive(report_policy(), "style-src"))}


def _page(name: str, headers: dict[str, str] = PAGE_HEADERS) -> FileResponse:
    return FileResponse(STATIC_DIR / name, media_type="text/html; charset=utf-8", headers=headers)


@router.get("/join/{slug}")
def join_page(slug: str) -> FileResponse:
    """Joins the study (recruitment parameters such as ``PROLIFIC_PID`` come in the query) and goes to ``/p/{token}``."""
    return _page("join.html")


@router.get("/p/{token}")
def participant_page(token: str) -> FileResponse:
    """The participant's page for every step of the session; it renders ``GET /api/p/{token}/state``."""
    return _page("participant.html")


@router.get("/admin")
def admin_page() -> FileResponse:
    """The experimenter's dashboard; it logs in with the admin token and works on the admin API."""
    return _page("admin.html", ADMIN_PAGE_HEADERS)


def static_files() -> StaticFiles:
    """``/static``: the pages' scripts and styles."""
    return StaticFiles(directory=STATIC_DIR)
