"""What moves in the 3D view, without a server: viser's wire format (checked against viser 1.1.1's own message
classes and serialisation), the frames a ``LiveView`` builds, and what a ``ViewerSink`` writes."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import struct
from concurrent.futures import ThreadPoolExecutor

import msgspec
import pytest
import zstandard
from viser import _messages as viser_messages

from experiment.world import FRAME_NAMES, ItemMode, build_scene, link_poses, teleop_start_state
from experiment.world.robot import solve_ik
from server.viewer.cameras import VIEW_FOV_DEG
from server.viewer.live import LiveView, ViewerSink, camera_messages
from server.viewer.scene import BIN_HIGHLIGHT, TARGET_MARKER, TARGET_SLOT, pose_tuples, start_state
from server.viewer.wire import pack, unpack


def run_in_own_loop(coroutine):
    """``asyncio.run`` in a thread of its own: an earlier test (Playwright's sync API) may leave an event loop running
    in this one."""
    with ThreadPoolExecutor(1) as pool:
        return pool.submit(asyncio.run, coroutine).result()


FIELDS = {"SetPositionMessage": "position", "SetOrientationMessage": "wxyz"}


def decode(frame: bytes) -> dict:
    """A frame without binary buffers, read by the wire format's spec (not ``server.viewer.wire.unpack``)."""
    raw_len, packed_len = struct.unpack_from("<QQ", frame)
    assert len(frame) == 16 + packed_len  # no binary buffers follow
    return msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:], max_output_size=raw_len))


def as_viser(message: dict) -> dict:
    """The same message built with viser's own class and serialised by viser (``as_serializable_dict``)."""
    cls = getattr(viser_messages, message["type"])
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    return cls(**{k: v for k, v in message.items() if k in fields}).as_serializable_dict([])


def normalised(value):
    """Tuples as lists (msgpack has one array type), in dicts and lists."""
    if isinstance(value, dict):
        return {k: normalised(v) for k, v in value.items()}
    return [normalised(v) for v in value] if isinstance(value, (list, tuple)) else value


def test_every_message_is_what_viser_would_send():
    scene = build_scene("high", 5, target_slot=2)
    view = LiveView(scene, view="local")
    changes, frame = view.update(teleop_start_state(scene))
    messages = changes + frame + view.set_view("end_effector") + view.whole()
    kinds = {m["type"] for m in messages}
    assert {"SetPositionMessage", "SetOrientationMessage", "SetCameraFovMessage", "SetCameraPositionMessage",
            "SetCameraLookAtMessage", "SetCameraUpDirectionMessage"} <= kinds
    for message in messages + [camera_messages((1, 2, 3), (0, 0, 0), (0, 0, 1), 0.7)[0],
                               {"name": "/x", "visible": False, "owner": "", "type": "SetSceneNodeVisibilityMessage"}]:
        assert message == as_viser(message)
    decoded = decode(pack(messages))
    assert normalised(decoded["messages"]) == normalised(messages)
    assert set(decoded) == {"messages", "timestampSec", "binaryBufferLengths"} and decoded["binaryBufferLengths"] == []


def test_a_frame_is_every_moving_pose_and_only_when_something_moved():
    scene = build_scene("low", 2, target_slot=0)
    view = LiveView(scene)
    state = start_state(scene)
    changes, frame = view.update(state)
    assert changes == []  # the marks are as created
    expected = pose_tuples(link_poses(state))
    positions = {m["name"]: m["position"] for m in frame if m["type"] == "SetPositionMessage"}
    orientations = {m["name"]: m["wxyz"] for m in frame if m["type"] == "SetOrientationMessage"}
    assert set(positions) == set(orientations) == set(FRAME_NAMES)
    for name in FRAME_NAMES:
        assert positions[name] == pytest.approx(expected[name][0])
        assert orientations[name] == pytest.approx(expected[name][1])
    assert view.update(state) == ([], [])  # nothing moved: nothing to send
    turned = dataclasses.replace(state, joints=(state.joints[0] + 0.1, *state.joints[1:]))
    _, frame = view.update(turned)  # j1 turns: the arm moves, the base, the mast and the item on the shelf do not
    moved = {m["name"] for m in frame}
    assert "/robot/j1" in moved and not moved & {"/robot/base", "/robot/mast", "/items/target"}
    assert not any(m["type"] == "SetPositionMessage" and m["name"] == "/robot/j1" for m in frame)  # it turns in place
    assert not any(m["type"].startswith("SetCamera") for m in frame)  # the world camera stays where the viewer put it


def test_the_marks_change_with_the_item_once():
    scene = build_scene("low", 2, target_slot=0)
    view = LiveView(scene)
    view.update(start_state(scene))
    grasped = dataclasses.replace(start_state(scene), item=dataclasses.replace(start_state(scene).item,
                                                                               mode=ItemMode.GRASPED))
    changes, _ = view.update(grasped)
    assert {(m["name"], m["visible"]) for m in changes} >= {(BIN_HIGHLIGHT, True), (TARGET_SLOT, False),
                                                           (TARGET_MARKER, False)}
    assert view.update(dataclasses.replace(grasped, t=1.0))[0] == []  # sent when it changed, not per frame
    # a viewer that connects now gets the marks that differ from how the replay creates them
    marks = {(m["name"], m["visible"]) for m in view.whole() if m["type"] == "SetSceneNodeVisibilityMessage"}
    assert (BIN_HIGHLIGHT, True) in marks and (TARGET_SLOT, False) in marks


def test_a_follow_camera_moves_with_the_arm():
    scene = build_scene("low", 2, target_slot=1)
    view = LiveView(scene, view="end_effector")
    _, first = view.update(teleop_start_state(scene))
    lowered = solve_ik(scene.park, tuple(float(v) for v in scene.target.grasp_point() + (0, 0, 0.1)))
    _, second = view.update(dataclasses.replace(teleop_start_state(scene), joints=tuple(float(q) for q in lowered)))

    def camera(frame):
        return next(m["position"] for m in frame if m["type"] == "SetCameraPositionMessage")

    assert math.dist(camera(first), camera(second)) > 0.05
    assert next(m["fov"] for m in second if m["type"] == "SetCameraFovMessage") == pytest.approx(
        math.radians(VIEW_FOV_DEG["end_effector"]))


def test_a_new_trial_rests_the_robot_at_its_start():
    view = LiveView(build_scene("low", 2, target_slot=0), stage="attempt")
    view.follow(teleop_start_state(view.scene))
    assert view.live and view.rest() == ([], [])  # following the hub's world: no resting pose in between
    other = build_scene("high", 9, target_slot=3)
    assert view.show_trial(other) and not view.show_trial(other)
    _, frame = view.rest()
    expected = pose_tuples(link_poses(start_state(other)))
    assert frame and view.poses == expected
    for m in frame:  # what moved, to where it rests now
        assert m[FIELDS[m["type"]]] == pytest.approx(expected[m["name"]][FIELDS[m["type"]] == "wxyz"])


def position(name: str, x: float) -> dict:
    return {"name": name, "position": (x, 0.0, 0.0), "owner": "", "type": "SetPositionMessage"}


def test_a_sink_writes_nothing_before_the_replay_then_every_change_and_the_newest_poses():
    async def run() -> None:
        sink = ViewerSink()
        sink.offer([{"type": "A"}], [position("/a", 0.0)])
        sink.offer_packed(b"scene change")
        assert not sink.ready and sink.changes == [] and sink.frame == {} and sink.packed == []  # before: dropped
        sink.start([b"replay 1", b"replay 2"])
        sink.offer([{"type": "mark1"}], [position("/a", 1.0), position("/b", 1.0)])
        sink.offer([], [position("/a", 2.0)])  # a slow socket: /a's newer pose replaces its older, /b's stays
        sink.offer([{"type": "mark2"}], [])
        assert [await asyncio.wait_for(sink.next(), 1.0) for _ in range(2)] == [b"replay 1", b"replay 2"]
        data = await asyncio.wait_for(sink.next(), 1.0)
        assert [(m["type"], m.get("name"), m.get("position", [None])[0]) for m in decode(data)["messages"]] == [
            ("mark1", None, None), ("mark2", None, None),
            ("SetPositionMessage", "/a", 2.0), ("SetPositionMessage", "/b", 1.0)]
        assert sink.merged == 1
        waiting = asyncio.create_task(sink.next())
        await asyncio.sleep(0.01)
        assert not waiting.done()
        sink.offer([], [position("/b", 3.0)])
        assert [m["position"][0] for m in decode(await asyncio.wait_for(waiting, 1.0))["messages"]] == [3.0]

    run_in_own_loop(run())


def test_a_scene_change_is_written_after_what_was_offered_before_it_and_before_what_comes_after():
    async def run() -> None:
        sink = ViewerSink()
        sink.start([])
        sink.offer([{"type": "mark1"}], [position("/a", 1.0)])
        sink.offer_packed(b"new trial")
        sink.offer([{"type": "mark2"}], [position("/a", 2.0)])
        first, second, third = [await asyncio.wait_for(sink.next(), 1.0) for _ in range(3)]
        assert [(m["type"], m.get("position", [None])[0]) for m in decode(first)["messages"]] == [
            ("mark1", None), ("SetPositionMessage", 1.0)]  # not merged with the pose after the change
        assert second == b"new trial"
        assert [(m["type"], m.get("position", [None])[0]) for m in decode(third)["messages"]] == [
            ("mark2", None), ("SetPositionMessage", 2.0)]

    run_in_own_loop(run())


def test_a_closed_sink_ends_its_socket_at_once_even_while_it_waits():
    async def run() -> None:
        sink = ViewerSink()
        sink.start([])
        waiting = asyncio.create_task(sink.next())
        await asyncio.sleep(0.01)
        sink.offer([], [position("/a", 1.0)])
        sink.close()
        assert await asyncio.wait_for(waiting, 1.0) is None
        assert await asyncio.wait_for(sink.next(), 1.0) is None

    run_in_own_loop(run())


def test_a_frame_with_binary_buffers_is_what_viser_sends():
    """A mesh's arrays follow the compressed messages, each 8-byte aligned, as viser's ``_message_producer`` writes
    them; the placeholders index them."""
    import numpy as np

    message = viser_messages.MeshMessage("/m", viser_messages.MeshProps(
        vertices=np.arange(9, dtype=np.float32).reshape(3, 3), faces=np.array([[0, 1, 2]], dtype=np.uint32),
        color=(1, 2, 3), wireframe=False, opacity=None, flat_shading=True, side="front", material="standard",
        scale=1.0, cast_shadow=False, receive_shadow=False))
    buffers: list = []
    serialised = message.as_serializable_dict(buffers)
    frame = pack([serialised], buffers)
    raw_len, packed_len = struct.unpack_from("<QQ", frame)
    payload = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:16 + packed_len],
                                                                             max_output_size=raw_len))
    assert payload["binaryBufferLengths"] == [36, 12]
    start = 16 + packed_len + (8 - (16 + packed_len) % 8) % 8
    vertices_at = start
    faces_at = vertices_at + 36 + 4  # 36 bytes, then padding to the next multiple of 8
    assert frame[vertices_at:vertices_at + 36] == np.arange(9, dtype=np.float32).tobytes()
    assert frame[faces_at:faces_at + 12] == np.array([0, 1, 2], dtype=np.uint32).tobytes()
    assert len(frame) == faces_at + 12
    decoded, arrays = unpack(frame)
    assert decoded["messages"][0]["props"]["vertices"] == {"__binary_index": 0, "dtype": "<f4"}
    assert arrays == [np.arange(9, dtype=np.float32).tobytes(), np.array([0, 1, 2], dtype=np.uint32).tobytes()]


def _hub(world_hz: float = 30.0):
    """What the view's ticks read of the world hub: how late the latest tick started, and the loop's period."""
    from types import SimpleNamespace

    return SimpleNamespace(late_s=0.0, period_s=1.0 / world_hz)


def _watched_session(manager):
    """One session with a ready viewer, and a function that runs ``n`` ticks starting ``late`` world periods late
    and returns the view frames they made."""
    from server.viewer.manager import ViewerSession
    from server.world.playback import LiveWorld

    scene = build_scene("low", 2, target_slot=0)
    sink = ViewerSink()
    sink.start([])
    vs = ViewerSession(1, "P1", None, LiveView(scene, stage="attempt"), {sink})  # type: ignore[arg-type]
    manager._sessions[1] = vs
    state = start_state(scene)
    ticks = iter(range(1, 10_000))

    def updates(n: int, late: float) -> int:
        manager.hub.late_s, before = late * manager.hub.period_s, vs.live.frames
        for _ in range(n):
            i = next(ticks)
            manager._on_tick({"P1": LiveWorld(scene.seed, dataclasses.replace(state, t=float(i), joints=(
                0.01 * i, *state.joints[1:])))})
        return vs.live.frames - before
    return updates


def test_a_congested_event_loop_updates_the_views_every_other_tick():
    """While the world loop's ticks start late, the views get every second tick (a lower frame rate) and nothing else
    changes: requests keep the event loop. Back on time, every tick again."""
    from server.viewer.manager import LATE_STEP_PERIODS, ViewerManager
    from server.world.hub import LATE_TICK_PERIODS

    manager = ViewerManager(_hub(), None, None)  # type: ignore[arg-type]  # ticks read no database
    updates = _watched_session(manager)
    assert updates(30, 0.0) == 30  # on time: every tick
    assert updates(30, LATE_TICK_PERIODS) == 30  # late for the load report, not yet for the views
    assert updates(30, 1.5 * LATE_STEP_PERIODS) == 15  # late: every other tick
    assert updates(30, 30.0) == 15  # however late
    assert manager.ticks_skipped == 30 and manager.ticks_seen == 120
    assert updates(30, 0.0) == 30


@pytest.mark.parametrize("world_hz", [10.0, 30.0, 240.0])
def test_late_means_the_same_share_of_a_tick_at_any_world_rate(world_hz):
    """The views shed ticks, and the load report counts them late, from a share of the world loop's period: 25 ms
    and 10 ms at the default 30 Hz, never a fixed time that would be several ticks at 240 Hz or a quarter of one
    at 10 Hz."""
    from server.settings import Settings
    from server.viewer.manager import LATE_STEP_PERIODS, ViewerManager
    from server.world.hub import LATE_TICK_PERIODS, WorldHub

    period = 1.0 / world_hz
    manager = ViewerManager(_hub(world_hz), None, None)  # type: ignore[arg-type]
    updates = _watched_session(manager)
    assert updates(10, 0.9 * LATE_STEP_PERIODS) == 10
    assert updates(10, 1.1 * LATE_STEP_PERIODS) == 5

    hub = WorldHub(Settings(world_hz=world_hz))
    assert hub.period_s == pytest.approx(period)
    for late_s in (0.0, 0.9 * LATE_TICK_PERIODS * period, 1.1 * LATE_TICK_PERIODS * period, 0.025, 0.2):
        hub.note_start(late_s)
    assert hub.late_ticks == 1 + (0.025 >= LATE_TICK_PERIODS * period) + 1  # 10 Hz: 25 ms is a quarter of a tick
    assert hub.latest_start_s == 0.2 and hub.late_s == 0.2


def test_a_pacer_that_waits_for_late_ticks_in_a_row_skips_no_frame_for_a_single_one():
    """The pacer's other form: shedding from the n-th late tick in a row, so that a late tick or two between ticks
    on time (a collection, one long callback) cost no frame, while lasting lateness still halves the rate."""
    from server.viewer.manager import LATE_STEP_PERIODS, ViewerManager, ViewPacer

    manager = ViewerManager(_hub(), None, None)  # type: ignore[arg-type]
    manager.pacer = ViewPacer(late_ticks_before_shedding=3)
    updates = _watched_session(manager)
    for _ in range(10):  # late now and then, never three ticks in a row
        assert updates(2, 2 * LATE_STEP_PERIODS) + updates(1, 0.0) == 3
    assert manager.ticks_skipped == 0
    assert updates(30, 1.5 * LATE_STEP_PERIODS) == 2 + 14  # lasting: two ticks as usual, then every other tick
    assert updates(30, 0.0) == 30


def test_the_log_says_when_the_views_skipped_ticks(caplog):
    """Once a minute at most, a warning with the ticks the views skipped (nothing when none were)."""
    from server.viewer.manager import LATE_STEP_PERIODS, SHEDDING_REPORT_S, ViewerManager

    manager = ViewerManager(_hub(), None, None)  # type: ignore[arg-type]
    updates = _watched_session(manager)
    # a quarter of a second past each minute: start + 60 - start can come out a hair under 60 in floating point
    first = manager._shedding_reported[0] + SHEDDING_REPORT_S + 0.25
    updates(30, 0.0)
    manager.report_shedding(first)
    assert "skipped" not in caplog.text
    updates(33, 2 * LATE_STEP_PERIODS)
    manager.report_shedding(first + 1)  # too soon after the last report
    assert "skipped" not in caplog.text
    manager.report_shedding(first + SHEDDING_REPORT_S + 0.25)
    assert "3D views skipped 17 of 33 world ticks (51.5 %) in the last 60 s" in caplog.text  # (the 1st, 3rd, …, 33rd)


def test_the_log_warns_of_skipped_ticks_only_from_the_share_the_dashboard_warns_at(caplog):
    """A few skipped ticks (0.05-0.6 % in a participant's log, a warning a minute) are the pacer at work: the log
    warns from the share that makes the load report say "busy" (``server.loadmeter.views_skip_too_many``), not below."""
    from server.loadmeter import BUSY_SKIPPED, LoadFigures, load_status
    from server.viewer.manager import LATE_STEP_PERIODS, SHEDDING_REPORT_S, ViewerManager

    def figures(share: float) -> LoadFigures:
        return LoadFigures(window_s=60.0, ticks_per_s=30.0, late_share=0.0, latest_start_s=0.0, skipped_share=share)

    manager = ViewerManager(_hub(), None, None)  # type: ignore[arg-type]
    updates = _watched_session(manager)
    at = manager._shedding_reported[0]
    threshold = round(BUSY_SKIPPED * 1000)  # skipped ticks of 1000 at the threshold
    for n_skipped, warned in ((1, False), (6, False), (threshold - 1, False), (threshold, True), (100, True)):
        before = manager.ticks_skipped
        updates(1000 - 2 * n_skipped, 0.0)
        updates(2 * n_skipped, 2 * LATE_STEP_PERIODS)  # ticks late in a row: every other one skipped
        assert manager.ticks_skipped - before == n_skipped
        at += SHEDDING_REPORT_S + 0.25
        caplog.clear()
        manager.report_shedding(at)
        share = n_skipped / 1000
        assert ("3D views skipped" in caplog.text) is warned, (n_skipped, caplog.text)
        assert (load_status(figures(share), 30.0)[0] == "busy") is warned  # the dashboard says the same


def test_a_graded_pacer_sheds_more_ticks_the_later_they_start_and_fades_back():
    """The pacer's graded form (more ticks between updates per step of lateness, a fading memory of it)."""
    from server.viewer.manager import ViewerManager, ViewPacer

    manager = ViewerManager(_hub(), None, None)  # type: ignore[arg-type]
    manager.pacer = ViewPacer(late_step=0.3, max_ticks=6, fade=0.9, late_ticks_before_shedding=1)
    updates = _watched_session(manager)
    assert updates(30, 0.0) == 30
    assert updates(30, 0.45) == 15  # every other tick
    assert updates(30, 0.75) == 10  # every third
    assert updates(60, 30.0) == 10  # saturated: the lowest rate, never none
    assert updates(60, 0.0) < 60  # a tick a whole second late: the rate comes back gradually (in 1.5 s)...
    assert updates(30, 0.0) == 30  # ...and whole


def test_the_hub_computes_no_world_for_the_views_on_a_tick_they_skip():
    """The pacer's decision is taken when the hub asks what is wanted: a skipped tick costs no view's world."""
    from server.viewer.manager import LATE_STEP_PERIODS, ViewerManager, ViewerSession

    hub = _hub()
    manager = ViewerManager(hub, None, None)  # type: ignore[arg-type]
    scene = build_scene("low", 2, target_slot=0)
    manager._sessions[1] = ViewerSession(1, "P1", None, None, LiveView(scene), {ViewerSink()})  # type: ignore[arg-type]
    assert manager._wanted() == ["P1"]
    manager._on_tick({})
    hub.late_s = 1.5 * LATE_STEP_PERIODS * hub.period_s  # every other tick
    wanted = []
    for _ in range(4):
        wanted.append(manager._wanted())
        manager._on_tick({})
    assert wanted == [[], ["P1"], [], ["P1"]]


def test_the_viewer_poll_reads_the_sessions_a_chunk_per_unit_of_work():
    """A unit of work holds the event loop: the poll reads at most ``POLL_CHUNK`` sessions in one, so requests get
    the loop between chunks, and every session is read."""
    from server.viewer.manager import POLL_CHUNK, ViewerManager, ViewerSession
    from server.viewer.targets import Reading, Target

    units: list[int] = []

    async def run_unit(work):
        return work(None)

    manager = ViewerManager(None, run_unit, None)  # type: ignore[arg-type]

    def read(session, participant_ids, runtimes):
        units.append(len(participant_ids))
        return Reading({pid: Target(True) for pid in participant_ids})

    manager._targets.read = read  # type: ignore[method-assign]
    manager.play_attempts = lambda attempts: asyncio.sleep(0)  # type: ignore[method-assign]
    scene = build_scene("low", 2, target_slot=0)
    count = 2 * POLL_CHUNK + 5
    for pid in range(count):
        manager._sessions[pid] = ViewerSession(pid, f"P{pid}", None, LiveView(scene), {ViewerSink()})  # type: ignore[arg-type]
    run_in_own_loop(manager.poll_once())
    assert units == [POLL_CHUNK, POLL_CHUNK, 5]
