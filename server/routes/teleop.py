"""The teleoperation socket ``/api/p/{token}/teleop``: a thin loop around ``services.teleop.TeleopChannel``.

The messages are the typed models of ``server.teleop_messages`` (JSON Schema at ``/api/schema/teleop.json``).
The handler answers client messages while a task pushes the world at most ``teleop_world_hz`` a second;
whichever sees the teleoperation end sends ``over`` and closes the socket.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse
from starlette.websockets import WebSocketState

from server.app_services import services_of
from server.bodies import StrictJsonRoute
from server.errors import AppError
from server.services.teleop import TeleopChannel
from server.socket_guard import CLOSE_POLICY, origin_allowed
from server.teleop_messages import AckMessage, json_schema

router = APIRouter(route_class=StrictJsonRoute, tags=["participant"])

CLOSE_UNKNOWN_TOKEN = 4404
CLOSE_OVER = 1000
CLOSE_INTERNAL = 1011
BINARY_REFUSED = "binary frames are not part of this protocol: send each message as JSON text"


@router.get("/api/schema/teleop.json", summary="JSON Schema of the teleoperation socket's messages")
def teleop_schema() -> JSONResponse:
    """Every message of ``/api/p/{token}/teleop`` in both directions (``client_to_server``, ``server_to_client``)."""
    return JSONResponse(json_schema())


@router.websocket("/api/p/{token}/teleop")
async def teleop_socket(websocket: WebSocket, token: str) -> None:
    services = services_of(websocket.app)
    if not origin_allowed(websocket, services.settings):
        await websocket.close(code=CLOSE_POLICY)  # before accepting: the browser gets a 403
        return
    await websocket.accept()
    channel = TeleopChannel(services, token)
    try:
        hello = await channel.open()
    except AppError as exc:
        await websocket.close(code=CLOSE_UNKNOWN_TOKEN, reason=exc.detail[:120])
        return
    sending = asyncio.Lock()

    async def send(messages: list[Any]) -> None:
        async with sending:
            if websocket.application_state != WebSocketState.CONNECTED:
                return
            for message in messages:
                await websocket.send_text(message.model_dump_json())
            if channel.finished:  # after ``over``
                await websocket.close(code=CLOSE_OVER)

    async def push() -> None:
        with contextlib.suppress(WebSocketDisconnect):  # the client left between two pushes: the loop below ends too
            await channel.push_forever(send)

    await send([hello])
    pusher = asyncio.create_task(push())
    try:
        while websocket.application_state == WebSocketState.CONNECTED:
            frame = await websocket.receive()
            if frame["type"] == "websocket.disconnect":
                break
            if frame.get("text") is None:  # a binary frame
                await send([AckMessage(seq=None, ok=False, error=BINARY_REFUSED)])
                continue
            await send(await channel.receive(frame["text"]))
    except WebSocketDisconnect:
        pass
    except Exception as exc:  # noqa: BLE001 -- a failure here is this participant's alone: logged, socket closed
        services.faults.record("teleop_socket", exc, participant=channel.participant_key)
        with contextlib.suppress(Exception):
            await websocket.close(code=CLOSE_INTERNAL, reason="the server could not handle a message; reconnect")
    finally:
        pusher.cancel()
        await channel.close()
