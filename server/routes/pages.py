"""The participant's browser pages: plain HTML files from ``static/`` (no templating, no build step).

The pages only render what the participant API says (``GET /api/p/{token}/state``), so
these handlers just serve files. The token or the recruitment parameters stay in the URL and
are read by the page's script; the headers keep them from leaking (no referrer, no caching)
and forbid any request to another origin.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

router = APIRouter(tags=["pages"], include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"

#: Same-origin only: scripts, styles, fetch/websocket and the 3D view's iframe.
PAGE_HEADERS = {
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Content-Security-Policy": ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
                                "connect-src 'self'; frame-src 'self'; media-src 'self'; object-src 'none'; "
                                "base-uri 'none'; form-action 'self'; frame-ancestors 'self'"),
}


def _page(name: str) -> FileResponse:
    return FileResponse(STATIC_DIR / name, media_type="text/html; charset=utf-8", headers=PAGE_HEADERS)


@router.get("/join/{slug}")
def join_page(slug: str) -> FileResponse:
    """Joins the study (recruitment parameters such as ``PROLIFIC_PID`` come in the query) and goes to ``/p/{token}``."""
    return _page("join.html")


@router.get("/p/{token}")
def participant_page(token: str) -> FileResponse:
    """The participant's page for every step of the session; it renders ``GET /api/p/{token}/state``."""
    return _page("participant.html")


def static_files() -> StaticFiles:
    """``/static``: the pages' scripts and styles."""
    return StaticFiles(directory=STATIC_DIR)
