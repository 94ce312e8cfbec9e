"""A session's scene as viser messages (``server.viewer.scene``), checked against viser 1.1.1 itself: a real viser
server, given the same scene through its public scene API, holds exactly the messages trustlab replays, and a
viewer that was shown one trial and then the next ends with the scene viser would replay for the next."""

from __future__ import annotations

import math
from typing import Any

import pytest
import viser

from experiment.world import FRAME_NAMES, Box, body_shapes, build_scene, link_poses, scene_boxes
from experiment.world import constants as K
from server.viewer import scene as S
from server.viewer.live import LiveView
from server.viewer.wire import Serialized, unpack

# --- the reference: the scene built with viser's own API, as trustlab did with a viser server per session ---------

def _add_shape(api: Any, box: Box, **extra: Any) -> None:
    center, wxyz, color = tuple(map(float, box.center)), tuple(map(float, box.wxyz)), tuple(map(int, box.color))
    if box.shape == "cylinder":
        api.add_cylinder(box.name, radius=float(box.size[0]) / 2, height=float(box.size[2]), color=color,
                         radial_segments=24, position=center, wxyz=wxyz, **extra)
    else:
        api.add_box(box.name, color=color, dimensions=tuple(map(float, box.size)), position=center, wxyz=wxyz, **extra)


def viser_reference(scene) -> list[dict[str, Any]]:
    """What a viser server built through its scene API holds for ``scene`` (what it replays to a client that
    connects: viser's own scene serialiser reads the same), serialised with the binary placeholders resolved."""
    server = S.start_server()
    try:
        S.configure(server)
        api = server.scene
        boxes = scene_boxes(scene)
        _add_shape(api, next(b for b in boxes if b.name == "/floor"), cast_shadow=False)
        (x0, y0), (x1, y1) = K.FLOOR_BOUNDS
        api.add_grid("/floor_grid", width=x1 - x0, height=y1 - y0, cell_size=0.25, section_size=1.0,
                     cell_color=S.GRID_COLOR, section_color=S.GRID_SECTION_COLOR,
                     position=((x0 + x1) / 2, (y0 + y1) / 2, 0.001), shadow_opacity=0.2)
        for box in boxes:
            if box.name.startswith("/shelf/"):
                _add_shape(api, box)
        start = link_poses(S.start_state(scene))
        for name in FRAME_NAMES:
            api.add_frame(name, show_axes=False, position=tuple(start[name][0]), wxyz=tuple(start[name][1]))
        for box in body_shapes(scene):
            if box.name != S.TARGET_GEOM:
                _add_shape(api, box)
        bx, by = K.BIN_XY
        sx, sy, _ = K.BIN_SIZE
        api.add_frame(S.BIN_HIGHLIGHT, show_axes=False, position=(bx, by, K.BIN_RIM), visible=False)
        band, t = S.BIN_RIM_BAND, S.BIN_RIM_THICKNESS
        outer = (sx / 2 + (band - K.BIN_WALL) / 2, sy / 2 + (band - K.BIN_WALL) / 2)
        api.add_mesh_simple(f"{S.BIN_HIGHLIGHT}/rim", *S.frame_mesh(outer, (outer[0] - band, outer[1] - band), 0.0, t),
                            color=S.HIGHLIGHT_COLOR, flat_shading=True, cast_shadow=False, receive_shadow=False)
        api.add_box(f"{S.BIN_HIGHLIGHT}/opening", color=S.HIGHLIGHT_COLOR,
                    dimensions=(sx - 2 * K.BIN_WALL, sy - 2 * K.BIN_WALL, 0.003), position=(0.0, 0.0, 0.0),
                    opacity=S.BIN_OPENING_OPACITY, side="double", cast_shadow=False, receive_shadow=False)
        for box in boxes:
            if box.name.startswith(("/items/", "/obstacles/")):
                _add_shape(api, box)
        _add_shape(api, next(b for b in body_shapes(scene) if b.name == S.TARGET_GEOM))
        target = scene.target
        x, y, tip, _ = S.arrow_axis(scene)
        pad = target.width + 0.05
        api.add_box(S.TARGET_SLOT, color=S.HIGHLIGHT_COLOR, dimensions=(pad, pad, 0.004),
                    position=(x, y, float(target.center[2]) - target.height / 2 + 0.002), cast_shadow=False)
        m = S.HALO_MARGIN
        if target.shape == "cylinder":
            api.add_cylinder(S.TARGET_HALO, radius=target.width / 2 + m, height=target.height + 2 * m,
                             color=S.HIGHLIGHT_COLOR, radial_segments=24, side="back", cast_shadow=False,
                             receive_shadow=False)
        else:
            api.add_box(S.TARGET_HALO, color=S.HIGHLIGHT_COLOR, side="back", cast_shadow=False, receive_shadow=False,
                        dimensions=tuple(float(v) + 2 * m for v in target.size))
        api.add_frame(S.TARGET_MARKER, show_axes=False, position=(x, y, tip))
        api.add_mesh_simple(S.TARGET_ARROW, *S.arrow_mesh(S.ARROW_HEAD, S.ARROW_HEAD_RADIUS, S.ARROW_SHAFT,
                                                          S.ARROW_SHAFT_RADIUS),
                            color=S.HIGHLIGHT_COLOR, flat_shading=True, cast_shadow=False, receive_shadow=False)
        api.add_label(S.TARGET_LABEL, S.LABEL_TEXT, position=(0.0, 0.0, S.ARROW_HEAD + S.ARROW_SHAFT + 0.02),
                      anchor="bottom-center", depth_test=False, font_screen_scale=S.LABEL_SCALE)
        buffer = server._websock_server._broadcast_buffer
        with buffer.buffer_lock:
            held = list(buffer.message_from_id.values())
    finally:
        S.stop_server(server)
    serialised = Serialized.of(held)
    return resolved(serialised.messages, [bytes(b) for b in serialised.buffers])


def resolved(messages: list[dict[str, Any]], buffers: list[bytes]) -> list[dict[str, Any]]:
    """Messages with every binary placeholder replaced by its bytes (indices differ from frame to frame), tuples as
    lists (msgpack has one array type) and the GUI panel's run id (one per viser server) left out."""
    def walk(value: Any) -> Any:
        if isinstance(value, dict):
            if "__binary_index" in value:
                return {"bytes": bytes(buffers[value["__binary_index"]]), "dtype": value["dtype"]}
            return {k: walk(v) for k, v in value.items() if k != "run_id"}
        if isinstance(value, (list, tuple)):
            return [walk(v) for v in value]
        return value
    return [walk(m) for m in messages]


def received(frames: list[bytes]) -> list[dict[str, Any]]:
    """What a client decodes from ``frames``, in order."""
    out = []
    for frame in frames:
        payload, buffers = unpack(frame)
        out += resolved(payload["messages"], buffers)
    return out


SCENES = [("high", 5, 2), ("low", 7, 1), ("high", 11, 0), ("low", 3, 5)]


@pytest.mark.parametrize(("complexity", "seed", "slot"), SCENES)
def test_a_viewer_that_connects_gets_what_visers_server_replays(complexity, seed, slot):
    scene = build_scene(complexity, seed, target_slot=slot)
    replay = received(S.SceneView(scene).replay([]))
    stamp = replay.pop()  # after everything else: a client holding it holds the whole scene (page's proof)
    assert stamp["type"] == "FrameMessage"
    assert stamp["name"] == S.stamp_node(scene.stamp) == f"/scene_stamp_{scene.stamp}"
    assert replay[-1] == {"type": "ReplayDoneMessage"}
    assert replay[:-1] == viser_reference(scene)


# --- a trial's change, on a model of viser's client scene tree ----------------------------------------------------

def apply(tree: dict[str, dict[str, Any]], messages: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """viser's client scene tree after ``messages``: a node by name with what created it, its pose and visibility;
    removing a node removes its descendants."""
    for m in messages:
        kind, name = m["type"], m.get("name")
        if "props" in m:
            tree[name] = {"create": m, "position": [0.0, 0.0, 0.0], "wxyz": [1.0, 0.0, 0.0, 0.0], "visible": True}
        elif kind == "RemoveSceneNodeMessage":
            for other in [n for n in tree if n == name or n.startswith(name + "/")]:
                del tree[other]
        elif kind == "SetPositionMessage":
            tree[name]["position"] = m["position"]
        elif kind == "SetOrientationMessage" and name:
            tree[name]["wxyz"] = m["wxyz"]
        elif kind == "SetSceneNodeVisibilityMessage":
            tree[name]["visible"] = m["visible"]
    return tree


def close(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(close(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(close(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, abs_tol=1e-9)
    return a == b


@pytest.mark.parametrize(("before", "after"), [(SCENES[0], SCENES[1]), (SCENES[1], SCENES[2]), (SCENES[2], SCENES[0]),
                                               (SCENES[1], SCENES[3])])
def test_a_connected_viewer_shown_the_next_trial_holds_the_scene_a_new_viewer_would_get(before, after):
    """Removing the trial shown and creating the next (what moves sent as a connected viewer gets it) leaves a
    viewer with exactly the nodes, props, poses and visibility that viser would replay for the next trial."""
    first = build_scene(before[0], before[1], target_slot=before[2])
    second = build_scene(after[0], after[1], target_slot=after[2])
    view, live = S.SceneView(first), LiveView(first)
    tree = apply({}, received(view.replay(live.whole())))
    change = view.show_trial(second)
    assert change is not None and view.scene is second and view.show_trial(second) is None  # once
    live.show_trial(second)
    assert S.stamp_node(first.stamp) in tree
    tree = apply(tree, received([change]) + resolved(live.rest()[1], []))
    assert S.stamp_node(first.stamp) not in tree and not any(n.startswith(S.STAMP_PREFIX) for n in tree)
    tree = apply(tree, received([view.stamp_frame()]))  # sent last (server.viewer.manager)

    fresh_view, fresh_live = S.SceneView(second), LiveView(second)
    fresh = apply({}, received(fresh_view.replay(fresh_live.whole())))
    assert tree.keys() == fresh.keys()
    assert all(close(tree[name], fresh[name]) for name in fresh), [n for n in fresh if not close(tree[n], fresh[n])]
    assert any(m["type"] == "RemoveSceneNodeMessage" for m in received([change]))


def test_the_preamble_is_visers_own_for_trustlabs_configuration():
    """Theme (no logo or share button, trustlab's brand colour), the control panel minimised, z up, the lights and the
    world preset's camera as every client's first: taken once per process from a viser server."""
    kinds = [type(m).__name__ for m in S.preamble()]
    assert {"ThemeConfigurationMessage", "GuiSetPanelCollapsedMessage", "EnableLightsMessage",
            "SetCameraPositionMessage", "SetCameraLookAtMessage", "SetCameraFovMessage"} <= set(kinds)
    theme = next(m for m in S.preamble() if type(m).__name__ == "ThemeConfigurationMessage")
    assert theme.show_logo is False and theme.show_share_button is False
    fov = next(m for m in S.preamble() if type(m).__name__ == "SetCameraFovMessage")
    assert fov.initial is True and fov.fov == pytest.approx(math.radians(S.VIEW_FOV_DEG["world"]))
    assert S.preamble() is S.preamble()  # (one viser server per process)
    assert viser.__version__ == "1.1.1"  # what these messages are checked against


def test_no_viser_server_per_session(monkeypatch):
    """Sessions' scenes and their trials' changes start no viser server (the preamble is taken once per process)."""
    S.preamble()
    started = []
    monkeypatch.setattr(S, "start_server", lambda: started.append(1))
    monkeypatch.setattr(viser, "ViserServer", lambda *a, **k: started.append(1))
    views = [S.SceneView(build_scene("high", seed, target_slot=seed % 6)) for seed in range(5)]
    for seed, view in enumerate(views):
        assert view.show_trial(build_scene("low", 100 + seed, target_slot=1)) is not None
        assert len(view.replay([])) == 3  # static nodes, the trial's, its stamp
    assert started == []
