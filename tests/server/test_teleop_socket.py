"""The teleoperation socket: server-paced motion, dead-man stop, the published contract, the guided practice."""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from datetime import timedelta

import numpy as np
import pytest
from sqlalchemy import select
from starlette.websockets import WebSocketDisconnect

from experiment.flow import PracticeStep, TrialRef
from experiment.world import build_scene, teleop_start_state
from experiment.world.path import bin_release_point
from experiment.world.robot import arm_points, solve_ik
from experiment.world.teleop import TeleopCommand, _with_joints, hold_command
from server.harness.teleop_client import CheckedSocket
from server.models import Event, Participant, Trial, utcnow
from server.settings import Settings
from server.world.hub import WorldHub
from server.world.teleop import DEADMAN_S, MAX_ADVANCE_PERIODS, TrialKey
from tests.server.factories import join, make_client, make_study

ASKS = 2  # index of the default practice trial where the robot asks (low complexity)


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    return client, admin


def at_practice(client, token: str, index: int) -> dict:
    """Consent, then start practice trial ``index`` (0-based) directly."""
    client.post(f"/api/p/{token}/consent", json={"agree": True})
    with client.app.state.services.sessionmaker.begin() as session:
        session.scalar(select(Participant).where(Participant.status == "active",
                                                 Participant.step["phase"].as_string() != "practice")
                       ).step = PracticeStep(index=index)
    response = client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": index + 1})
    assert response.status_code == 200, response.text
    return response.json()


def teleoperating(client) -> tuple[str, str]:
    """A new participant at the practice trial where the robot asks: its token and public id."""
    token = join(client)["token"]
    at_practice(client, token, ASKS)
    with client.app.state.services.sessionmaker() as session:
        return token, session.scalar(select(Participant.public_id))


def tcp(world: dict) -> np.ndarray:
    return np.array(world["tcp"])


# -- the hub: the arm moves on the server's clock ------------------------------------------------------------------
def hub_session(speed: float = 1.0):
    hub = WorldHub(Settings(database_url="sqlite://", world_loop=False, planner_processes=0))
    scene = build_scene("low", 3)
    teleop = hub.teleop(TrialKey("p", TrialRef(True, 0, 3)), scene, speed=speed)
    return hub, teleop


@pytest.mark.parametrize("rate_hz", [2, 10, 60])
def test_the_arm_moves_as_far_per_second_whatever_the_message_rate(rate_hz):
    hub, teleop = hub_session()
    t0 = teleop.advanced_at
    start = np.array(arm_points(teleop.state.base, teleop.state.joints).tcp)
    hub.arms.set_input(teleop, TeleopCommand(ee_velocity=(0.0, 0.1, 0.0)), seq=0, client_ms=None, now=t0)
    for i in range(1, rate_hz):  # keep-alives at the rate, for one second
        hub.arms.keepalive(teleop, now=t0 + i / rate_hz)
    hub.arms.set_input(teleop, TeleopCommand(), seq=1, client_ms=None, now=t0 + 1.0)
    hub.arms.advance(teleop, t0 + 3.0)  # released: nothing more moves
    moved = np.array(arm_points(teleop.state.base, teleop.state.joints).tcp) - start
    assert moved[1] == pytest.approx(0.1, abs=0.004) and abs(moved[0]) < 0.01 and abs(moved[2]) < 0.01


def test_ticks_and_messages_move_the_arm_alike():
    """Advancing in 30 Hz ticks or only when the input changes gives the same arm; keep-alives move nothing."""
    arms = []
    for ticks in (True, False):
        hub, teleop = hub_session()
        t0 = teleop.advanced_at
        hub.arms.set_input(teleop, TeleopCommand(ee_velocity=(0.05, 0.0, -0.1)), seq=0, client_ms=None, now=t0)
        for i in range(1, 16):
            if ticks:
                hub.arms.advance(teleop, t0 + i / 30)
            else:  # a page's keep-alives and repeated inputs: the held input is unchanged, nothing is computed
                state = teleop.state
                hub.arms.keepalive(teleop, now=t0 + i / 30)
                hub.arms.set_input(teleop, TeleopCommand(ee_velocity=(0.05, 0.0, -0.1)), seq=i, client_ms=None,
                              now=t0 + i / 30 + 0.001)
                assert teleop.state is state
        hub.arms.set_input(teleop, TeleopCommand(), seq=99, client_ms=None, now=t0 + 0.5)  # released
        arms.append(np.array(teleop.state.joints))
    assert np.allclose(arms[0], arms[1], atol=2e-3)
    assert not np.allclose(arms[0], teleop_start_state(teleop.scene).joints, atol=0.05)


def test_a_held_input_stops_at_the_dead_man_time():
    hub, teleop = hub_session()
    t0 = teleop.advanced_at
    hub.arms.set_input(teleop, TeleopCommand(ee_velocity=(0.0, 0.1, 0.0)), seq=0, client_ms=None, now=t0)
    for t in np.arange(0.05, 3.0, 1 / 30):  # the server's ticks go on; no message arrives
        hub.arms.advance(teleop, t0 + t)
    start = teleop_start_state(teleop.scene)
    moved = arm_points(teleop.state.base, teleop.state.joints).tcp[1] - arm_points(start.base, start.joints).tcp[1]
    assert moved == pytest.approx(0.1 * DEADMAN_S, abs=0.004)
    assert not teleop.moving and any(entry.get("event") == "deadman_stop" for entry in teleop.log)


def test_a_keepalive_after_a_dead_man_stop_resumes_the_held_input():
    hub, teleop = hub_session()
    t0 = teleop.advanced_at
    hub.arms.set_input(teleop, TeleopCommand(ee_velocity=(0.0, 0.1, 0.0)), seq=0, client_ms=None, now=t0)
    hub.arms.advance(teleop, t0 + 2.0)  # the page stalled: stopped at the dead-man time
    assert not teleop.moving
    hub.arms.keepalive(teleop, now=t0 + 2.0)  # it is back, the key still held
    assert teleop.moving
    hub.arms.set_input(teleop, TeleopCommand(), seq=1, client_ms=None, now=t0 + 2.5)
    start = teleop_start_state(teleop.scene)
    moved = arm_points(teleop.state.base, teleop.state.joints).tcp[1] - arm_points(start.base, start.joints).tcp[1]
    assert moved == pytest.approx(0.1 * (DEADMAN_S + 0.5), abs=0.004)


def test_a_late_world_loop_moves_the_arm_less_and_logs_the_time_it_lost():
    """While the world loop runs, an advance makes up for at most MAX_ADVANCE_PERIODS of it: a saturated server
    must not do more physics the later its ticks come (that spiral froze it at 100 participants). The time lost
    is logged, so the inputs, their times and the lost time still reconstruct the arm's motion."""
    hub, teleop = hub_session(speed=2.0)
    hub.ticking = True  # as while WorldHub.run ticks
    period = 1 / hub.settings.world_hz
    held = TeleopCommand(ee_velocity=(0.0, 0.1, 0.0))
    t0 = teleop.advanced_at
    hub.arms.set_input(teleop, held, seq=0, client_ms=None, now=t0)
    expected = teleop.state
    for i in range(1, 6):  # ticks on time: every interval integrated whole
        hub.arms.advance(teleop, t0 + i * period)
        expected, _ = hold_command(expected, teleop.scene, held, period * 2.0)
        assert _same_state(teleop.state, expected)
    late = 0.3
    hub.arms.advance(teleop, t0 + 5 * period + late)  # a tick 0.3 s after the last one
    expected, _ = hold_command(expected, teleop.scene, held, MAX_ADVANCE_PERIODS * period * 2.0)
    assert _same_state(teleop.state, expected)
    hub.arms.advance(teleop, t0 + 6 * period + late)  # on time again
    expected, _ = hold_command(expected, teleop.scene, held, period * 2.0)
    assert _same_state(teleop.state, expected)
    hub.arms.set_input(teleop, TeleopCommand(), seq=1, client_ms=None, now=t0 + 6 * period + late)  # released
    log = teleop.log.take()
    lags = [entry for entry in log if entry.get("event") == "server_lag"]
    assert len(lags) == 1 and lags[0]["lost_ms"] == pytest.approx((late - MAX_ADVANCE_PERIODS * period) * 1000, abs=0.2)
    assert log.index(lags[0]) < [entry.get("seq") for entry in log].index(1)  # logged before the release
    # Reconstructed from the log: held from seq 0 to seq 1, less the lost time.
    held_ms = log[-1]["server_ms"] - log[0]["server_ms"] - lags[0]["lost_ms"]
    rebuilt, _ = hold_command(teleop_start_state(teleop.scene), teleop.scene, held, held_ms / 1000 * 2.0)
    assert np.allclose(rebuilt.joints, teleop.state.joints, atol=1e-3)
    # Without a world loop (messages advance the arm), a late message still makes up for up to MAX_ADVANCE_S.
    hub, teleop = hub_session(speed=2.0)
    t0 = teleop.advanced_at
    hub.arms.set_input(teleop, held, seq=0, client_ms=None, now=t0)
    hub.arms.advance(teleop, t0 + late)
    assert _same_state(teleop.state, hold_command(teleop_start_state(teleop.scene), teleop.scene, held, late * 2.0)[0])
    assert not any(entry.get("event") == "server_lag" for entry in teleop.log.take())


def _same_state(a, b) -> bool:
    """Equal but for the rounding of clock differences."""
    return np.isclose(a.t, b.t, atol=1e-9) and np.allclose(a.joints, b.joints, atol=1e-9) and a.item == b.item


def test_a_closed_socket_stops_the_arm_at_once():
    hub, teleop = hub_session()
    t0 = teleop.advanced_at
    hub.arms.set_input(teleop, TeleopCommand(ee_velocity=(0.0, 0.1, 0.0)), seq=0, client_ms=None, now=t0)
    hub.arms.release(teleop, now=t0 + 0.2)
    joints = teleop.state.joints
    hub.arms.advance(teleop, t0 + 0.6)
    assert teleop.state.joints == joints and not teleop.moving


# -- the socket ----------------------------------------------------------------------------------------------------
def test_the_contract_is_served_and_unknown_sessions_are_refused(api):
    client, _ = api
    schema = client.get("/api/schema/teleop.json").json()
    assert {"client_to_server", "server_to_client"} <= set(schema["properties"]) and "InputMessage" in schema["$defs"]
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect("/api/p/" + "x" * 32 + "/teleop") as ws:
            ws.receive_text()
    assert closed.value.code == 4404


def test_a_socket_opened_outside_teleoperation_says_so_and_closes(api):
    client, _ = api
    token = join(client)["token"]
    at_practice(client, token, 0)  # the robot will try by itself: a decision window, no teleoperation
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        hello = ws.receive()
        assert hello["type"] == "hello" and hello["stage"] != "teleop" and hello["teleop"] is None
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive()
    assert closed.value.code == 1000


def test_the_hello_carries_what_a_client_needs_to_steer(api):
    client, _ = api
    token = join(client)["token"]
    state = at_practice(client, token, ASKS)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        hello = CheckedSocket(raw).receive()
    setup = hello["teleop"]
    assert hello["stage"] == "teleop" and hello["trial"] == {"practice": True, "block": 0, "trial": ASKS + 1,
                                                             "complexity": "low"}
    scene = build_scene("low", int(setup["scene"]["seed"]))
    target = setup["scene"]["target"]
    assert np.allclose(target["grasp_point"], scene.target.grasp_point(), atol=1e-6)
    assert target["description"] in state["trial"]["message"] and target["description"] == state["trial"]["target"]
    assert np.allclose(setup["scene"]["bin"]["release_point"], bin_release_point(scene, scene.park), atol=1e-6)
    assert setup["limits"]["grasp_radius"] == pytest.approx(0.04) and setup["limits"]["deadman_s"] == DEADMAN_S
    start = teleop_start_state(scene)
    assert np.allclose(setup["world"]["tcp"], arm_points(start.base, start.joints).tcp, atol=1e-6)
    assert setup["guidance"]["step"] == "move_above_item" and not setup["guidance"]["can_grasp"]
    assert setup["tutorial"] == {"try_number": 1, "max_tries": 3}  # the participant's first teleoperation


def test_inputs_move_the_arm_on_the_servers_clock_and_are_logged(api):
    client, _ = api
    token, _ = teleoperating(client)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        start = tcp(ws.receive()["teleop"]["world"])
        ws.send_raw("not json")
        assert not ws.receive_until("ack")["ok"]
        ws.send_raw('{"type": "input", "seq": 1, "ee_velocity": [0, "a", 0]}')
        bad = ws.receive_until("ack")
        assert bad["seq"] == 1 and not bad["ok"] and "ee_velocity" in bad["error"]
        ws.send_raw('{"type": "input", "seq": 2, "ee_velocity": [0, 0, 0.1], "joint_velocity": [0, 0, 0, 0]}')
        assert "not both" in ws.receive_until("ack")["error"]
        assert ws.input(3, ee_velocity=[0.0, 0.0, 0.2], client_ms=12.5)["ok"]  # one message: the arm keeps rising
        risen = start
        deadline = time.monotonic() + 5
        while risen[2] - start[2] < 0.05 and time.monotonic() < deadline:
            world = ws.receive_until("world")
            risen = tcp(world["world"])
            assert world["input_seq"] == 3 and world["moving"]
        assert risen[2] - start[2] >= 0.05
        assert ws.input(4, client_ms=20.0)["ok"]  # released
    entries = []
    for _ in range(100):  # the log is written when the socket closes, just after we leave
        with client.app.state.services.sessionmaker() as session:
            entries = [e for ev in session.scalars(select(Event).where(Event.kind == "teleop_log")) for e in
                       ev.payload["entries"]]
        if any(e.get("seq") == 4 for e in entries):
            break
        time.sleep(0.05)
    inputs = [e for e in entries if "input" in e]
    assert [(e["seq"], e["client_ms"], e["input"]) for e in inputs] == [(3, 12.5, {"ee_velocity": [0.0, 0.0, 0.2]}),
                                                                       (4, 20.0, {})]
    assert inputs[1]["server_ms"] > inputs[0]["server_ms"]


def test_every_open_teleoperations_log_is_written_together_about_once_a_second(api, monkeypatch):
    """One unit of work a second writes the new entries of all open sockets (not one unit per socket), while they
    are still open."""
    from server.services import teleop_log as log_writer_module

    client, _ = api
    written: list[list[str]] = []
    real = log_writer_module._log_batches

    def spy(session, batches):
        written.append(sorted(token for token, _, _ in batches))
        real(session, batches)

    monkeypatch.setattr(log_writer_module, "_log_batches", spy)
    tokens = [teleoperating(client)[0] for _ in range(2)]

    def logged() -> set[float]:
        with client.app.state.services.sessionmaker() as session:
            return {entry["client_ms"] for event in session.scalars(select(Event).where(Event.kind == "teleop_log"))
                    for entry in event.payload["entries"] if "input" in entry}

    with client:  # the app's lifespan runs the writer
        with client.websocket_connect(f"/api/p/{tokens[0]}/teleop") as a, \
                client.websocket_connect(f"/api/p/{tokens[1]}/teleop") as b:
            first, second = CheckedSocket(a), CheckedSocket(b)
            first.receive(), second.receive()  # hello
            assert first.input(1, ee_velocity=[0.0, 0.0, 0.1], client_ms=1.0)["ok"]
            assert second.input(1, ee_velocity=[0.0, 0.0, 0.1], client_ms=2.0)["ok"]
            deadline = time.monotonic() + 10
            while sorted(tokens) not in written:
                assert time.monotonic() < deadline, written
                time.sleep(0.05)
            assert logged() == {1.0, 2.0}  # in the database while both sockets are open
            assert first.input(2, client_ms=3.0)["ok"] and second.input(2, client_ms=4.0)["ok"]
    assert logged() == {1.0, 2.0, 3.0, 4.0}  # the sockets' own last writes: the app's shutdown waited for them


def test_a_closing_sockets_last_log_write_is_done_before_the_server_stops(api, monkeypatch):
    """A socket writes its last log entries when it closes, in a worker thread that a cancelled socket task does not
    stop; a server stopping meanwhile waits for that write before it disposes of the connection pool. Otherwise the
    write returned its connection into a pool that was gone, where no one closed it (PostgreSQL: a ResourceWarning
    when it was collected, during some later test)."""
    from server.services import teleop_log as log_writer_module

    client, _ = api
    real, closing, events = log_writer_module._log_batches, threading.Event(), []

    def slow(session, batches):
        closing.set()
        time.sleep(0.5)  # the server is asked to stop while this write runs
        real(session, batches)
        events.append("written")

    engine = client.app.state.services.engine
    real_dispose = engine.dispose

    def dispose(*args, **kwargs):
        events.append(f"dispose with {engine.pool.checkedout()} connections out")
        real_dispose(*args, **kwargs)

    monkeypatch.setattr(engine, "dispose", dispose)
    monkeypatch.setattr(log_writer_module, "LOG_FLUSH_S", 3600.0)  # only the socket's close writes its log
    token, _ = teleoperating(client)
    with client:
        with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
            ws = CheckedSocket(raw)
            ws.receive()  # hello
            assert ws.input(1, ee_velocity=[0.0, 0.0, 0.1], client_ms=7.0)["ok"]
            monkeypatch.setattr(log_writer_module, "_log_batches", slow)
        assert closing.wait(10)
    assert events == ["written", "dispose with 0 connections out"]
    with client.app.state.services.sessionmaker() as session:
        logged = [entry["client_ms"] for event in session.scalars(select(Event).where(Event.kind == "teleop_log"))
                  for entry in event.payload["entries"] if "input" in entry]
    assert logged == [7.0]


def test_a_teleoperation_log_that_could_not_be_written_is_kept_for_the_next_write(api, monkeypatch):
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from server.services import teleop_log as log_writer_module

    client, _ = api
    token, _ = teleoperating(client)
    hub, teleop = hub_session()
    gone = hub.teleop(TrialKey("q", TrialRef(True, 0, 3)), teleop.scene)  # a session deleted meanwhile (a preview)
    for arm, entries in ((teleop, [{"server_ms": 1.0, "event": "grasped"}, {"server_ms": 2.0, "event": "dropped"}]),
                         (gone, [{"server_ms": 1.0, "event": "grasped"}])):
        for entry in entries:
            arm.log.append(entry)
    failing = [True]

    async def flaky_unit(work, owner=None):
        if failing[0]:
            raise OSError("disk full")
        with client.app.state.services.sessionmaker.begin() as session:
            return work(session)

    writer = log_writer_module.TeleopLogWriter(client.app.state.services.database, client.app.state.services.faults)
    monkeypatch.setattr(writer.database, "run", flaky_unit)
    writer.watch(token, teleop)
    writer.watch("no-such-token", gone)
    with ThreadPoolExecutor(1) as pool:
        pool.submit(asyncio.run, writer.flush()).result()  # the write fails, together and each alone
        assert [entry["event"] for entry in teleop.log] == ["grasped", "dropped"]  # kept, in order
        teleop.log.append({"server_ms": 3.0, "event": "deposited"})
        failing[0] = False
        pool.submit(asyncio.run, writer.flush()).result()
    assert list(teleop.log) == [] and list(gone.log) == []
    with client.app.state.services.sessionmaker() as session:
        events = session.scalars(select(Event).where(Event.kind == "teleop_log")).all()
    assert [[entry["event"] for entry in event.payload["entries"]] for event in events] == [
        ["grasped", "dropped", "deposited"]]


def test_past_the_rate_limit_a_release_is_still_taken(api):
    client, _ = api
    token, _ = teleoperating(client)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        ws.receive()
        for seq in range(30):  # a burst far above the limit, sent without waiting for the acks
            ws.send({"type": "input", "seq": seq, "ee_velocity": [0.0, 0.0, 0.1]})
        acks = [ws.receive_until("ack") for _ in range(30)]
        refused = [ack for ack in acks if not ack["ok"]]
        # the bucket refills as time passes, so on a slow machine the last of the burst may be taken again
        assert refused and all("too many" in ack["error"] for ack in refused)
        assert ws.input(30)["ok"]  # letting go is never refused
        while (world := ws.receive_until("world"))["input_seq"] != 30:
            pass
        assert world["moving"] is False


def put_item_over_the_bin(client, public_id: str) -> None:
    """Skip the steering: grasp the item where it stands and hold it over the bin (through the server's hub)."""
    hub: WorldHub = client.app.state.services.hub
    teleop = hub.arms.get(public_id)
    scene = teleop.scene
    at_item = replace(teleop.state, joints=tuple(solve_ik(scene.park, scene.target.grasp_point()).tolist()))
    grasped, events = hold_command(at_item, scene, TeleopCommand(gripper="close"), 0.5)
    assert "grasped" in events
    over_bin = tuple(solve_ik(scene.park, bin_release_point(scene, scene.park)).tolist())
    teleop.state = _with_joints(grasped, over_bin)


def test_a_deposit_completes_the_trial_before_over_is_sent(api):
    client, _ = api
    token, public_id = teleoperating(client)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        ws.receive()
        put_item_over_the_bin(client, public_id)
        ws.send({"type": "input", "seq": 1, "gripper": "open"})
        assert ws.receive_until("ack")["ok"]
        world = ws.receive_until("world")
        assert "deposited" in world["events"] and world["guidance"]["step"] == "done"
        over = ws.receive_until("over")
        assert over == {"type": "over", "reason": "deposited", "trial_recorded": True, "retry": False}
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive()
        assert closed.value.code == 1000
    state = client.get(f"/api/p/{token}/state").json()
    assert state["last_trial"]["teleop_success"] is True and state["step"] == {"phase": "practice", "index": ASKS + 1}


def expire(client, token: str) -> dict:
    """Let the teleoperation's time run out (the next look at the session, here its state, applies it)."""
    with client.app.state.services.sessionmaker.begin() as session:
        row = session.scalar(select(Trial).where(Trial.stage == "teleop"))
        row.teleop_deadline_at = utcnow() - timedelta(seconds=1)
    return client.get(f"/api/p/{token}/state").json()


def test_the_guided_practice_starts_over_until_its_tries_are_used_up(api):
    client, _ = api
    token = join(client)["token"]
    state = at_practice(client, token, ASKS)
    assert state["trial"]["tutorial"] == {"try_number": 1, "max_tries": 3}
    assert state["tutorial"]["max_tries"] == 3 and state["teleop_time_limit_s"] > 0
    with client.app.state.services.sessionmaker() as session:
        public_id = session.scalar(select(Participant.public_id))
    hub: WorldHub = client.app.state.services.hub
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        ws.receive()
        ws.input(1, ee_velocity=[0.0, 0.0, 0.2])
        ws.receive_until("world")
        state = expire(client, token)
        over = ws.receive_until("over")
        assert over["reason"] == "time_limit" and over["retry"] is True
    assert state["trial"]["stage"] == "teleop" and state["trial"]["tutorial"] == {"try_number": 2, "max_tries": 3}
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:  # the new try starts at the ready pose
        hello = CheckedSocket(raw).receive()
    assert hello["teleop"]["tutorial"]["try_number"] == 2
    scene = hub.arms.get(public_id).scene
    assert hello["teleop"]["world"]["joints"] == pytest.approx(list(teleop_start_state(scene).joints), abs=1e-6)
    assert expire(client, token)["trial"]["tutorial"]["try_number"] == 3
    state = expire(client, token)  # tries used up: the trial counts as failed, practice goes on
    assert state["last_trial"]["teleop_success"] is False and state["step"] == {"phase": "practice", "index": ASKS + 1}
    with client.app.state.services.sessionmaker() as session:
        row = session.scalar(select(Trial).where(Trial.trial == ASKS + 1))
        assert row.tutorial and row.teleop_tries == 3
        kinds = [e.kind for e in session.scalars(select(Event).order_by(Event.id))]
    assert kinds.count("teleop_timeout") == 3 and kinds.count("teleop_retry") == 2


def test_a_teleoperation_that_runs_out_of_time_is_over(api):
    client, _ = api
    token = join(client)["token"]
    at_practice(client, token, ASKS)
    with client.app.state.services.sessionmaker.begin() as session:  # the first teleoperation, but not guided
        session.scalar(select(Trial)).tutorial = False
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        ws.receive()
        state = expire(client, token)
        assert ws.receive_until("over") == {"type": "over", "reason": "time_limit", "trial_recorded": False,
                                            "retry": False}
    assert state["last_trial"]["teleop_success"] is False


def test_only_teleoperations_before_the_first_deposit_are_guided(api):
    client, _ = api
    token, public_id = teleoperating(client)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        ws.receive()
        put_item_over_the_bin(client, public_id)
        ws.input(1, gripper="open")
        ws.receive_until("over")
    state = client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": ASKS + 2}).json()
    assert state["trial"]["stage"] == "teleop" and state["trial"]["tutorial"] is None
    assert state["trial"]["teleop_ms_left"] <= state["teleop_time_limit_s"] * 1000


def test_assistance_from_the_study_config_aligns_the_gripper(database_url):
    from tests.server.factories import fast_config
    config = fast_config()
    config = config.model_copy(update={"teleop": config.teleop.model_copy(update={"align_radius_m": 0.12})})
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=config)
    token, public_id = teleoperating(client)
    hub: WorldHub = client.app.state.services.hub
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw)
        setup = ws.receive()["teleop"]
        assert setup["limits"]["align_radius"] == pytest.approx(0.12)
        teleop = hub.arms.get(public_id)
        scene = teleop.scene
        near = scene.target.grasp_point() + np.array([-0.05, 0.03, 0.04])  # 7 cm off: no grasp without help
        teleop.state = replace(teleop.state, joints=tuple(solve_ik(scene.park, near).tolist()))
        ws.input(1, gripper="close")
        world = ws.receive_until("world")
    assert {"aligned", "grasped"} <= set(world["events"]) and world["world"]["item"]["mode"] == "grasped"
    with client.app.state.services.sessionmaker() as session:
        row = session.scalar(select(Trial).where(Trial.trial == ASKS + 1))
        assert row.align_radius_m == pytest.approx(0.12) and row.grasp_radius_m == pytest.approx(0.04)


def test_the_hello_announces_the_world_rate_the_socket_gets():
    """The socket pushes right after the world loop's ticks: it announces no more world messages a second than the
    loop ticks (a client that closes its loop through the socket sizes its gain by it)."""
    from types import SimpleNamespace

    from server.services.teleop import TeleopChannel

    settings = Settings(database_url="sqlite://", teleop_world_hz=60.0, world_hz=30.0)
    hub = SimpleNamespace(ticking=True)
    channel = TeleopChannel(SimpleNamespace(hub=hub, settings=settings, teleop_log=None, database=None, runtimes=None),  # type: ignore[arg-type]
                            "t" * 32)
    assert channel.world_hz() == 30.0
    hub.ticking = False  # no loop: the socket's own timer advances and pushes
    assert channel.world_hz() == 60.0
