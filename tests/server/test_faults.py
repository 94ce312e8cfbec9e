"""Client faults and their defined outcomes (issue 6; docs/reliability.md).

Each test drives a real server (uvicorn on a loopback port, with its event loop, database turns, world loop and
sweeper) the way a misbehaving browser would: a reload storm, duplicated and reordered requests, a websocket
dropped mid-teleoperation, two tabs of one participant, and a participant idle past the abandonment time.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.sync.client import ClientConnection, connect

from experiment.config import TimingConfig
from experiment.flow import INSTRUCTIONS, PracticeStep, QuestionnaireStep, ShelfSurveyStep, Step, TrialStep, all_steps
from experiment.iohmm import paper_params
from experiment.templates import demo_fast
from experiment.world import build_scene, teleop_start_state
from server.harness.bots import Bot
from server.harness.client import BotError, BotStats, remote_sockets
from server.harness.live import Live, expected_records, live_server, run_all
from server.models import Answer, Event, IdempotentResponse, Participant, Trial, utcnow
from server.services.sessions import describe, participant_by_token

#: demo-fast, with a decision window long enough for a test to act inside it.
TIMING = TimingConfig(decision_window_s=30.0, animation_speed=100.0, teleop_time_limit_s=300.0)
CONFIG = demo_fast().model_copy(update={"timing": TIMING})
STORM = 16  # concurrent copies of one request
PRACTICE_1 = {"practice": True, "block": 0, "trial": 1}
#: The first shelf survey of the first block (the demo asks it after trial 3).
SHELF_1 = ShelfSurveyStep(block=1, shelf=1, trial=3)
BLOCK_ORDER = [block.name for block in CONFIG.blocks]
#: The questionnaire after the first block (the demo asks the same one after the second block too).
AFTER_1 = QuestionnaireStep(context="after:1", block=1,
                            questionnaire=CONFIG.block(BLOCK_ORDER[0]).questionnaires_after[0])


@pytest.fixture
def live(database_url: str) -> Iterator[Live]:
    with live_server(database_url) as server:
        open_study(server)
        yield server


@pytest.fixture
def http(live: Live) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=live.url, timeout=30) as client:
        yield client


def open_study(live: Live, slug: str = "slow", config=CONFIG) -> None:
    created = live.admin("POST", "/api/admin/studies",
                         json={"status": "open", "slug": slug, "config": config.model_dump(mode="json")})
    assert created.status_code == 201, created.text


#: The resume key of the one browser these tests' participants use (the join page keeps one per study).
BROWSER_KEY = "faults-browser-resume-key"


def join(http: httpx.Client, external_id: str, slug: str = "slow") -> dict[str, Any]:
    joined = http.post(f"/api/studies/{slug}/join", params={"PROLIFIC_PID": external_id},
                       json={"resume_key": BROWSER_KEY})
    assert joined.status_code == 200, joined.text
    return joined.json()


def post(http: httpx.Client, token: str, what: str, body: Any = None, key: str | None = None) -> httpx.Response:
    return http.post(f"/api/p/{token}/{what}", json=body, headers={"Idempotency-Key": key} if key else {})


def state(http: httpx.Client, token: str) -> dict[str, Any]:
    response = http.get(f"/api/p/{token}/state")
    assert response.status_code == 200, response.text
    return response.json()


def jump(live: Live, token: str, step: Step, block_order: list[str] | None = None) -> None:
    """Put the session at ``step`` directly in the database (the steps before it are other tests' business)."""
    with live.app.state.services.sessionmaker.begin() as session:
        participant = participant_by_token(session, token)
        participant.step = step
        if block_order is not None:
            participant.block_order = block_order


def written(live: Live, token: str) -> dict[str, Any]:
    """Everything a participant's requests can write, to compare before and after a refused request."""
    with live.app.state.services.sessionmaker() as session:
        participant = participant_by_token(session, token)
        trials = session.execute(select(Trial.practice, Trial.block, Trial.trial, Trial.stage, Trial.human_action)
                                 .where(Trial.participant_id == participant.id).order_by(Trial.id)).all()

        def rows(model) -> int:
            return session.scalar(select(func.count()).select_from(model).where(model.participant_id == participant.id))

        return {"step": participant.step, "status": participant.status, "trials": [tuple(t) for t in trials],
                "answers": rows(Answer), "events": rows(Event), "stored_responses": rows(IdempotentResponse)}


def events_of(live: Live, token: str, kind: str) -> list[Event]:
    with live.app.state.services.sessionmaker() as session:
        participant = participant_by_token(session, token)
        return list(session.scalars(select(Event).where(Event.participant_id == participant.id, Event.kind == kind)
                                    .order_by(Event.id)))


def storm(requests: list[Callable[[], httpx.Response]]) -> list[httpx.Response]:
    """All ``requests`` at once (each thread waits for the others before sending); no 5xx among the answers."""
    ready = threading.Barrier(len(requests))

    def send(request: Callable[[], httpx.Response]) -> httpx.Response:
        ready.wait()
        return request()

    with ThreadPoolExecutor(len(requests)) as pool:
        responses = list(pool.map(send, requests))
    assert [r.text for r in responses if r.status_code >= 500] == []
    return responses


def page_answers(page: dict[str, Any]) -> dict[str, Any]:
    """A valid answer to questionnaire page ``page`` (as the state shows it): the scale's lowest point everywhere."""
    return {"questionnaire": page["id"], "context": page["context"],
            "answers": {item["id"]: page["scale"]["min"] for item in page["items"]}}


def to_practice(http: httpx.Client, token: str) -> None:
    assert post(http, token, "consent", {"agree": True}).status_code == 200
    assert post(http, token, "instructions/done").status_code == 200


def assert_conflict(response: httpx.Response, step: Step) -> None:
    """A 409 whose reason names the step the session is at."""
    assert response.status_code == 409, response.text
    assert f"the session is at {describe(step)}" in response.json()["detail"], response.json()["detail"]


# -- reload storm -------------------------------------------------------------------------------------------------


def test_reload_storm_writes_once_and_every_response_is_consistent(live, http):
    token = join(http, "storm")["token"]
    url = f"/api/p/{token}/state"
    reloads = [lambda: http.get(url)] * STORM

    # consent sent many times without a key, amid reloads: one 200, the rest 409 naming the step it moved to
    responses = storm([lambda: post(http, token, "consent", {"agree": True})] * STORM + reloads)
    posts, gets = responses[:STORM], responses[STORM:]
    assert sorted(r.status_code for r in posts) == [200] + [409] * (STORM - 1)
    for refused in (r for r in posts if r.status_code == 409):
        assert_conflict(refused, INSTRUCTIONS)
    assert {r.json()["phase"] for r in gets} <= {"consent", "instructions"}
    assert len(events_of(live, token, "consent")) == 1

    # one click retried with its Idempotency-Key: every copy gets the stored response
    responses = storm([lambda: post(http, token, "instructions/done", key="click-1")] * STORM + reloads)
    assert {r.status_code for r in responses} == {200}
    assert len({r.text for r in responses[:STORM]}) == 1
    assert {r.json()["phase"] for r in responses[STORM:]} <= {"instructions", "practice"}
    assert written(live, token)["stored_responses"] == 1
    steps = [e.payload for e in events_of(live, token, "step")]
    assert steps == [{"phase": "instructions"}, {"phase": "practice", "index": 0}]

    # a trial start re-sent (naturally idempotent): one trial row, every response shows that trial
    responses = storm([lambda: post(http, token, "trials/start", PRACTICE_1)] * STORM + reloads)
    assert {r.status_code for r in responses} == {200}
    for response in responses:
        shown = response.json()
        if shown["trial"] is None:  # a reload served before the start
            assert shown["ready_to_start"] == PRACTICE_1
        else:
            trial = shown["trial"]
            assert (trial["trial"], trial["robot_action"], trial["stage"]) == (1, "auto", "presenting")
    assert all(r.json()["trial"] for r in responses[:STORM])
    assert written(live, token)["trials"] == [(True, 0, 1, "presenting", None)]

    # a questionnaire page sent from reloaded pages (new keys) and retried ones (one key), all at once
    jump(live, token, AFTER_1, BLOCK_ORDER)
    page = state(http, token)["questionnaire"]
    body = page_answers(page)
    responses = storm([lambda: post(http, token, "answers", body)] * (STORM // 2)
                      + [lambda: post(http, token, "answers", body, key="page-1")] * (STORM // 2))
    accepted = [r for r in responses if r.status_code == 200]
    assert accepted and len({r.text for r in accepted}) == 1
    after = written(live, token)
    for refused in (r for r in responses if r.status_code != 200):
        assert_conflict(refused, after["step"])
    assert after["answers"] == len(page["items"])


# -- duplicated and reordered requests ------------------------------------------------------------------------------


def test_duplicated_requests_replay_the_stored_response_or_get_409_and_write_nothing(live, http):
    token = join(http, "duplicate")["token"]

    def once_and_again(what: str, body: Any, key: str, next_step: Step) -> None:
        """``what`` with a key, repeated with the key, then without it, then (with a body) the key with another body."""
        first = post(http, token, what, body, key=key)
        assert first.status_code == 200, first.text
        before = written(live, token)
        again = post(http, token, what, body, key=key)
        assert (again.status_code, again.json()) == (200, first.json())  # the stored response, nothing redone
        assert written(live, token) == before
        unkeyed = post(http, token, what, body)  # the same request with no key: refused, nothing written
        assert_conflict(unkeyed, next_step)
        assert written(live, token) == before
        if body is not None:
            other = post(http, token, what, body | {"agree": not body["agree"]}, key=key)
            assert other.status_code == 422 and "different request" in other.json()["detail"]
            assert written(live, token) == before

    once_and_again("consent", {"agree": True}, "consent-1", INSTRUCTIONS)
    once_and_again("instructions/done", None, "instructions-1", PracticeStep(index=0))

    started = post(http, token, "trials/start", PRACTICE_1)
    again = post(http, token, "trials/start", PRACTICE_1)  # naturally idempotent: the same trial, no second row
    assert again.status_code == 200 and again.json()["trial"] == started.json()["trial"] | {
        "scene_wait_ms_left": again.json()["trial"]["scene_wait_ms_left"]}
    assert len(written(live, token)["trials"]) == 1
    post(http, token, "trials/shown",
         PRACTICE_1 | {"view": "2d", "scene_stamp": started.json()["trial"]["scene_stamp"]})

    press = PRACTICE_1 | {"window_opened_ms": 100.0, "pressed_ms": 700.0}
    first = post(http, token, "trials/intervene", press, key="press-1")
    assert first.status_code == 200 and first.json()["trial"]["stage"] == "teleop"
    before = written(live, token)
    assert post(http, token, "trials/intervene", press, key="press-1").json() == first.json()
    unkeyed = post(http, token, "trials/intervene", press)
    assert_conflict(unkeyed, PracticeStep(index=0))
    assert "stage teleop" in unkeyed.json()["detail"] and written(live, token) == before

    jump(live, token, SHELF_1, BLOCK_ORDER)
    body = page_answers(state(http, token)["questionnaire"])
    first = post(http, token, "answers", body, key="shelf-1")
    assert first.status_code == 200
    before = written(live, token)
    assert post(http, token, "answers", body, key="shelf-1").json() == first.json()
    assert_conflict(post(http, token, "answers", body), before["step"])
    assert written(live, token) == before


def test_reordered_requests_get_409_naming_the_current_step_and_write_nothing(live, http):
    token = join(http, "reorder")["token"]
    to_practice(http, token)
    at = PracticeStep(index=0)

    def refused(what: str, body: Any, *, step: Step = at) -> httpx.Response:
        before = written(live, token)
        response = post(http, token, what, body)
        assert_conflict(response, step)
        assert written(live, token) == before
        return response

    # before trial 1 started: trial 2 cannot start, trial 1 cannot be intervened in, no questionnaire is asked
    refused("trials/start", PRACTICE_1 | {"trial": 2})
    refused("trials/intervene", PRACTICE_1)
    refused("answers", {"questionnaire": CONFIG.shelf_questionnaire, "answers": {}})
    # while trial 1's scene comes up, the window is not open: Intervene is refused
    presenting = post(http, token, "trials/start", PRACTICE_1).json()["trial"]
    assert presenting["stage"] == "presenting"
    refused("trials/intervene", PRACTICE_1)
    # during trial 1's decision window: trial 2 still cannot start, nor be intervened in
    shown = PRACTICE_1 | {"view": "2d", "scene_stamp": presenting["scene_stamp"]}
    assert post(http, token, "trials/shown", shown).json()["trial"]["stage"] == "decision"
    refused("trials/start", PRACTICE_1 | {"trial": 2})
    refused("trials/intervene", PRACTICE_1 | {"trial": 2})

    # the window closes: an intervene that arrives after it is refused; the robot attempts (rely)
    with live.app.state.services.sessionmaker.begin() as session:
        trial = session.scalar(select(Trial).where(Trial.practice.is_(True), Trial.trial == 1))
        trial.decision_deadline_at = utcnow() - timedelta(seconds=1)
    late = post(http, token, "trials/intervene", PRACTICE_1)
    assert late.status_code == 409 and "decision window has closed" in late.json()["detail"]
    state(http, token)  # the next request applies the closed window: the robot attempted it
    assert [(t[:3], t[4]) for t in written(live, token)["trials"]] == [((True, 0, 1), "rely")]

    # at the first shelf survey: answers meant for a later shelf, or another page, are refused
    jump(live, token, SHELF_1, BLOCK_ORDER)
    page = state(http, token)["questionnaire"]
    current = page_answers(page)
    refused("answers", current | {"context": "shelf:1:2"}, step=SHELF_1)
    refused("answers", current | {"context": "after:1"}, step=SHELF_1)
    refused("trials/start", {"practice": False, "block": 1, "trial": 4}, step=SHELF_1)
    assert post(http, token, "answers", current).status_code == 200
    assert written(live, token)["answers"] == len(page["items"])


# -- a websocket dropped mid-teleoperation ----------------------------------------------------------------------------


def teleop_url(live: Live, token: str) -> str:
    return "ws" + live.url[4:] + f"/api/p/{token}/teleop"


def send_inputs(ws: ClientConnection, n: int, first_client_ms: float) -> dict[str, Any] | None:
    """``n`` input messages (arm up), paced under the rate limit; each one's client_ms tags it in the log. Returns
    the latest world message seen."""
    world = None
    for i in range(n):
        ws.send(json.dumps({"type": "input", "seq": i, "client_ms": first_client_ms + i,
                            "ee_velocity": [0.0, 0.0, 0.05]}))
        while (reply := json.loads(ws.recv(timeout=30)))["type"] != "ack":
            world = reply if reply["type"] == "world" else world
        assert reply["ok"], reply
        time.sleep(1 / 30)
    return world


def drop(ws: ClientConnection) -> None:
    """Lose the connection without a close frame (a laptop lid shut, a network gone)."""
    ws.socket.shutdown(socket.SHUT_RDWR)
    with pytest.raises(ConnectionClosed):
        for _ in range(1000):  # world messages that arrived before the drop are still read
            ws.recv(timeout=10)
    assert ws.close_code == CloseCode.ABNORMAL_CLOSURE  # no close frame went either way
    ws.close()  # only releases the client's side now


def logged_client_ms(live: Live, token: str) -> set[float]:
    """The client times of every teleoperation input in the event log."""
    return {entry["client_ms"] for event in events_of(live, token, "teleop_log") for entry in event.payload["entries"]
            if "input" in entry}


def wait_logged(live: Live, token: str, client_ms: set[float]) -> None:
    deadline = time.monotonic() + 15
    while not client_ms <= logged_client_ms(live, token):
        assert time.monotonic() < deadline, f"commands {sorted(client_ms - logged_client_ms(live, token))} not logged"
        time.sleep(0.05)


def test_dropped_teleop_socket_resumes_from_the_servers_arm_and_after_a_restart_from_the_ready_pose(database_url):
    teleop_trial = {"practice": True, "block": 0, "trial": 3}  # the practice trial where the robot asks
    with live_server(database_url) as first, httpx.Client(base_url=first.url, timeout=30) as http:
        open_study(first)
        token = join(http, "drop")["token"]
        to_practice(http, token)
        jump(first, token, PracticeStep(index=2))
        assert post(http, token, "trials/start", teleop_trial).json()["trial"]["stage"] == "teleop"
        ws = connect(teleop_url(first, token))
        start = json.loads(ws.recv(timeout=30))["teleop"]["world"]
        send_inputs(ws, 10, 1000.0)
        drop(ws)
        wait_logged(first, token, {1000.0 + i for i in range(10)})  # the dropped socket's log was written

        def hello_world() -> dict[str, Any]:
            with connect(teleop_url(first, token)) as ws:
                return json.loads(ws.recv(timeout=30))["teleop"]["world"]

        moved = hello_world()  # reconnect: the arm is where the inputs left it, and it stopped with the socket
        assert moved["tcp"][2] > start["tcp"][2] + 0.01
        time.sleep(0.5)
        assert hello_world() == moved
        with connect(teleop_url(first, token)) as ws:
            ws.recv(timeout=30)
            send_inputs(ws, 5, 2000.0)
        wait_logged(first, token, {2000.0 + i for i in range(5)})
        deadline = written_deadline(first, token)

    with live_server(database_url) as second, httpx.Client(base_url=second.url, timeout=30) as http:
        with connect(teleop_url(second, token)) as ws:  # a new process: the arm starts again at the ready pose
            setup = json.loads(ws.recv(timeout=30))["teleop"]
            scene = build_scene(setup["scene"]["complexity"], int(setup["scene"]["seed"]),
                                setup["scene"]["target_slot"])
            assert setup["world"]["joints"] == pytest.approx(teleop_start_state(scene).joints, abs=1e-6)
            assert setup["world"] == start
        assert written_deadline(second, token) == deadline  # the time limit runs on from the trial's start
        bot = Bot(http, remote_sockets(second.url), "slow", paper_params(), 1, BotStats())
        bot.token = token
        bot.teleoperate()  # the scripted operator finishes the trial from there
        after = state(http, token)
        assert after["last_trial"]["trial"] == 3 and after["last_trial"]["teleop_success"] is True
        teleoperated = [t for t in written(second, token)["trials"] if t[:3] == (True, 0, 3)]
        assert teleoperated == [(True, 0, 3, "done", "intervene")]
        assert {1000.0 + i for i in range(10)} | {2000.0 + i for i in range(5)} <= logged_client_ms(second, token)
        assert len(events_of(second, token, "trial_completed")) == 1


def written_deadline(live: Live, token: str):
    with live.app.state.services.sessionmaker() as session:
        participant = participant_by_token(session, token)
        return session.scalar(select(Trial.teleop_deadline_at).where(Trial.participant_id == participant.id,
                                                                     Trial.stage == "teleop"))


# -- two tabs of one participant --------------------------------------------------------------------------------------


class Tab(Bot):
    """One of two browser tabs of the same participant: a 409 (the other tab was first) reloads the state."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.conflicts: list[str] = []
        self.steps: list[dict[str, Any]] = []

    def call(self, method: str, path: str, json_body: Any = None, key: bool = False) -> dict[str, Any]:
        result = super().call(method, path, json_body, key)
        if "step" in result or "state" in result:
            self.steps.append((result.get("state") or result)["step"])
        return result

    def post(self, what: str, body: Any = None, key: bool = True) -> dict[str, Any]:
        try:
            return super().post(what, body, key)
        except BotError as exc:
            if "-> 409:" not in str(exc) or what == "trials/intervene":  # the bot handles a late intervene itself
                raise
            self.conflicts.append(str(exc))
            return self.state()


def test_two_tabs_of_one_participant_make_one_consistent_session(database_url):
    with live_server(database_url) as live:
        open_study(live, "fast", demo_fast())
        tabs = [Tab(httpx.Client(base_url=live.url, timeout=30), remote_sockets(live.url), "fast", paper_params(), seed,
                    BotStats(), external_id="two-tabs") for seed in (1, 2)]
        results, threads = run_all(tabs)
        for thread in threads:
            thread.join(timeout=300)
        for tab in tabs:
            tab.http.close()
        assert results == [None, None]
        with live.app.state.services.sessionmaker() as session:
            participants = session.scalars(select(Participant)).all()
        assert len(participants) == 1 and participants[0].status == "completed" and tabs[0].token == tabs[1].token
        order = participants[0].block_order
        trials = written(live, tabs[0].token)
    steps = [step.model_dump() for step in all_steps(CONFIG, order)]  # as the API shows them
    practice, scored, answers = expected_records(CONFIG, order)
    assert len(set(t[:3] for t in trials["trials"])) == len(trials["trials"]) == practice + scored
    assert sum(not t[0] for t in trials["trials"]) == scored and {t[3] for t in trials["trials"]} == {"done"}
    assert trials["answers"] == answers
    for tab in tabs:  # each tab only ever saw the session move forward, and every refusal named the step
        positions = [steps.index(step) for step in tab.steps]
        assert positions == sorted(positions)
        assert all("the session is at" in conflict for conflict in tab.conflicts), tab.conflicts
    assert sum(len(tab.conflicts) for tab in tabs) > 0, "the tabs never raced"


# -- a participant idle past the abandonment time ----------------------------------------------------------------


def test_idle_participant_is_abandoned_refused_and_not_counted(database_url):
    with live_server(database_url, sweep_interval_s=0.1) as live, httpx.Client(base_url=live.url, timeout=30) as http:
        open_study(live)
        first_trial = {"practice": False, "block": 1, "trial": 1}

        def started(external_id: str) -> tuple[str, list[str]]:
            token = join(http, external_id)["token"]
            to_practice(http, token)
            jump(live, token, TrialStep(block=1, trial=1))
            assert post(http, token, "trials/start", first_trial).status_code == 200
            with live.app.state.services.sessionmaker() as session:
                return token, participant_by_token(session, token).block_order

        idle, idle_order = started("idle")
        _, other_order = started("busy")
        assert idle_order != other_order  # counterbalanced

        with live.app.state.services.sessionmaker.begin() as session:  # idle past the abandonment time
            participant_by_token(session, idle).last_seen_at = utcnow() - timedelta(seconds=TIMING.idle_timeout_s + 1)
        deadline = time.monotonic() + 15
        while written(live, idle)["status"] != "abandoned":
            assert time.monotonic() < deadline, "the sweeper did not mark the idle session abandoned"
            time.sleep(0.05)
        assert len(events_of(live, idle, "abandoned")) == 1
        before = written(live, idle)

        for what, body in [("consent", {"agree": True}), ("instructions/done", None), ("trials/start", first_trial),
                           ("trials/intervene", first_trial), ("answers", {"questionnaire": "x", "answers": {}}),
                           ("heartbeat", {}), ("events", {"events": [{"kind": "focus"}]})]:
            refused = post(http, idle, what, body)
            assert refused.status_code == 410 and "inactive for too long" in refused.json()["detail"], (what,
                                                                                                        refused.text)
        assert state(http, idle)["phase"] == "abandoned"  # the page can still show why it ended
        with connect(teleop_url(live, idle)) as ws, pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)
        assert ws.close_code == 4404 and "inactive for too long" in ws.close_reason
        again = join(http, "idle")  # the same join link: the same (ended) session, not a second one
        assert (again["token"], again["created"], again["state"]["phase"]) == (idle, False, "abandoned")
        assert written(live, idle) == before

        newcomer, newcomer_order = started("newcomer")  # the abandoned session's order is free again
        assert newcomer_order == idle_order
        with live.app.state.services.sessionmaker() as session:
            assert session.scalar(select(func.count()).select_from(Participant)) == 3
            assignment = participant_by_token(session, newcomer).assignment
        counts = {tuple(order): n for order, n in assignment["counts_before"]}
        assert counts == {tuple(idle_order): 0, tuple(other_order): 1}
