"""Simulated participants over HTTP and the teleoperation websocket, exactly as a browser would.

A bot joins, consents, reads the instructions, practises, answers every questionnaire and supervises every trial.
Its rely/intervene choices come from an IOHMM (``experiment.participants.reliance``: a hidden trust state moved by
each trial's experience); its teleoperation is a person at the page or the robot world's scripted controller
(``server.harness.bot_teleop``). A bot works against a real server (``httpx`` + ``websockets``) or in process
(FastAPI's ``TestClient``); ``server.harness.crowd`` runs many.
"""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from typing import Any, Protocol

import httpx
import numpy as np

from experiment.iohmm import IOHMMParams
from experiment.participants.reliance import SimulatedHuman
from experiment.schedule import derive_rng
from experiment.task import Complexity, Experience, HumanAction, RobotAction
from server.harness.bot_teleop import PERSON_MAX_SPEEDUP, teleoperate_as_person, teleoperate_scripted
from server.harness.client import (
    STALL_TIMEOUT_S,
    BotError,
    BotStats,
    Refused,
    Socket,
    SocketFactory,
    StudyFull,
    route_name,
)

#: A request refused with 429 (e.g. the join rate limit) is retried after its Retry-After, this many times.
MAX_RATE_LIMIT_RETRIES = 20
#: While the 3D view has not drawn the trial's scene, the bot looks again this much later (the page's SCENE_CHECK_MS).
SCENE_RETRY_S = 0.3


class SceneDisplay(Protocol):
    """A bot's 3D view of its session, open from the join to the end as the page keeps it (e.g. the headless viser
    client of ``server.harness.viewer_client``). With one, the bot reports each trial's scene as ``3d``."""

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
            raise Refused(f"{method} {path} -> {response.status_code}: {response.text[:300]}", response.status_code)
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
            return self.report_shown(ref | {"view": "text"})
        if self.display.drawn_stamp() != trial.get("scene_stamp"):
            time.sleep(SCENE_RETRY_S)
            return self.state()
        return self.report_shown(ref | {"view": "3d", "scene_stamp": trial["scene_stamp"],
                                        "client_time_ms": time.perf_counter() * 1000})

    def report_shown(self, body: dict[str, Any]) -> dict[str, Any]:
        """POST trials/shown; a 409 (the trial moved on meanwhile: a slow client, a server restart, and the window
        opened at its wait limit and closed) is answered as the page does: by reading the state again, and looking
        again ``SCENE_RETRY_S`` later if it still presents the trial."""
        state, moved_on = self.post_unless_moved_on("trials/shown", body, key=False)
        if moved_on and (state.get("trial") or {}).get("stage") == "presenting":
            time.sleep(SCENE_RETRY_S)
        return state

    def post_unless_moved_on(self, what: str, body: Any, key: bool) -> tuple[dict[str, Any], bool]:
        """POST, or, where the server answers 409 (the session moved on before the request arrived: a window that
        closed, a trial that ended), the state read again, as the page does; and whether it moved on."""
        try:
            return self.post(what, body, key), False
        except Refused as exc:
            if exc.status != 409:
                raise
            return self.state(), True

    def trial(self, state: dict[str, Any]) -> dict[str, Any]:
        trial = state["trial"]
        if trial["stage"] == "presenting":
            return self.show_scene(trial)
        if trial["stage"] == "decision":
            if self.wants_to_intervene(trial):
                opened = time.perf_counter() * 1000
                body = {"practice": trial["practice"], "block": trial["block"], "trial": trial["trial"],
                        "window_opened_ms": opened, "pressed_ms": opened + float(self.rng.uniform(200, 900))}
                # a 409: the window closed while we decided, and the robot attempts
                return self.post_unless_moved_on("trials/intervene", body, key=True)[0]
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
        """``bot_teleop.teleoperate_as_person``, as a person of this bot's seed; ``last_teleop`` says how it went."""
        self.last_teleop = {}
        teleoperate_as_person(ws, setup, int(self.rng.integers(2**31)), self.stats, self.last_teleop)

    def _teleoperate_scripted(self, ws: Socket, setup: dict[str, Any]) -> None:
        teleoperate_scripted(ws, setup, self.stats)


def _code(response: httpx.Response) -> str | None:
    try:
        return response.json().get("code")
    except ValueError:
        return None
