"""The participant's 3D view through the app's own origin.

- ``GET /viewer/{token}/``: viser's web client (one self-contained
  ``index.html`` from the installed package; it makes no other request). With
  no ``?websocket=`` it connects to the page URL minus the trailing slash:
- ``WS /viewer/{token}``: accepts the ``viser-v<version>`` subprotocol and
  writes, in viser's wire format, what viser's own server would: the replay of
  the session's scene (``server.viewer.scene``), then the scene's changes and
  what moves (``server.viewer.live``: one frame per world tick). What the
  client sends (its camera as the participant turns it) is read and dropped:
  the camera presets are the server's. Close codes: 4404 unknown or finished
  session; 1002 missing or wrong client version, as viser itself does; 1012
  the session's view stopped (its viewers had gone) or moved, reconnect.
- ``POST /api/p/{token}/camera`` ``{"view": "world" | "local" | "end_effector"}``:
  moves the camera of the session's viewers (and later ones) and logs a
  ``camera`` event.

The participant page embeds the view as ``<iframe src="/viewer/{token}/">``.
"""

from __future__ import annotations

import contextlib
import functools
import gzip
from pathlib import Path

import anyio
import viser
from fastapi import APIRouter, Request, Response, WebSocket
from fastapi.responses import RedirectResponse
from starlette.websockets import WebSocketDisconnect, WebSocketState

from experiment.events import EventKind
from server.app_services import services_of
from server.bodies import StrictJsonRoute
from server.deps import ParticipantContext, Token, UnitsDep
from server.errors import AppError
from server.schemas import CameraRead, CameraUpdate, error_responses
from server.services import sessions
from server.services.audit import log_event
from server.socket_guard import CLOSE_POLICY, FrameBudget, origin_allowed
from server.viewer.live import ViewerSink
from server.viewer.manager import SessionViews, ViewerManager

router = APIRouter(route_class=StrictJsonRoute, tags=["viewer"])

SUBPROTOCOL = f"viser-v{viser.__version__}"
CLOSE_UNKNOWN_TOKEN = 4404
CLOSE_PROTOCOL = 1002
CLOSE_RESTART = 1012
#: A 3D view's client may send this many seconds' worth of its message allowance at once.
VIEWER_BURST_SECONDS = 2.0
CLIENT_HTML = Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
#: Shown in the page title and hides viser's control panel (participants get the page's own controls).
HEAD_EXTRA = """<title>Robot view</title>
<style>
  /* viser's control panel and its toasts are not for participants (the page has its own controls) */
  [data-testid="floating-panel"], .mantine-Notifications-root { display: none !important; }
</style>
"""


@functools.lru_cache(maxsize=1)
def client_html() -> tuple[bytes, bytes]:
    """viser's client page (plain, gzipped), with our title and style."""
    html = CLIENT_HTML.read_text(encoding="utf-8")
    html = html.replace("<title>Viser</title>", "", 1).replace("</head>", HEAD_EXTRA + "</head>", 1)
    raw = html.encode()
    return raw, gzip.compress(raw, compresslevel=6, mtime=0)


def _manager(app) -> SessionViews:
    return services_of(app).viewers


@router.get("/viewer/{token}/", include_in_schema=False)
async def viewer_page(token: str, request: Request) -> Response:
    await _manager(request.app).lookup(token)  # AppError -> 404/409/410
    raw, packed = client_html()
    # no-store: the URL holds the session token, which no cache (shared or the browser's disk) may keep
    headers = {"Cache-Control": "no-store", "Referrer-Policy": "no-referrer",
               "X-Content-Type-Options": "nosniff", "Vary": "Accept-Encoding",
               "Content-Security-Policy": "frame-ancestors 'self'"}
    if "gzip" in request.headers.get("accept-encoding", ""):
        return Response(packed, media_type="text/html; charset=utf-8", headers=headers | {"Content-Encoding": "gzip"})
    return Response(raw, media_type="text/html; charset=utf-8", headers=headers)


@router.get("/viewer/{token}", include_in_schema=False)
async def viewer_page_redirect(token: str, request: Request) -> RedirectResponse:
    await _manager(request.app).lookup(token)  # an unknown link is refused here too, not redirected
    query = request.url.query
    return RedirectResponse(f"{token}/" + (f"?{query}" if query else ""), status_code=307)


@router.websocket("/viewer/{token}")
async def viewer_socket(websocket: WebSocket, token: str) -> None:
    settings = services_of(websocket.app).settings
    if not origin_allowed(websocket, settings):
        await websocket.close(code=CLOSE_POLICY)  # before accepting: the browser gets a 403
        return
    offered = [p for p in websocket.scope.get("subprotocols", []) if p.startswith("viser-v")]
    chosen = offered[0] if offered else None
    await websocket.accept(subprotocol=chosen)
    if chosen != SUBPROTOCOL:
        client = chosen[len("viser-v"):] if chosen else "unknown"
        await _close(websocket, CLOSE_PROTOCOL, f"Version mismatch. Client: {client}, Server: {viser.__version__}")
        return
    manager = _manager(websocket.app)
    if not isinstance(manager, ViewerManager):  # the view process serves the views; it missed this socket
        await _close(websocket, CLOSE_RESTART, "the 3D view is served by another process; reconnect")
        return
    try:
        vs, sink = await manager.open(token)
    except AppError as exc:
        await _close(websocket, CLOSE_UNKNOWN_TOKEN, exc.detail[:120])
        return
    try:
        budget = FrameBudget(settings.viewer_message_rate_hz, VIEWER_BURST_SECONDS * settings.viewer_message_rate_hz)
        server_ended = await _serve(websocket, sink, budget)
    finally:
        manager.release(vs, sink)
    if server_ended:
        if vs.finished:
            await _close(websocket, CLOSE_UNKNOWN_TOKEN, "this session is finished")
        else:
            await _close(websocket, CLOSE_RESTART, "the 3D view restarted; reconnect")


async def _serve(websocket: WebSocket, sink: ViewerSink, budget: FrameBudget) -> bool:
    """Write what ``sink`` gives and drop what the browser sends, until either side ends; True if the sink did (the
    session's view stopped). A browser that sends more than its ``budget`` is closed (1008)."""
    ended: list[str] = []

    async def from_browser(scope: anyio.CancelScope) -> None:
        try:
            while (await websocket.receive())["type"] != "websocket.disconnect":
                if not budget.take():
                    await _close(websocket, CLOSE_POLICY, "too many messages")
                    break
        except (RuntimeError, OSError, WebSocketDisconnect):
            pass
        ended.append("browser")
        scope.cancel()

    async def to_browser(scope: anyio.CancelScope) -> None:
        try:
            while (data := await sink.next()) is not None:
                await websocket.send_bytes(data)
            ended.append("server")
        except (RuntimeError, OSError, WebSocketDisconnect):
            ended.append("browser")
        scope.cancel()

    # anyio (not bare asyncio tasks): the ASGI server cancels this handler through an anyio cancel scope
    # when the browser leaves, and only anyio's task group hands that cancellation back to it intact.
    async with anyio.create_task_group() as group:
        group.start_soon(from_browser, group.cancel_scope)
        group.start_soon(to_browser, group.cancel_scope)
    return ended[:1] == ["server"]


async def _close(websocket: WebSocket, code: int, reason: str) -> None:
    """Close if still open (Starlette raises when the browser is already gone)."""
    if websocket.application_state == WebSocketState.DISCONNECTED:
        return
    with contextlib.suppress(RuntimeError, WebSocketDisconnect, OSError):
        await websocket.close(code=code, reason=reason)


@router.post("/api/p/{token}/camera", response_model=CameraRead, tags=["participant"],
             responses=error_responses(404, 409, 410))
async def set_camera(body: CameraUpdate, token: Token, units: UnitsDep) -> CameraRead:
    """Switch the session's 3D view to a camera preset (world, local = gripper area, end effector)."""
    def act(ctx: ParticipantContext) -> CameraRead:
        sessions.require_active(ctx.participant)
        viewers = units.services.viewers.set_view(ctx.participant.id, body.view)
        log_event(ctx.session, ctx.study.id, ctx.participant.id, EventKind.CAMERA, client_time_ms=body.client_time_ms,
                  view=body.view, viewers=viewers)
        return CameraRead(view=body.view, viewers=viewers)
    return await units.participant(token, act)

