"""Teleoperation over a websocket: the page (or a bot) sends commands, the server moves the arm.

Protocol (JSON text frames):

- client → server: ``{"seq": n, "command": {"ee_velocity": [vx, vy, vz]} | {"joint_velocity": [..4]}
  (+ optional "gripper": "open"|"close"|"toggle"), "client_ms": performance.now()}``
- server → client: ``{"type": "hello", "trial": {...}, "scene": {"complexity", "seed", "target_slot"}, "world": {...}}`` on
  connect and whenever a new teleoperation begins; then one ``{"type": "ack", "seq", "ok", "events",
  "world", "trial_done"}`` per command (``"error"`` says why a command was refused). The scene seed is a
  62-bit integer sent as a decimal string (JavaScript numbers hold 53 bits).

The server decides grasp and deposit; a deposit completes the trial in the
database before the ack that says ``trial_done`` is sent. Commands are
written to the event log in batches (at most ``LOG_FLUSH_S`` apart).
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from sqlalchemy.orm import Session

from experiment.world.teleop import parse_command
from server.deps import run_unit, run_unit_here
from server.errors import AppError
from server.models import Participant, utcnow
from server.services import sessions, trials
from server.services.audit import log_event
from server.world import TeleopSession, TrialKey, WorldHub, world_state_dict

router = APIRouter(tags=["participant"])

LOG_FLUSH_S = 1.0
MAX_MESSAGE_BYTES = 4096
CLOSE_UNKNOWN_TOKEN = 4404


@router.websocket("/api/p/{token}/teleop")
async def teleop_socket(websocket: WebSocket, token: str) -> None:
    app = websocket.app
    hub: WorldHub = app.state.world
    await websocket.accept()
    try:
        current = await run_unit(app, lambda session: _load(session, app, token))
    except AppError as exc:
        await websocket.close(code=CLOSE_UNKNOWN_TOKEN, reason=exc.detail[:120])
        return
    teleop = _open(hub, current)
    await websocket.send_json(_hello(current, teleop))
    last_flush, last_check = time.monotonic(), time.monotonic()
    try:
        while True:
            raw = await websocket.receive_text()
            reply, teleop, current = await _handle(app, hub, token, raw, teleop, current)
            await websocket.send_json(reply)
            if reply.get("trial_done") or (teleop is None and time.monotonic() - last_check > 0.5):
                last_check = time.monotonic()
                current = await run_unit(app, lambda session: _load(session, app, token))
                teleop = _open(hub, current)
                if teleop is not None:
                    await websocket.send_json(_hello(current, teleop))
            if teleop is not None and time.monotonic() - last_flush > LOG_FLUSH_S:
                last_flush = time.monotonic()
                await _flush(app, token, teleop)
    except WebSocketDisconnect:
        pass
    finally:
        if teleop is not None and (batch := teleop.take_log()):
            # To the end even if this handler is cancelled or the event loop is stopping: a worker thread writes it.
            await asyncio.shield(asyncio.get_running_loop().run_in_executor(
                None, run_unit_here, app, lambda session: _log_batch(session, token, teleop, batch)))


async def _handle(app, hub: WorldHub, token: str, raw: str, teleop: TeleopSession | None,
                  current: dict[str, Any]) -> tuple[dict[str, Any], TeleopSession | None, dict[str, Any]]:
    message, error = _parse(raw)
    seq = message.get("seq") if isinstance(message, dict) else None
    if error:
        return {"type": "ack", "seq": seq, "ok": False, "error": error}, teleop, current
    if teleop is not None and not hub.is_current(teleop):
        # Ended elsewhere (another tab of the participant deposited the item, or the time limit passed):
        # a stale arm takes no more commands; what this socket logged is kept.
        await _flush(app, token, teleop)
        return ({"type": "ack", "seq": seq, "ok": False,
                 "error": "not teleoperating now (this teleoperation ended: its item was deposited or its time ran out)"},
                None, current)
    if teleop is None:
        return ({"type": "ack", "seq": seq, "ok": False,
                 "error": f"not teleoperating now (the session is at {current['describe']})"}, teleop, current)
    if not hub.allow(teleop):
        return {"type": "ack", "seq": seq, "ok": False, "error": "too many commands; slow down"}, teleop, current
    try:
        state, events = hub.command(teleop, message["command"], current["speed"])
    except ValueError as exc:
        return {"type": "ack", "seq": seq, "ok": False, "error": str(exc)}, teleop, current
    teleop.log.append([round((time.monotonic() - teleop.started) * 1000, 1), message.get("client_ms"),
                       message["command"], list(events)])
    reply = {"type": "ack", "seq": seq, "ok": True, "events": list(events), "world": world_state_dict(state),
             "trial_done": False}
    if "deposited" in events:
        elapsed_ms = (time.monotonic() - teleop.started) * 1000
        batch = teleop.take_log()
        done = await run_unit(app, lambda session: _finish(session, app, token, teleop, batch, elapsed_ms))
        hub.end_teleop(teleop.key)
        reply["trial_done"], reply["trial_recorded"] = True, done
        teleop = None
    return reply, teleop, current


def _parse(raw: str) -> tuple[Any, str | None]:
    if len(raw) > MAX_MESSAGE_BYTES:
        return {}, f"message larger than {MAX_MESSAGE_BYTES} bytes"
    try:
        message = json.loads(raw)
    except json.JSONDecodeError:
        return {}, "message is not JSON"
    if not isinstance(message, dict) or not isinstance(message.get("command"), dict):
        return message, 'message must be an object with a "command" object'
    try:
        parse_command(message["command"])
    except ValueError as exc:
        return message, str(exc)
    return message, None


def _load(session: Session, app, token: str) -> dict[str, Any]:
    """The participant's current trial, as the websocket needs it (raises AppError for a bad token)."""
    participant, _, runtime = sessions.open_session(session, app.state.runtimes, token)
    sessions.require_active(participant)
    trials.advance(session, participant, runtime, utcnow(), app.state.world)
    sessions.touch(participant)
    trial = trials.current_trial(session, participant)
    planned = trials.planned_trial(participant, runtime) if trial is not None else None
    return {"participant_key": participant.public_id, "seed": runtime.config.seed,
            "speed": runtime.config.timing.animation_speed, "describe": sessions.describe(participant.step),
            "stage": trial.stage if trial else None, "planned": planned,
            "trial": None if trial is None else {"practice": trial.practice, "block": trial.block,
                                                 "trial": trial.trial, "complexity": trial.complexity}}


def _open(hub: WorldHub, current: dict[str, Any]) -> TeleopSession | None:
    if current["stage"] != "teleop":
        return None
    t = current["trial"]
    key = TrialKey(current["participant_key"], t["practice"], t["block"], t["trial"])
    return hub.teleop(key, hub.scene(current["seed"], current["participant_key"], current["planned"]))


def _hello(current: dict[str, Any], teleop: TeleopSession | None) -> dict[str, Any]:
    hello: dict[str, Any] = {"type": "hello", "stage": current["stage"], "trial": current["trial"]}
    if teleop is not None:
        hello["scene"] = {"complexity": teleop.scene.complexity, "seed": str(teleop.scene.seed),
                          "target_slot": teleop.scene.target_slot}
        hello["world"] = world_state_dict(teleop.state)
    return hello


def _finish(session: Session, app, token: str, teleop: TeleopSession, batch: list[list[Any]], elapsed_ms: float) -> bool:
    """Log ``batch`` and complete the trial, in one transaction; False if it was already resolved (e.g. the time
    limit)."""
    participant = sessions.participant_by_token(session, token, lock=True)
    _log_commands(session, participant, teleop, batch)
    runtime = sessions.runtime_of(session, app.state.runtimes, participant)
    trial = trials.current_trial(session, participant)
    key = teleop.key
    if trial is None or trial.stage != "teleop" or (trial.practice, trial.block, trial.trial) != (
            key.practice, key.block, key.trial):
        return False
    trials.finish_teleop(session, participant, runtime, trial, True, elapsed_ms, utcnow())
    return True


async def _flush(app, token: str, teleop: TeleopSession) -> None:
    """Write the commands logged since the last flush."""
    if batch := teleop.take_log():
        await run_unit(app, lambda session: _log_batch(session, token, teleop, batch))


def _log_batch(session: Session, token: str, teleop: TeleopSession, batch: list[list[Any]]) -> None:
    _log_commands(session, sessions.participant_by_token(session, token), teleop, batch)


def _log_commands(session: Session, participant: Participant, teleop: TeleopSession, batch: list[list[Any]]) -> None:
    if not batch:
        return
    sessions.touch(participant)
    key = teleop.key
    log_event(session, participant.study_id, participant.id, "teleop_commands",
              practice=key.practice, block=key.block, trial=key.trial, commands=batch)
