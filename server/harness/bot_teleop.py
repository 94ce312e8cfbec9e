"""A bot's teleoperation of a trial over the teleoperation socket (``server.teleop_messages``).

As a person at the participant page's keyboard (``experiment.participants``: on/off keys at a person's reaction
times, from what the socket shows) when the study's robot moves at most ``PERSON_MAX_SPEEDUP`` times real time;
faster (a sped-up test study) no person could steer, and the robot world's scripted controller does, on the world
state the server sends back.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from typing import Any

from experiment.participants.page import PAGE_FRAME_S, ClientLoop
from experiment.participants.person import HumanModel
from experiment.world import build_scene, scripted_teleop_commands
from experiment.world.scripted import GAIN as SCRIPTED_GAIN
from experiment.world.state import ItemMode, ItemState, WorldState
from server.harness.client import STALL_TIMEOUT_S, BotError, BotStats, Socket

#: The scripted controller's messages in one teleoperation at most (a bound on a run that goes wrong).
MAX_TELEOP_COMMANDS = 20_000
#: The scripted controller's teleoperation messages per second at most (its velocities change continuously; it
#: closes its loop through the socket, so the faster messages and world updates go, the sooner it is done) ...
TELEOP_MESSAGE_HZ = 60.0
#: ... and never more than this share of the server's rate limit (announced in ``hello``).
TELEOP_RATE_LIMIT_SHARE = 0.5
#: A bot teleoperates as a person (``experiment.participants.person.HumanModel``) when the study's robot moves at most
#: this many times real time; faster (a sped-up test study) no person could steer, and the scripted controller does.
PERSON_MAX_SPEEDUP = 2.0


def teleoperate_as_person(ws: Socket, setup: dict[str, Any], seed: int, stats: BotStats, report: dict[str, Any]
                          ) -> None:
    """A person at the page's keyboard (``experiment.participants``): on/off keys at a person's reaction
    times, from what the socket shows; the page sends an input when the keys change and a keep-alive every
    ``keepalive_s`` while motion is held. A thread reads the socket (the page's ``onmessage``) and stamps each
    message when it arrives: an ack's latency is from sending to that stamp, not to the page loop's next look
    (up to ``PAGE_FRAME_S`` later). ``seed``: the person's; ``report`` (the bot's ``last_teleop``) gets how it
    went: the messages sent, the acks and world messages received, the ``over`` that ended it, its seconds."""
    human = HumanModel(setup, seed)
    client = ClientLoop(human, float(setup["limits"]["keepalive_s"]))
    inbox: queue.SimpleQueue[tuple[float, dict[str, Any]] | None] = queue.SimpleQueue()  # (arrived, message)
    ended: dict[str, Any] = {}

    def read() -> None:
        try:
            while (message := json.loads(ws.receive_text()))["type"] != "over":
                inbox.put((time.monotonic(), message))
            ended.update(message)
        except Exception as exc:  # noqa: BLE001 -- closed: the main loop ends on the sentinel
            ended["closed"] = repr(exc)[:200]
        inbox.put(None)

    reader = threading.Thread(target=read, name="bot-teleop-reader", daemon=True)
    reader.start()
    latest: dict[str, Any] = {"type": "hello", "world": setup["world"], "guidance": setup["guidance"]}
    sent_at: dict[int, float] = {}
    clock0 = time.monotonic()
    next_frame = next_keepalive = clock0
    keepalive_s = float(setup["limits"]["keepalive_s"])
    deadline = clock0 + float(setup.get("time_limit_s") or 0) + STALL_TIMEOUT_S
    report.update({"over": ended, "sent": 0, "acks": 0, "worlds": 0})
    try:
        while time.monotonic() < deadline:
            while not inbox.empty():
                if (arrival := inbox.get()) is None:
                    return
                arrived, message = arrival
                report["acks" if message["type"] == "ack" else "worlds"] += 1
                if message["type"] == "world":
                    latest = message
                elif message["type"] == "ack":
                    client.ack(message)
                    seq = message.get("seq")
                    if seq is not None and (sent := sent_at.pop(seq, None)) is not None:
                        stats.teleop_ack_ms.append((arrived - sent) * 1000)
            now = time.monotonic()
            outgoing = client.tick(now - clock0, latest, keepalive=False)
            if now >= next_keepalive:
                outgoing += client.keepalive(now - clock0)
                next_keepalive = now + keepalive_s
            report["sent"] += len(outgoing)
            for message in outgoing:
                sent_at[message["seq"]] = time.monotonic()
                try:
                    ws.send_text(json.dumps(message))
                except Exception:  # noqa: BLE001 -- closed after ``over``, which the reader takes
                    reader.join(timeout=10)
                    return
            next_frame += PAGE_FRAME_S
            time.sleep(max(0.0, next_frame - time.monotonic()))
        raise BotError("teleoperation did not finish")
    finally:
        report.update({"seconds": round(time.monotonic() - clock0, 1), "phase": human.phase})
        reader.join(timeout=0)


def teleoperate_scripted(ws: Socket, setup: dict[str, Any], stats: BotStats) -> None:
    """Steer with the scripted controller.

    One message is in flight at a time: an input when the controller's command changed, else a
    keep-alive, at most ``TELEOP_MESSAGE_HZ`` a second; the server moves the arm between them.
    """
    info = setup["scene"]
    scene = build_scene(info["complexity"], int(info["seed"]), info["target_slot"])
    world, held, sent_at, seq = _world_state(setup["world"]), None, 0.0, 0
    limits = setup["limits"]
    message_hz = min(TELEOP_MESSAGE_HZ, TELEOP_RATE_LIMIT_SHARE * limits["rate_limit_hz"])
    # The scripted controller is proportional; the server moves the arm ``speedup`` times faster than
    # real time while the bot sees the world about a message period plus a world period late: slow
    # the controller so that it does not overshoot (its loop gain stays below one).
    loop_delay_s = 1 / message_hz + 1 / limits["world_hz"]
    scale = min(1.0, 1.0 / (SCRIPTED_GAIN * limits["speedup"] * loop_delay_s))
    for _ in range(MAX_TELEOP_COMMANDS):
        time.sleep(max(0.0, sent_at + 1 / message_hz - time.perf_counter()))
        command = _command_dict(scripted_teleop_commands(world, scene), scale)
        message: dict[str, Any] = {"type": "keepalive", "seq": seq}
        if command != held or "gripper" in command:
            message = {"type": "input", "seq": seq, "client_ms": time.perf_counter() * 1000, **command}
            held = {k: v for k, v in command.items() if k != "gripper"}
        sent_at = time.perf_counter()
        try:
            ws.send_text(json.dumps(message))
        except Exception:  # noqa: BLE001 -- closed after ``over`` (a deposit's reply), which is still to read
            while json.loads(ws.receive_text())["type"] != "over":
                pass
            return
        while True:  # world messages until this message's ack
            reply = json.loads(ws.receive_text())
            if reply["type"] == "world":
                world = _world_state(reply["world"])
            elif reply["type"] == "over":
                return
            elif reply["type"] == "ack" and reply["seq"] == seq:
                break
        stats.teleop_ack_ms.append((time.perf_counter() - sent_at) * 1000)
        if not reply["ok"]:
            if "too many" not in (reply.get("error") or ""):
                while (after := json.loads(ws.receive_text()))["type"] == "world":
                    pass
                if after["type"] == "over":  # ended elsewhere (another tab)
                    return
                raise BotError(f"teleop message refused: {reply['error']}")
            held = None  # send the input again
        seq += 1
    raise BotError("teleoperation did not finish")


def _command_dict(command, scale: float = 1.0) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if command.ee_velocity is not None:
        out["ee_velocity"] = [v * scale for v in command.ee_velocity]
    if command.joint_velocity is not None:
        out["joint_velocity"] = [v * scale for v in command.joint_velocity]
    if command.gripper is not None:
        out["gripper"] = command.gripper
    return out


def _world_state(data: dict[str, Any]) -> WorldState:
    item = data["item"]
    return WorldState(data["t"], tuple(data["base"]), tuple(data["joints"]), data["gripper"], data["gripper_target"],
                      ItemState(ItemMode(item["mode"]), tuple(item["position"]), tuple(item["wxyz"])))
