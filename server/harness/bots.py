"""Simulated participants over HTTP and the teleoperation websocket, exactly as a browser would.

A bot joins, consents, reads the instructions, practises, answers every
questionnaire and supervises every trial. Its rely/intervene choices come
from an IOHMM (a hidden trust state moved by each trial's experience); its
teleoperation is the scripted controller of the robot world, run on the
world state the server sends back. A bot works against a real server
(``httpx`` + ``websockets``) or in process (FastAPI's ``TestClient``).
"""

from __future__ import annotations

import hashlib
import json
import queue
import threading
import time
import traceback
import uuid
from collections import defaultdict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import httpx
import numpy as np

from experiment.iohmm import IOHMMParams
from experiment.participants.page import PAGE_FRAME_S, ClientLoop
from experiment.participants.person import HumanModel
from experiment.participants.reliance import SimulatedHuman
from experiment.schedule import derive_rng
from experiment.task import Complexity, Experience, HumanAction, RobotAction
from experiment.world import build_scene, scripted_teleop_commands
from experiment.world.scripted import GAIN as SCRIPTED_GAIN
from experiment.world.state import ItemMode, ItemState, WorldState

#: Longest a bot waits for the server to move on before it calls it an error.
STALL_TIMEOUT_S = 120.0
MAX_TELEOP_COMMANDS = 20_000
#: The scripted controller's teleoperation messages per second at most (its velocities change continuously; it
#: closes its loop through the socket, so the faster messages and world updates go, the sooner it is done) ...
TELEOP_MESSAGE_HZ = 60.0
#: ... and never more than this share of the server's rate limit (announced in ``hello``).
TELEOP_RATE_LIMIT_SHARE = 0.5
#: A bot teleoperates as a person (``experiment.participants.person.HumanModel``) when the study's robot moves at most
#: this many times real time; faster (a sped-up test study) no person could steer, and the scripted controller does.
PERSON_MAX_SPEEDUP = 2.0
#: A request refused with 429 (e.g. the join rate limit) is retried after its Retry-After, this many times.
MAX_RATE_LIMIT_RETRIES = 20
#: While the 3D view has not drawn the trial's scene, the bot looks again this much later (the page's SCENE_CHECK_MS).
SCENE_RETRY_S = 0.3


class BotError(RuntimeError):
    pass


class StudyFull(BotError):
    """The join was refused: the study is at its cap on active participants (503, code ``study_full``). A person
    is told to come back later; for a run it is a refusal, not an error."""


class Socket(Protocol):
    def send_text(self, data: str) -> None: ...
    def receive_text(self) -> str: ...


SocketFactory = Callable[[str], AbstractContextManager[Socket]]


class SceneDisplay(Protocol):
    """A bot's 3D view of its session, open from the join to the end as the page keeps it (e.g. the headless viser
    client of ``benchmarks/viewer_client.py``). With one, the bot reports each trial's scene as ``3d``."""

    def open(self, token: str) -> None: ...
    def close(self) -> None: ...

    def drawn_stamp(self) -> str | None:
        """The stamp of the scene the view shows now (its ``/scene_stamp_<stamp>`` node, ``server.viewer.scene``):
        what a frame drawn after this call is drawn from; None before the view has a scene."""
        ...

    def moving(self, kind: str, start: float, end: float) -> None:
        """The robot moved from ``start`` to ``end`` (time.monotonic): ``attempt`` or ``teleop``."""
        ...


def bot_resume_key(external_id: str) -> str:
    """A bot's resume key (its browser's): derived from its external id, so a bot started again with the same id (a
    rerun, a restart after a kill) resumes its session as a page reopened in the same browser does."""
    return hashlib.sha256(f"trustlab-bot:{external_id}".encode()).hexdigest()[:32]


def route_name(method: str, path: str) -> str:
    """A request's method and route without the session's token ("POST trials/shown"; "POST join" for a join): the
    bots' and the benchmarks' loop watch's name for it."""
    _, participant, rest = path.partition("/api/p/")
    return f"{method} {rest.partition('/')[2] if participant else path.rsplit('/', 1)[-1]}"


@dataclass
class BotStats:
    latencies_ms: list[float] = field(default_factory=list)
    teleop_ack_ms: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    completed: int = 0
    trials: int = 0
    rate_limited: int = 0  # 429 responses waited out
    refused: int = 0  # joins refused because the study was full
    #: Each request's latency by method and route ("POST trials/shown"; a 429 and its repeat count twice): where the
    #: load comes from, and which step a person waits on.
    route_latencies_ms: defaultdict[str, list[float]] = field(default_factory=lambda: defaultdict(list))


class Bot:
    """One simulated participant."""

    def __init__(self, http: httpx.Client, sockets: SocketFactory, slug: str, model: IOHMMParams, seed: int,
                 stats: BotStats, external_id: str | None = None, display: SceneDisplay | None = None):
        self.http, self.sockets, self.slug, self.stats = http, sockets, slug, stats
        self.display = display
        #: time.monotonic() of the answer (the trial's start, or a 3d report) that said the session's viewer holds the
        #: trial's scene; None while none has.
        self.rng = derive_rng(seed, "bot", external_id or uuid.uuid4().hex)
        self.human = SimulatedHuman(model, self.rng)
        self.external_id = external_id
        self.token = ""
        #: (practice, block, trial) -> outcome of every trial result the server acknowledged to this bot.
        self.acknowledged: dict[tuple[bool, int, int], str] = {}
        #: How the latest teleoperation went (its seconds, messages sent and the ``over`` that ended it): a stall's
        #: error says it.
        self.last_teleop: dict[str, Any] | None = None

    # -- HTTP ------------------------------------------------------------------------
    def call(self, method: str, path: str, json_body: Any = None, key: bool = False) -> dict[str, Any]:
        headers = {"Idempotency-Key": uuid.uuid4().hex} if key else {}
        for _ in range(MAX_RATE_LIMIT_RETRIES):
            start = time.perf_counter()
            try:
                response = self.http.request(method, path, json=json_body, headers=headers)
            except (httpx.ReadError, httpx.WriteError, httpx.RemoteProtocolError):
                # A kept-alive connection the server closed as the request went out (its idle timeout): send it
                # once more on a new connection, as browsers do. Safe: every other bot request is a read, carries
                # an Idempotency-Key or repeats idempotently (the start of one trial); a join resumes only by its
                # external id with its resume key.
                if path.endswith("/join") and not self.external_id:
                    raise
                response = self.http.request(method, path, json=json_body, headers=headers)
            latency_ms = (time.perf_counter() - start) * 1000
            self.stats.latencies_ms.append(latency_ms)
            self.stats.route_latencies_ms[route_name(method, path)].append(latency_ms)
            if response.status_code != 429:
                break
            self.stats.rate_limited += 1
            time.sleep(float(response.headers.get("Retry-After", "1")))
        if response.status_code == 503 and _code(response) == "study_full":
            raise StudyFull(response.json().get("detail", "the study is full"))
        if response.status_code >= 400:
            raise BotError(f"{method} {path} -> {response.status_code}: {response.text[:300]}")
        return response.json()


    def post(self, what: str, body: Any = None, key: bool = True) -> dict[str, Any]:
        return self.call("POST", f"/api/p/{self.token}/{what}", body, key)

    def state(self) -> dict[str, Any]:
        return self.call("GET", f"/api/p/{self.token}/state")

    # -- the session -----------------------------------------------------------------
    def run(self, token: str | None = None) -> dict[str, Any]:
        """Join the study and go through it; with ``token``, go on with that session instead (e.g. a preview
        session the experimenter started)."""
        if token is None:
            body = {"params": {"PROLIFIC_PID": self.external_id},
                    "resume_key": bot_resume_key(self.external_id)} if self.external_id else {"params": {}}
            joined = self.call("POST", f"/api/studies/{self.slug}/join", body)
            self.token, state = joined["token"], joined["state"]
        else:
            self.token = token
            state = self.state()
        if self.display is not None:
            self.display.open(self.token)
        try:
            deadline = time.monotonic() + STALL_TIMEOUT_S
            last_step = None
            while state["phase"] not in ("debrief", "declined", "screened_out"):
                if json.dumps(state["step"], sort_keys=True) != last_step:
                    last_step, deadline = json.dumps(state["step"], sort_keys=True), time.monotonic() + STALL_TIMEOUT_S
                if time.monotonic() > deadline or state["phase"] in ("abandoned", "withdrawn"):
                    raise BotError(self._stalled(state, deadline))
                state = self.step(state)
        finally:
            if self.display is not None:
                self.display.close()
        self.stats.completed += 1
        return state

    def _stalled(self, state: dict[str, Any], deadline: float) -> str:
        """What a stall's error says: where the session stood, for how long, and the latest teleoperation."""
        trial = state.get("trial") or {}
        spent = time.monotonic() - deadline + STALL_TIMEOUT_S
        return (f"stalled at {state['phase']} {state['step']} (trial stage {trial.get('stage')}, {spent:.0f} s at this "
                f"step; latest teleoperation: {self.last_teleop})")

    def step(self, state: dict[str, Any]) -> dict[str, Any]:
        phase = state["phase"]
        if phase == "consent":
            return self.post("consent", {"agree": True})
        if phase == "instructions":
            return self.post("instructions/done")
        if phase == "practice_done":
            return self.post("practice/done")
        if phase in ("questionnaire", "shelf_survey"):
            return self.post("answers", self.answers(state))
        if state.get("ready_to_start"):
            return self.post("trials/start", state["ready_to_start"], key=False)
        return self.trial(state)

    def show_scene(self, trial: dict[str, Any]) -> dict[str, Any]:
        """Report the trial's scene on screen (POST trials/shown), as the page does.

        Without a display the bot shows no scene and reports its ``text`` view at once. With one, it reports ``3d``
        once its view has drawn the trial's scene (``SceneDisplay.drawn_stamp`` is the trial's ``scene_stamp``), and
        looks again every ``SCENE_RETRY_S`` until then (the server opens the window at its wait limit anyway).
        """
        ref = {"practice": trial["practice"], "block": trial["block"], "trial": trial["trial"]}
        if self.display is None:
            return self.post("trials/shown", ref | {"view": "text"}, key=False)
        if self.display.drawn_stamp() != trial.get("scene_stamp"):
            time.sleep(SCENE_RETRY_S)
            return self.state()
        return self.post("trials/shown", ref | {"view": "3d", "scene_stamp": trial["scene_stamp"],
                                                "client_time_ms": time.perf_counter() * 1000}, key=False)

    def trial(self, state: dict[str, Any]) -> dict[str, Any]:
        trial = state["trial"]
        if trial["stage"] == "presenting":
            return self.show_scene(trial)
        if trial["stage"] == "decision":
            if self.wants_to_intervene(trial):
                opened = time.perf_counter() * 1000
                body = {"practice": trial["practice"], "block": trial["block"], "trial": trial["trial"],
                        "window_opened_ms": opened, "pressed_ms": opened + float(self.rng.uniform(200, 900))}
                try:
                    return self.post("trials/intervene", body)
                except BotError as exc:  # the window closed while we decided: the robot attempts
                    if "409" not in str(exc):
                        raise
                    return self.state()
            time.sleep((trial["decision_ms_left"] or 0) / 1000 + 0.005)
        elif trial["stage"] == "attempt":
            start = time.monotonic()
            time.sleep((trial["attempt_ms_left"] or 0) / 1000 + 0.005)
            if self.display is not None:
                self.display.moving("attempt", start, time.monotonic())
        elif trial["stage"] == "teleop":
            start = time.monotonic()
            self.teleoperate()
            if self.display is not None:
                self.display.moving("teleop", start, time.monotonic())
        after = self.state()
        self._learn(after)
        return after

    def wants_to_intervene(self, trial: dict[str, Any]) -> bool:
        if trial["practice"]:
            return trial.get("hint") is not None and "Intervene" in trial["hint"] and "Do not" not in trial["hint"]
        action = self.human.respond(Complexity(trial["complexity"]), RobotAction(trial["robot_action"]))
        return action == HumanAction.INTERVENE

    def _learn(self, state: dict[str, Any]) -> None:
        last = state.get("last_trial")
        if last:
            self.acknowledged[(last["practice"], last["block"], last["trial"])] = last["outcome"]
        if last and not last["practice"] and (last["block"], last["trial"]) != getattr(self, "_learned", None):
            self._learned = (last["block"], last["trial"])
            self.stats.trials += 1
            self.human.update(Complexity(last["complexity"]), RobotAction(last["robot_action"]),
                              Experience(last["experience"]))

    def answers(self, state: dict[str, Any]) -> dict[str, Any]:
        q = state["questionnaire"]
        scale = q["scale"] or {"min": 0, "max": 0, "step": 1}  # a page without rating items has no scale
        points = np.arange(scale["min"], scale["max"] + scale["step"] / 2, scale["step"])
        high = self.human.trust.value == "high"
        answers: dict[str, Any] = {}
        for item in q["items"]:
            if item.get("kind", "rating") != "rating":  # text: left blank when optional; choice: the first option
                if item["kind"] == "choice":
                    answers[item["id"]] = item["options"][0]["value"]
                elif item["required"]:
                    answers[item["id"]] = "No comment."
                continue
            centre = (0.75 if high else 0.4) * (len(points) - 1)
            index = int(np.clip(round(self.rng.normal(centre, len(points) / 8)), 0, len(points) - 1))
            answers[item["id"]] = float(points[index])
        return {"questionnaire": q["id"], "context": q["context"], "answers": answers}

    # -- teleoperation -----------------------------------------------------------------
    def teleoperate(self) -> None:
        """Teleoperate the trial over its socket (``server.teleop_messages``): as a person at the page when the
        study's robot moves at most ``PERSON_MAX_SPEEDUP`` times real time, else with the scripted controller."""
        with self.sockets(f"/api/p/{self.token}/teleop") as ws:
            hello = json.loads(ws.receive_text())
            setup = hello.get("teleop")
            if setup is None:
                return
            if setup["limits"]["speedup"] <= PERSON_MAX_SPEEDUP:
                self._teleoperate_as_person(ws, setup)
            else:
                self._teleoperate_scripted(ws, setup)

    def _teleoperate_as_person(self, ws: Socket, setup: dict[str, Any]) -> None:
        """A person at the page's keyboard (``experiment.participants``): on/off keys at a person's reaction
        times, from what the socket shows; the page sends an input when the keys change and a keep-alive every
        ``keepalive_s`` while motion is held. A thread reads the socket (the page's ``onmessage``) and stamps each
        message when it arrives: an ack's latency is from sending to that stamp, not to the page loop's next look
        (up to ``PAGE_FRAME_S`` later)."""
        human = HumanModel(setup, int(self.rng.integers(2**31)))
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
        self.last_teleop = {"over": ended, "sent": 0, "acks": 0, "worlds": 0}
        try:
            while time.monotonic() < deadline:
                while not inbox.empty():
                    if (arrival := inbox.get()) is None:
                        return
                    arrived, message = arrival
                    self.last_teleop["acks" if message["type"] == "ack" else "worlds"] += 1
                    if message["type"] == "world":
                        latest = message
                    elif message["type"] == "ack":
                        client.ack(message)
                        if (sent := sent_at.pop(message.get("seq"), None)) is not None:
                            self.stats.teleop_ack_ms.append((arrived - sent) * 1000)
                now = time.monotonic()
                outgoing = client.tick(now - clock0, latest, keepalive=False)
                if now >= next_keepalive:
                    outgoing += client.keepalive(now - clock0)
                    next_keepalive = now + keepalive_s
                self.last_teleop["sent"] += len(outgoing)
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
            self.last_teleop |= {"seconds": round(time.monotonic() - clock0, 1), "phase": human.phase}
            reader.join(timeout=0)

    def _teleoperate_scripted(self, ws: Socket, setup: dict[str, Any]) -> None:
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
            self.stats.teleop_ack_ms.append((time.perf_counter() - sent_at) * 1000)
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


def _code(response: httpx.Response) -> str | None:
    try:
        return response.json().get("code")
    except ValueError:
        return None


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


@dataclass
class BotRunSummary:
    participants: int
    completed: int
    errors: list[str]
    trials: int
    latency_ms: dict[str, float]
    teleop_ack_ms: dict[str, float]
    seconds: float
    rate_limited: int = 0
    stats: BotStats | None = None  # the raw measurements (not in to_dict)
    refused: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"participants": self.participants, "completed": self.completed, "errors": self.errors,
                "trials": self.trials, "latency_ms": self.latency_ms, "teleop_ack_ms": self.teleop_ack_ms,
                "seconds": self.seconds, "rate_limited": self.rate_limited, "refused": self.refused}


def run_bots(make_http: Callable[[], httpx.Client], sockets: SocketFactory, slug: str, model: IOHMMParams, *,
             participants: int, concurrency: int = 4, seed: int = 0, ramp_s: float = 0.0,
             progress: Callable[[int, int], None] | None = None,
             displays: Callable[[int], SceneDisplay] | None = None) -> BotRunSummary:
    """Run ``participants`` bots, ``concurrency`` at a time; every error is counted, none is raised.

    ``ramp_s`` spreads the arrivals: bot i starts ``i * ramp_s / participants`` seconds in (people do not all
    open the link in the same millisecond). ``displays(i)``, if given, is bot i's 3D view.
    """
    stats = BotStats()
    start = time.perf_counter()
    done = 0

    def one(index: int) -> None:
        nonlocal done
        time.sleep(max(0.0, start + index * ramp_s / participants - time.perf_counter()))
        with make_http() as http:
            bot = Bot(http, sockets, slug, model, seed, stats, external_id=f"bot-{seed}-{index:05d}",
                      display=displays(index) if displays is not None else None)
            try:
                bot.run()
            except StudyFull:
                stats.refused += 1
            except Exception as exc:  # a bot's failure is data for the summary
                where = traceback.extract_tb(exc.__traceback__)[-1]
                stats.errors.append(f"bot {index}: {type(exc).__name__}: {exc} ({where.filename}:{where.lineno})")
        done += 1
        if progress:
            progress(done, participants)

    with ThreadPoolExecutor(max_workers=concurrency) as pool:
        list(pool.map(one, range(participants)))
    return BotRunSummary(participants, stats.completed, stats.errors, stats.trials, percentiles(stats.latencies_ms),
                         percentiles(stats.teleop_ack_ms), time.perf_counter() - start, stats.rate_limited, stats,
                         stats.refused)


def run_remote_bots(url: str, slug: str, model: IOHMMParams, *, participants: int, concurrency: int = 4,
                    seed: int = 0, ramp_s: float = 0.0, progress: Callable[[int, int], None] | None = None,
                    displays: Callable[[int], SceneDisplay] | None = None) -> BotRunSummary:
    """``run_bots`` against a running server at ``url`` (HTTP with httpx, websockets for teleoperation)."""
    base = url.rstrip("/")
    return run_bots(lambda: httpx.Client(base_url=base, timeout=30), remote_sockets(base), slug, model,
                    participants=participants, concurrency=concurrency, seed=seed, ramp_s=ramp_s, progress=progress,
                    displays=displays)


def remote_sockets(url: str) -> SocketFactory:
    """Websockets to the server at ``url`` (http(s)://host:port) for bots."""
    from websockets.sync.client import connect

    base = url.rstrip("/")
    ws_base = "ws" + base[4:] if base.startswith("http") else base

    @contextmanager
    def socket(path: str) -> Iterator[Socket]:
        with connect(ws_base + path, open_timeout=10, max_size=2**20) as ws:
            yield _SyncSocket(ws)

    return socket


class _SyncSocket:
    def __init__(self, ws: Any):
        self.ws = ws

    def send_text(self, data: str) -> None:
        self.ws.send(data)

    def receive_text(self) -> str:
        message = self.ws.recv(timeout=30)
        return message if isinstance(message, str) else message.decode()


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    array = np.asarray(values)
    return {"n": float(array.size), "p50": float(np.percentile(array, 50)), "p95": float(np.percentile(array, 95)),
            "p99": float(np.percentile(array, 99)), "max": float(array.max())}
