"""The browser pages: plain HTML files from ``static/`` (no templating, no build step).

The participant pages only render what the participant API says (``GET /api/p/{token}/state``)
and the experimenter's dashboard what the admin API says, so these handlers just serve files.
A participant's token or recruitment parameters stay in the URL and are read by the page's
script (the admin token only in the tab's sessionStorage); the headers keep them from leaking
(no referrer, no caching) and forbid any request to another origin.

Pages are served only here, with those headers: ``/static`` serves the pages' scripts, styles and vendored
libraries but no HTML (``/static/admin.html`` would be the dashboard without its policy). The API docs
(``/docs``) are Swagger UI from ``static/vendor/swagger-ui`` (no CDN), under a policy that allows their one
inline script by its hash; ``api_docs = false`` turns them off.
"""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException
from starlette.types import Scope

from experiment.report.html import content_security_policy as report_policy
from server.app_services import services_of
from server.bodies import StrictJsonRoute
from server.http_headers import PAGE_HEADERS

router = APIRouter(route_class=StrictJsonRoute, tags=["pages"], include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"


def _directive(policy: str, name: str) -> str:
    """The sources of one directive of a Content-Security-Policy."""
    parts = (part.strip() for part in policy.split(";"))
    return next(part.removeprefix(name).strip() for part in parts if part.startswith(name + " "))




#: The dashboard opens the HTML report from a Blob URL, and a Blob URL's page inherits the policy of the page
#: that made it: so the dashboard also allows the report's one inline style sheet (by its hash, nothing else).
ADMIN_PAGE_HEADERS = {**PAGE_HEADERS, "Content-Security-Policy": PAGE_HEADERS["Content-Security-Policy"].replace(
    "style-src 'self'", "style-src 'self' " + _directive(report_policy(), "style-src"))}


def _page(name: str, headers: dict[str, str] = PAGE_HEADERS) -> FileResponse:
    return FileResponse(STATIC_DIR / name, media_type="text/html; charset=utf-8", headers=headers)


@router.get("/join/{slug}")
def join_page(slug: str) -> FileResponse:
    """Joins the study (recruitment parameters such as ``PROLIFIC_PID`` come in the query) and goes to
    ``/p/{token}``."""
    return _page("join.html")


@router.get("/p/{token}")
def participant_page(token: str) -> FileResponse:
    """The participant's page for every step of the session; it renders ``GET /api/p/{token}/state``."""
    return _page("participant.html")


@router.get("/admin")
def admin_page() -> FileResponse:
    """The experimenter's dashboard; it logs in with the admin token and works on the admin API."""
    return _page("admin.html", ADMIN_PAGE_HEADERS)


@router.get("/docs")
def api_docs(request: Request) -> HTMLResponse:
    """Swagger UI for ``/openapi.json``, from the vendored ``swagger-ui-dist`` (pinned: static/vendor/swagger-ui)."""
    if not services_of(request.app).settings.api_docs:
        raise HTTPException(404, "Not Found")
    page = get_swagger_ui_html(openapi_url=request.app.openapi_url, title="trustlab API",
                               swagger_js_url="/static/vendor/swagger-ui/swagger-ui-bundle.js",
                               swagger_css_url="/static/vendor/swagger-ui/swagger-ui.css",
                               swagger_favicon_url="data:,",
                               swagger_ui_parameters={"validatorUrl": None})  # else a badge from swagger.io
    body = bytes(page.body)
    return HTMLResponse(body, headers=docs_headers(body.decode()))


def docs_headers(html: str) -> dict[str, str]:
    """The page headers for Swagger UI: its inline start-up script allowed by hash, and the style attributes its
    widgets set (styles run no code)."""
    hashes = " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(script.encode()).digest()).decode()}'"
                      for script in re.findall(r"<script>(.*?)</script>", html, flags=re.DOTALL))
    policy = PAGE_HEADERS["Content-Security-Policy"].replace("script-src 'self'", f"script-src 'self' {hashes}")
    return {**PAGE_HEADERS, "Content-Security-Policy": policy.replace("style-src 'self'",
                                                                      "style-src 'self' 'unsafe-inline'")}


class ScriptsAndStyles(StaticFiles):
    """``static/`` without its HTML files: a page is served by its route, with the page headers."""

    async def get_response(self, path: str, scope: Scope):
        if path.lower().endswith((".html", ".htm")):
            raise HTTPException(404, "Not Found: pages are served at their own address (/admin, /join/..., /p/...)")
        response = await super().get_response(path, scope)
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        return response


def static_files() -> StaticFiles:
    """``/static``: the pages' scripts and styles and the vendored libraries (no HTML)."""
    return ScriptsAndStyles(directory=STATIC_DIR)
