"""One hostile or broken client cannot harm a study (issue 36): the sockets' messages bounded by their schema, and a
failure in one participant's part of a background loop contained to that participant.

Each test here failed on the code before it: a teleoperation input of ``1e309`` was acked and stopped the world
loop for everyone, binary and deep frames raised in the handler, one failing sweep or log write held back the
others, and a page of any origin could open the sockets.
"""

from __future__ import annotations

import asyncio
import json
import time
from datetime import timedelta
from typing import Any

import jsonschema
import pytest
import viser
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import select
from starlette.websockets import WebSocketDisconnect

from experiment.flow import TrialRef
from server import strict_json
from server.faults import FaultLog, supervised
from server.harness.teleop_client import CheckedSocket
from server.loadmeter import LoadFigures, load_status
from server.models import Event, Participant, utcnow
from server.routes.teleop import BINARY_REFUSED
from server.services import teleop_log as log_writer_module
from server.sweeper import sweep
from server.teleop_messages import json_schema
from server.world import teleop as world_module
from server.world.teleop import TrialKey
from tests.server.factories import auth, join, make_client, make_study
from tests.server.test_teleop_socket import hub_session, tcp, teleoperating

CLIENT_SCHEMA = json_schema()
CLIENT_VALIDATOR = jsonschema.Draft202012Validator(
    {**CLIENT_SCHEMA["properties"]["client_to_server"], "$defs": CLIENT_SCHEMA["$defs"]})
NON_FINITE = ["NaN", "Infinity", "-Infinity", "1e309", "-1e400"]


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url, teleop_rate_limit_hz=10_000.0)
    make_study(client, admin)
    return client, admin


def numeric_fields() -> list[tuple[str, str, int | None, dict]]:
    """(message type, field, index in a tuple or None, the number's schema) of every number a client sends."""
    found = []
    for name in ("InputMessage", "KeepAliveMessage"):
        definition = CLIENT_SCHEMA["$defs"][name]
        kind = definition["properties"]["type"]["const"]
        for field, spec in definition["properties"].items():
            for option in spec.get("anyOf", [spec]):
                if option.get("type") in ("number", "integer"):
                    found.append((kind, field, None, option))
                for index, item in enumerate(option.get("prefixItems", [])):
                    found.append((kind, field, index, item))
    return found


def message_text(kind: str, field: str, index: int | None, value_text: str) -> str:
    """A message of ``kind`` valid but for ``field`` (element ``index``), written as the raw JSON ``value_text``."""
    base: dict[str, Any] = {"type": kind, "seq": 7}
    if index is not None:
        base[field] = [0.0] * (3 if field == "ee_velocity" else 4)
        base[field][index] = "@@"
    else:
        base[field] = "@@"
    return json.dumps(base).replace('"@@"', value_text)


def test_every_number_of_every_client_message_refuses_non_finite_and_out_of_range_values(api):
    client, _ = api
    token, public_id = teleoperating(client)
    fields = numeric_fields()
    assert {(k, f) for k, f, _, _ in fields} >= {("input", "seq"), ("input", "client_ms"), ("input", "ee_velocity"),
                                                  ("input", "joint_velocity"), ("keepalive", "seq")}
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw, check_sent=False)
        ws.receive()
        for kind, field, index, spec in fields:
            bad = [*NON_FINITE, repr(spec["maximum"] * 10 + 1), repr(spec["minimum"] * 10 - 1)]
            for value in bad:
                ws.send_raw(message_text(kind, field, index, value))
                ack = ws.receive_until("ack")
                assert ack["ok"] is False, (kind, field, index, value)
        assert ws.input(8, ee_velocity=[0.0, 0.0, 0.1], client_ms=3.0)["ok"]  # the socket serves on
        assert ws.input(9)["ok"]
    hub = client.app.state.services.hub
    with client.app.state.services.sessionmaker() as session:
        logged = [entry for event in session.scalars(select(Event).where(Event.kind == "teleop_log"))
                  for entry in event.payload["entries"]]
    strict_json.check(logged)  # only finite numbers reached the log
    assert [entry["seq"] for entry in logged if "seq" in entry] == [8, 9]
    assert not hub.faults.recent()


def test_binary_and_deeply_nested_frames_are_answered_and_the_socket_serves_on(api):
    client, _ = api
    token, _ = teleoperating(client)
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw, check_sent=False)
        ws.receive()
        raw.send_bytes(b'{"type": "keepalive", "seq": 1}')
        assert ws.receive_until("ack") == {"type": "ack", "seq": None, "ok": False, "error": BINARY_REFUSED}
        ws.send_raw("[" * 2000 + "]" * 2000)
        deep = ws.receive_until("ack")
        assert deep["ok"] is False and deep["seq"] is None
        ws.send_raw('{"type": "keepalive", "seq": 2, "x": ' + "[" * 1500 + "]" * 1500 + "}")
        assert ws.receive_until("ack")["ok"] is False
        ws.send_raw('{"type": "input", "seq": "3"}')  # as strictly as HTTP: a number is a JSON number
        assert ws.receive_until("ack")["ok"] is False
        ws.send_raw('{"type": "keepalive", "seq": 3, "pad": "' + "x" * 5000 + '"}')
        assert ws.receive_until("ack") == {"type": "ack", "seq": None, "ok": False,
                                           "error": "message larger than 4096 bytes"}
        assert ws.input(4, ee_velocity=[0.0, 0.0, 0.1])["ok"]
    assert not client.app.state.services.hub.faults.recent()


# -- a fuzz test of the protocol from its JSON Schema ---------------------------------------------------------------
def from_schema(spec: dict) -> st.SearchStrategy:
    """Values valid under ``spec`` (the subset of JSON Schema the socket's messages use)."""
    if "$ref" in spec:
        return st.deferred(lambda: from_schema(CLIENT_SCHEMA["$defs"][spec["$ref"].rsplit("/", 1)[1]]))
    if "const" in spec:
        return st.just(spec["const"])
    if "enum" in spec:
        return st.sampled_from(spec["enum"])
    for combinator in ("anyOf", "oneOf"):
        if combinator in spec:
            return st.one_of([from_schema(option) for option in spec[combinator]])
    kind = spec.get("type")
    if kind == "null":
        return st.none()
    if kind == "boolean":
        return st.booleans()
    if kind == "number":
        return st.floats(spec.get("minimum"), spec.get("maximum"), allow_nan=False, allow_infinity=False)
    if kind == "integer":
        return st.integers(spec.get("minimum"), spec.get("maximum"))
    if kind == "string":
        return st.text(max_size=20)
    if kind == "array":
        return st.tuples(*(from_schema(item) for item in spec["prefixItems"])).map(list)
    if kind == "object":
        required = set(spec.get("required", ()))
        optional = {name: from_schema(s) for name, s in spec["properties"].items() if name not in required}
        return st.fixed_dictionaries({name: from_schema(spec["properties"][name]) for name in required},
                                     optional=optional)
    raise AssertionError(f"a schema the fuzzer does not know: {spec}")


NASTY = st.one_of(st.sampled_from(["NaN", "Infinity", "-Infinity", "1e309", "9007199254740993", '"\\ud800"',
                                   "true", "null", '"1"', "[" * 300 + "]" * 300, "{}", "[]", "-0.0", "1.0"]),
                  st.integers().map(str), st.floats(allow_nan=False, allow_infinity=False).map(repr),
                  st.text(max_size=10).map(json.dumps))


@st.composite
def client_frames(draw) -> str:
    """A message the schema allows, or one mutated at one place (a value replaced, a key added or dropped)."""
    message = draw(from_schema(CLIENT_SCHEMA["properties"]["client_to_server"]))
    mutation = draw(st.sampled_from(["none", "value", "extra", "drop"]))
    if mutation == "value":
        key = draw(st.sampled_from(sorted(message)))
        value = message[key]
        if isinstance(value, list):
            value = list(value)
            value[draw(st.integers(0, len(value) - 1))] = "@@"
            message[key] = value
        else:
            message[key] = "@@"
        return json.dumps(message).replace('"@@"', draw(NASTY))
    if mutation == "extra":
        message[draw(st.sampled_from(["extra", "Type", "seq2"]))] = 1
    elif mutation == "drop":
        message.pop(draw(st.sampled_from(sorted(message))))
    return json.dumps(message)


def allowed(text: str) -> bool:
    """The oracle: standard JSON, valid under the published schema, and (the one rule a schema cannot say) not
    two motions at once."""
    try:
        message = strict_json.loads(text)
    except strict_json.StrictJsonError:
        return False
    if not CLIENT_VALIDATOR.is_valid(message):
        return False
    return not (message.get("ee_velocity") is not None and message.get("joint_velocity") is not None)


def test_the_socket_takes_exactly_what_its_json_schema_allows(api):
    client, _ = api
    token, _ = teleoperating(client)
    taken = refused = 0
    with client.websocket_connect(f"/api/p/{token}/teleop") as raw:
        ws = CheckedSocket(raw, check_sent=False)
        ws.receive()

        @settings(max_examples=400, derandomize=True, deadline=None, database=None,
                  suppress_health_check=[HealthCheck.too_slow])
        @given(client_frames())
        def each(text: str) -> None:
            nonlocal taken, refused
            ws.send_raw(text)
            ack = ws.receive_until("ack")
            assert ack["ok"] is allowed(text), (text[:200], ack)
            taken, refused = taken + ack["ok"], refused + (not ack["ok"])

        each()
        assert ws.input(10**6)["ok"]
    assert taken > 50 and refused > 50  # both sides of the contract were exercised
    assert not client.app.state.services.hub.faults.recent()


# -- containment: one participant's failure is theirs alone --------------------------------------------------------
def test_a_failing_arm_is_contained_and_every_other_arm_keeps_moving(database_url, monkeypatch):
    client, admin = make_client(database_url=database_url, world_loop=True)
    make_study(client, admin)
    with client:  # the world loop runs
        poisoned, poisoned_id = teleoperating(client)
        healthy, healthy_id = teleoperating_another(client)
        hub = client.app.state.services.hub
        real_hold_moves = world_module.hold_moves
        poisoned_scene = []

        def failing_for_one(state, scene, moves, rules):
            # Only a held motion fails: a settling step with nothing held failing before the input came would end
            # the teleoperation, and the socket would take a fresh arm (a new scene) that moves well.
            if poisoned_scene and scene is poisoned_scene[0] and any(move.command.moves for move in moves):
                raise ValueError("a step no check foresaw")
            return real_hold_moves(state, scene, moves, rules)

        monkeypatch.setattr(world_module, "hold_moves", failing_for_one)
        with client.websocket_connect(f"/api/p/{poisoned}/teleop") as bad_raw, \
                client.websocket_connect(f"/api/p/{healthy}/teleop") as good_raw:
            bad, good = CheckedSocket(bad_raw), CheckedSocket(good_raw)
            bad.receive()
            start = tcp(good.receive()["teleop"]["world"])
            poisoned_scene.append(hub.arms.get(poisoned_id).scene)
            assert bad.input(1, ee_velocity=[0.0, 0.0, 0.2])["ok"]
            assert good.input(1, ee_velocity=[0.0, 0.0, 0.2])["ok"]
            ticks = hub.ticks
            deadline = time.monotonic() + 10
            risen = start
            while risen[2] - start[2] < 0.05 and time.monotonic() < deadline:
                risen = tcp(good.receive_until("world")["world"])
            assert risen[2] - start[2] >= 0.05  # the healthy arm moved on the world loop's ticks
            while hub.ticks < ticks + 10 and time.monotonic() < deadline:
                good.receive_until("world")
            assert hub.ticks >= ticks + 10 and hub.ticking  # the loop goes on
            for _ in range(100):
                if any(f.participant == poisoned_id for f in hub.faults.recent()):
                    break
                time.sleep(0.05)
            faults = hub.faults.recent()
            assert faults and {f.participant for f in faults} == {poisoned_id} and faults[0].loop == "world"
            poisoned_arm = hub.arms.get(poisoned_id)  # (ended, if it failed again with nothing held)
            assert poisoned_arm is None or not poisoned_arm.moving  # stopped
            assert good.input(2)["ok"]
        load = client.get("/api/admin/server/load", headers=auth(admin)).json()
        assert load["status"] == "fault" and load["faults_recent"] >= 1 and "not a lack of capacity" in load["message"]
    assert healthy_id != poisoned_id


def teleoperating_another(client) -> tuple[str, str]:
    """A second participant at the teleoperated practice trial (``teleoperating`` reads the first's id)."""
    from tests.server.test_teleop_socket import ASKS
    with client.app.state.services.sessionmaker() as session:
        known = set(session.scalars(select(Participant.public_id)))
    token = join(client)["token"]
    client.post(f"/api/p/{token}/consent", json={"agree": True})
    from experiment.flow import PracticeStep
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalar(select(Participant).where(Participant.public_id.not_in(known)))
        participant.step = PracticeStep(index=ASKS)
        public_id = participant.public_id
    response = client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": ASKS + 1})
    assert response.status_code == 200, response.text
    return token, public_id


def test_one_sessions_log_that_cannot_be_written_never_holds_back_anothers(api, monkeypatch):
    from concurrent.futures import ThreadPoolExecutor

    client, _ = api
    token, _ = teleoperating(client)
    hub, teleop = hub_session()
    poisoned = hub.teleop(TrialKey("poisoned", TrialRef(True, 0, 3)), teleop.scene)
    real_log_batches = log_writer_module._log_batches

    def failing_for_one(session, batches):
        if any(token == "poisoned-token" for token, _, _ in batches):
            raise ValueError("cannot be written")
        real_log_batches(session, batches)

    monkeypatch.setattr(log_writer_module, "_log_batches", failing_for_one)
    writer = log_writer_module.TeleopLogWriter(client.app.state.services.database, client.app.state.services.faults)
    writer.watch(token, teleop)
    writer.watch("poisoned-token", poisoned)
    with ThreadPoolExecutor(1) as pool:
        for round_ in range(log_writer_module.MAX_LOG_WRITE_FAILURES):
            teleop.log.append({"server_ms": float(round_), "event": "blocked"})
            poisoned.log.append({"server_ms": float(round_), "event": "blocked"})
            pool.submit(asyncio.run, writer.flush()).result()
            assert list(teleop.log) == []  # the healthy session's entries were written in the same flush
    with client.app.state.services.sessionmaker() as session:
        written = [e for ev in session.scalars(select(Event).where(Event.kind == "teleop_log"))
                   for e in ev.payload["entries"]]
    assert len(written) == log_writer_module.MAX_LOG_WRITE_FAILURES
    # the poisoned one's entries were kept and retried, then given up with a fault and a note of how many
    assert [e["event"] for e in poisoned.log] == ["log_lost"]
    assert list(poisoned.log)[0]["entries"] == log_writer_module.MAX_LOG_WRITE_FAILURES
    assert [f.loop for f in client.app.state.services.faults.recent()] == ["teleop_log"]


def test_a_teleoperations_log_is_capped(monkeypatch):
    monkeypatch.setattr(world_module, "MAX_LOG_ENTRIES", 5)
    _, teleop = hub_session()
    for i in range(20):
        teleop.log.append({"server_ms": float(i), "event": "blocked"})
    assert [e["event"] for e in teleop.log] == ["blocked"] * 4 + ["log_capped"]


def test_one_participant_whose_sweep_fails_does_not_stop_the_sweep(database_url, monkeypatch):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    tokens = [join(client)["token"] for _ in range(3)]
    app = client.app
    with app.state.services.sessionmaker() as session:
        ids = sorted(session.scalars(select(Participant.id)))
    from server import sweeper
    real_runtime_of = sweeper.runtime_of

    def failing_for_one(session, runtimes, participant):
        if participant.id == ids[1]:
            raise OverflowError("date value out of range")
        return real_runtime_of(session, runtimes, participant)

    monkeypatch.setattr(sweeper, "runtime_of", failing_for_one)
    faults = FaultLog()
    changed = sweep(app.state.services.sessionmaker, app.state.services.runtimes, app.state.services.hub,
                    now=utcnow() + timedelta(hours=2),
                    faults=faults)
    assert changed == 2
    phases = [client.get(f"/api/p/{t}/state").json()["phase"] for t in tokens]
    assert phases[0] == phases[2] == "abandoned"
    assert [(f.loop, f.participant) for f in faults.recent()] == [("sweeper", str(ids[1]))]


def test_a_config_number_that_would_overflow_is_refused_before_it_is_stored(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    config = client.get("/api/admin/studies/s1", headers=auth(admin)).json()["config"]
    for place in [("timing", "idle_timeout_s"), ("task", "rewards", "ask"), ("compensation", "bonus_cap")]:
        changed = json.loads(json.dumps(config))
        *path, last = place
        parent = changed
        for key in path:
            parent = parent[key]
        parent[last] = 1e300  # finite, but a timedelta or a value iteration would overflow
        response = client.put("/api/admin/studies/s1/config", json={"config": changed}, headers=auth(admin))
        assert response.status_code == 422, (place, response.text)
        assert ".".join(place) in response.json()["detail"]
    reward = json.dumps(config["task"]["rewards"]["ask"])
    text = json.dumps({"config": config}).replace(f'"ask": {reward}', '"ask": NaN', 1)
    started = time.monotonic()
    response = client.put("/api/admin/studies/s1/config", content=text,
                          headers=auth(admin) | {"content-type": "application/json"})
    assert response.status_code == 422 and "NaN" in response.json()["detail"]
    assert time.monotonic() - started < 5  # refused as it is read, not after solving a policy with it


# -- supervision and the load report --------------------------------------------------------------------------------
def test_a_loop_that_fails_as_a_whole_is_started_again_and_counted():
    faults, runs = FaultLog(), []

    async def loop() -> None:
        runs.append(1)
        if len(runs) < 3:
            raise RuntimeError("the loop broke")

    asyncio.run(supervised("world", loop, faults, restart_delay_s=0))
    assert len(runs) == 3 and [f.loop for f in faults.recent()] == ["world", "world"]


def test_the_load_report_names_a_fault_not_a_lack_of_capacity():
    faults = FaultLog()
    faults.record("sweeper", ValueError("bad row"), participant="p1")
    healthy = LoadFigures(window_s=60, ticks_per_s=10, late_share=0.5, latest_start_s=0.3, skipped_share=0.5)
    status, message = load_status(healthy, 30.0, faults=faults.recent())
    assert status == "fault" and "sweeper" in message and "1 participant" in message
    assert "Cap the study" not in message
    assert load_status(healthy, 30.0)[0] == "overloaded"  # without the fault: what the figures say


# -- who may open the sockets, and how fast they may send -----------------------------------------------------------
def test_sockets_refuse_pages_of_other_origins(database_url):
    client, admin = make_client(database_url=database_url, allowed_origins=["https://lab.example.org"])
    make_study(client, admin)
    token, _ = teleoperating(client)
    for path in (f"/api/p/{token}/teleop", f"/viewer/{token}"):
        with pytest.raises(WebSocketDisconnect) as refused:
            with client.websocket_connect(path, headers={"origin": "https://evil.example"},
                                          subprotocols=["viser-v1.1.1"]) as ws:
                ws.receive()
        assert refused.value.code == 1008
    for origin in (None, "http://testserver", "https://lab.example.org"):  # no browser, this server, allowed
        headers = {"origin": origin} if origin else {}
        with client.websocket_connect(f"/api/p/{token}/teleop", headers=headers) as ws:
            assert json.loads(ws.receive_text())["type"] == "hello"


def test_a_viewer_socket_that_floods_the_server_is_closed(database_url):
    from tests.server.test_viewer import receive_within
    client, admin = make_client(database_url=database_url, world_loop=True, viewer_message_rate_hz=50.0)
    make_study(client, admin)
    token, _ = teleoperating(client)
    with client, client.websocket_connect(f"/viewer/{token}", subprotocols=[f"viser-v{viser.__version__}"]) as ws:
        for _ in range(500):
            ws.send_bytes(b"\x80")
        with pytest.raises(WebSocketDisconnect) as closed:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                receive_within(ws, 5.0)
    assert closed.value.code == 1008
