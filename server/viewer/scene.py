"""The 3D scene of one participant session, as the viser messages that draw it (no viser server per session).

Built from the world's primitives (``experiment.world.render``): ``scene_boxes``
gives the floor, the shelf, the other items and the obstacles in world
coordinates; ``body_shapes`` gives the robot's (and the target item's) shapes
relative to the moving frames of ``link_poses``, which are created once under
their ``FRAME_NAMES`` and then only moved.

Node names (stable, what tests and recordings rely on):

- static: ``/floor``, ``/floor_grid``, ``/shelf/<part>``, the robot frames
  ``/robot/base`` .. ``/robot/finger_right`` with their shapes
  (``/robot/base/body``, ``/robot/base/bin_*``, ``/robot/j2/link``, ...);
- per trial (rebuilt when the trial changes): ``/items/<slot>`` (every item but
  the target), ``/obstacles/<i>`` (high complexity only), ``/items/target/geom``
  (the target item, in the moving frame ``/items/target``) and what marks it:
  ``/target_marker`` (a frame above the item's top with ``/target_marker/arrow``,
  a downward arrow floating over the obstacles and the shelf, and
  ``/target_marker/label``, a tag drawn over everything), ``/items/target/halo``
  (an outline around the item: a larger back-faced copy of it) and
  ``/target_slot`` (a pad on the board under it), all in ``HIGHLIGHT_COLOR``;
- ``/robot/base/bin_highlight`` (static, moves with the base): the bin's opening
  (a rim frame and a translucent plane), shown only while the item is held;
- ``/scene_stamp_<stamp>``: an empty frame named after the trial's scene (``Scene.stamp``), created after the
  rest of the trial's first picture: the page reads it back from viser's client to prove what a frame drew.

A ``SceneView`` holds a session's scene as viser 1.1.1's messages, built with viser's own message classes the way
its scene API builds them (``SceneNodes``) and written in its wire format (``server.viewer.wire``) by the viewer
sockets themselves: a viewer that connects gets the replay viser's server would send it, and a connected viewer
the removal of the trial shown and the creation of the next (why no viser server per session:
docs/architecture.md, "The 3D view"). What precedes the nodes (theme, panel, lights,
first camera: ``preamble``) is taken once per process from a viser server. What moves (the frames' poses, which
marks show, a follow camera) is ``server.viewer.live``'s. The marks are created as a trial starts
(``CREATED_VISIBLE``: the target's shown, the bin's hidden). ``tests/server/test_viewer_scene.py`` checks the
messages against what a real viser server, given the same scene through its API, sends a client.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from collections.abc import Iterable, Iterator, Mapping
from typing import Any, cast

import numpy as np
import rich
import viser
from viser import _messages as viser_messages

from experiment.world import (
    FRAME_NAMES,
    Box,
    Scene,
    WorldState,
    body_shapes,
    link_frames,
    link_poses,
    scene_boxes,
)
from experiment.world import constants as K
from experiment.world.geometry import quat, vec3
from experiment.world.path import ready_joints
from experiment.world.state import as_joints, shelf_item_state
from server.viewer.cameras import VIEW_FOV_DEG, world_camera
from server.viewer.wire import Message, Serialized, pack

TARGET_GEOM = "/items/target/geom"
TARGET_SLOT = "/target_slot"
TARGET_MARKER = "/target_marker"
TARGET_ARROW = "/target_marker/arrow"
TARGET_LABEL = "/target_marker/label"
TARGET_HALO = "/items/target/halo"
BIN_HIGHLIGHT = "/robot/base/bin_highlight"
#: The scene's stamp (``stamp_node``): a root node that draws nothing, named after the scene the view holds.
STAMP_PREFIX = "/scene_stamp_"
#: What marks the item to collect and, while it is held, the bin: a neon magenta, unlike every item colour
#: (``experiment.world.scene.ITEM_COLORS``), the obstacles' red, the shelf, the floor and the robot.
HIGHLIGHT_COLOR = (255, 0, 255)
#: The arrow over the target: its tip this far above the item's top (above the obstacles, which stand at most
#: ``OBSTACLE_ABOVE_ITEM_RANGE[1]`` above it), head and shaft (m).
ARROW_GAP = K.OBSTACLE_ABOVE_ITEM_RANGE[1] + 0.02
ARROW_HEAD, ARROW_HEAD_RADIUS, ARROW_SHAFT, ARROW_SHAFT_RADIUS = 0.15, 0.08, 0.15, 0.03
#: The outline around the target item: its copy is this much larger on every side (m).
HALO_MARGIN = 0.014
#: The bin highlight's rim frame: this wide over the walls and this thick (m); the opening's plane opacity.
BIN_RIM_BAND, BIN_RIM_THICKNESS, BIN_OPENING_OPACITY = 0.03, 0.012, 0.45
#: The tag over the arrow (drawn over everything, constant size on screen).
LABEL_TEXT, LABEL_SCALE = "collect this", 1.3
#: From the target item's top to the arrow's top (m): what the world camera keeps in view over every slot.
MARKER_HEIGHT = ARROW_GAP + ARROW_HEAD + ARROW_SHAFT
#: The bin on the base (in the base frame): what the local camera keeps in view while the item is held.
BIN_BOX = Box("/robot/base/bin", np.array([K.BIN_XY[0], K.BIN_XY[1], (K.BASE_TOP + K.BIN_RIM) / 2]),
              np.array([K.BIN_SIZE[0], K.BIN_SIZE[1], K.BIN_RIM - K.BASE_TOP]), (0, 0, 0))
#: How the marks are created (a trial's start: the item on its shelf): what a viewer shows after the replay.
CREATED_VISIBLE = {TARGET_SLOT: True, TARGET_HALO: True, TARGET_MARKER: True, BIN_HIGHLIGHT: False}
GRID_COLOR, GRID_SECTION_COLOR = (185, 188, 182), (150, 152, 146)
#: Sides of every cylinder (the items, the wheels, the joint housing, a cylinder's outline).
CYLINDER_SEGMENTS = 24
BRAND_COLOR = (40, 110, 190)

Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]

# --- quiet server start/stop -------------------------------------------------------------

_quiet_lock = threading.Lock()
_quiet_depth = 0
_saved_quiet = [False]


@contextlib.contextmanager
def quiet_rich() -> Iterator[None]:
    """Mute rich's global console: viser prints a banner on start and a line on stop even with verbose=False."""
    global _quiet_depth
    console = rich.get_console()
    with _quiet_lock:
        if _quiet_depth == 0:
            _saved_quiet[0] = console.quiet
            console.quiet = True
        _quiet_depth += 1
    try:
        yield
    finally:
        with _quiet_lock:
            _quiet_depth -= 1
            if _quiet_depth == 0:
                console.quiet = _saved_quiet[0]


def start_server() -> viser.ViserServer:
    """A ViserServer on an ephemeral loopback port (blocks ~5 ms; call from a worker thread)."""
    with quiet_rich():
        return viser.ViserServer(host="127.0.0.1", port=0, verbose=False)


def stop_server(server: viser.ViserServer) -> None:
    """Stop a server and wait for its thread (blocks up to ~1 s; call from a worker thread)."""
    with quiet_rich():
        server.stop()


# --- poses ---------------------------------------------------------------------------------

def start_state(scene: Scene) -> WorldState:
    """The robot parked at the trial's start pose (arm ready, gripper open), the item in its slot."""
    return WorldState(0.0, scene.start, as_joints(ready_joints()), K.GRIPPER_MAX, K.GRIPPER_MAX,
                      shelf_item_state(scene))


def state_poses(state: WorldState) -> dict[str, Any]:
    """``link_poses(state)`` as plain tuples (the same numbers, without numpy's per-call overhead)."""
    frames: dict[str, Any] = link_frames(state.base, state.joints, state.gripper)
    frames["/items/target"] = (state.item.position, state.item.wxyz)
    return frames


def pose_tuples(poses: Mapping[str, Any]) -> dict[str, Pose]:
    """``{name: (position, wxyz)}`` as float tuples, from ``link_poses`` (arrays) or a hub frame (lists)."""
    out: dict[str, Pose] = {}
    for name, (p, q) in poses.items():
        out[name] = ((float(p[0]), float(p[1]), float(p[2])), (float(q[0]), float(q[1]), float(q[2]), float(q[3])))
    return out


# --- the scene -----------------------------------------------------------------------------

def arrow_axis(scene: Scene) -> tuple[float, float, float, float]:
    """The arrow over the target: x, y, z of its tip, z of its top (m)."""
    target = scene.target
    x, y, z = (float(v) for v in target.center)
    tip = z + target.height / 2 + ARROW_GAP
    return x, y, tip, tip + ARROW_HEAD + ARROW_SHAFT


def configure(server: viser.ViserServer) -> None:
    """What precedes the scene in every viewer (the preamble): viser's theme without its logo and share button, its
    control panel minimised (1.1.1 cannot remove it; the client page we serve hides it with CSS), z up, the default
    lights, and every new client's first camera (the world preset; also viser's "reset view")."""
    server.gui.configure_theme(show_logo=False, show_share_button=False, dark_mode=False, brand_color=BRAND_COLOR,
                               control_width="small")
    server.gui.main_panel.minimize()
    server.scene.set_up_direction("+z")
    server.scene.configure_default_lights(enabled=True, cast_shadow=True)
    cam = server.initial_camera
    cam.position, cam.look_at = world_camera(MARKER_HEIGHT)
    cam.up = (0.0, 0.0, 1.0)
    cam.fov = math.radians(VIEW_FOV_DEG["world"])


@functools.cache
def preamble() -> tuple[viser_messages.Message, ...]:
    """The messages viser's server sends every client before the scene's nodes, for ``configure``: taken once per
    process from a viser server configured so (its palette, its up-direction quaternion, its panel's run id), as
    viser's own scene serialiser takes them. Blocks up to ~1 s (the server's stop): warm it in a worker thread."""
    server = start_server()
    try:
        configure(server)
        buffer = server._websock_server._broadcast_buffer
        with buffer.buffer_lock:
            # viser types its buffer by its messages' base class; what it holds are scene messages
            return tuple(cast(viser_messages.Message, m) for m in buffer.message_from_id.values())
    finally:
        stop_server(server)


#: The props viser's ``add_*`` give a node for the arguments trustlab leaves at their defaults (viser 1.1.1).
FRAME_DEFAULTS: dict[str, Any] = {"axes_length": 0.5, "axes_radius": 0.025, "origin_radius": 0.05,
                                  "origin_color": (236, 236, 0), "scale": 1.0}
SURFACE_DEFAULTS: dict[str, Any] = {"wireframe": False, "opacity": None, "side": "front", "material": "standard",
                                    "cast_shadow": True, "receive_shadow": True, "scale": 1.0}
IDENTITY: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
ORIGIN: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _allclose(values: Any, default: tuple[float, ...]) -> bool:
    """``numpy.allclose(values, default)`` (viser's test for a pose left at its default), without numpy's ~10 µs a
    call: a trial's nodes make two each."""
    return all(abs(float(v) - d) <= 1e-8 + 1e-5 * abs(d) for v, d in zip(values, default, strict=True))


def _rgb(color: Any) -> tuple[int, int, int]:
    return int(color[0]), int(color[1]), int(color[2])


def frame_message(name: str) -> viser_messages.FrameMessage:
    return viser_messages.FrameMessage(name, viser_messages.FrameProps(show_axes=False, **FRAME_DEFAULTS))


def box_message(name: str, dimensions: Any, color: Any, **props: Any) -> viser_messages.BoxMessage:
    return viser_messages.BoxMessage(name, viser_messages.BoxProps(
        dimensions=vec3(dimensions), color=_rgb(color), **(SURFACE_DEFAULTS | {"flat_shading": True} | props)))


def cylinder_message(name: str, radius: float, height: float, color: Any,
                     **props: Any) -> viser_messages.CylinderMessage:
    return viser_messages.CylinderMessage(name, viser_messages.CylinderProps(
        radius=float(radius), height=float(height), color=_rgb(color), radial_segments=CYLINDER_SEGMENTS,
        **(SURFACE_DEFAULTS | {"flat_shading": False} | props)))


def mesh_message(name: str, vertices: np.ndarray, faces: np.ndarray, color: Any,
                 **props: Any) -> viser_messages.MeshMessage:
    return viser_messages.MeshMessage(name, viser_messages.MeshProps(
        vertices=vertices.astype(np.float32), faces=faces.astype(np.uint32), color=_rgb(color),
        **(SURFACE_DEFAULTS | {"flat_shading": False} | props)))


def shape_message(box: Box, **props: Any) -> viser_messages.Message:
    """A world primitive (``experiment.world.render``): a box or an upright cylinder."""
    if box.shape == "cylinder":
        return cylinder_message(box.name, float(box.size[0]) / 2, float(box.size[2]), box.color, **props)
    return box_message(box.name, box.size, box.color, **props)


class SceneNodes:
    """Scene nodes as viser's scene API creates them (``SceneNodeHandle._make``, viser 1.1.1): a missing ancestor
    first, as a virtual frame; then the node's message, its orientation and position unless they are the defaults,
    and its visibility."""

    def __init__(self, existing: Iterable[str] = ()):
        self.names: set[str] = set(existing)
        self.created: list[str] = []  # by this builder, in order
        self.messages: list[viser_messages.Message] = []

    def add(self, message: Any, *, position: Any = ORIGIN, wxyz: Any = IDENTITY, visible: bool = True) -> None:
        name: str = message.name
        parts = name.split("/")[1:-1]
        for depth in range(1, len(parts) + 1):
            ancestor = "/" + "/".join(parts[:depth])
            if ancestor not in self.names:
                anchor = frame_message(ancestor)
                anchor.virtual = True
                self._created(anchor, visible=True)
        self._created(message, visible=visible, position=position, wxyz=wxyz)

    def _created(self, message: Any, *, visible: bool, position: Any = ORIGIN, wxyz: Any = IDENTITY) -> None:
        self.names.add(message.name)
        self.created.append(message.name)
        self.messages.append(message)
        if not _allclose(wxyz, IDENTITY):
            self.messages.append(viser_messages.SetOrientationMessage(message.name, quat(wxyz)))
        if not _allclose(position, ORIGIN):
            self.messages.append(viser_messages.SetPositionMessage(message.name, vec3(position)))
        self.messages.append(viser_messages.SetSceneNodeVisibilityMessage(message.name, visible))

    def shape(self, box: Box, **props: Any) -> None:
        self.add(shape_message(box, **props), position=box.center, wxyz=box.wxyz)

    def roots(self) -> list[str]:
        """The nodes this builder created whose parents it did not: removing them removes all it created."""
        created = set(self.created)
        return [name for name in self.created if name.rsplit("/", 1)[0] not in created]


def static_nodes(scene: Scene) -> SceneNodes:
    """What every trial shows: the floor and its grid, the shelf, the robot's moving frames (at the trial's start
    pose) with their shapes, and the bin's highlight (hidden)."""
    nodes = SceneNodes()
    boxes = scene_boxes(scene)
    nodes.shape(next(b for b in boxes if b.name == "/floor"), cast_shadow=False)
    (x0, y0), (x1, y1) = K.FLOOR_BOUNDS
    nodes.add(viser_messages.GridMessage("/floor_grid", viser_messages.GridProps(
        width=x1 - x0, height=y1 - y0, plane="xy", cell_color=GRID_COLOR, cell_thickness=1.0, cell_size=0.25,
        section_color=GRID_SECTION_COLOR, section_thickness=1.0, section_size=1.0, infinite_grid=False,
        fade_distance=100.0, fade_strength=1.0, fade_from="camera", shadow_opacity=0.2, plane_color=(255, 255, 255),
        plane_opacity=0.0, scale=1.0)), position=((x0 + x1) / 2, (y0 + y1) / 2, 0.001))
    for box in boxes:
        if box.name.startswith("/shelf/"):
            nodes.shape(box)
    start = link_poses(start_state(scene))
    for name in FRAME_NAMES:
        p, q = start[name]
        nodes.add(frame_message(name), position=p, wxyz=q)
    for box in body_shapes(scene):
        if box.name != TARGET_GEOM:
            nodes.shape(box)
    # the bin's opening, in the base frame so that it follows the base for free
    bx, by = K.BIN_XY
    sx, sy, _ = K.BIN_SIZE
    nodes.add(frame_message(BIN_HIGHLIGHT), position=(bx, by, K.BIN_RIM), visible=CREATED_VISIBLE[BIN_HIGHLIGHT])
    band, t = BIN_RIM_BAND, BIN_RIM_THICKNESS
    outer = (sx / 2 + (band - K.BIN_WALL) / 2, sy / 2 + (band - K.BIN_WALL) / 2)
    inner = (outer[0] - band, outer[1] - band)
    nodes.add(mesh_message(f"{BIN_HIGHLIGHT}/rim", *frame_mesh(outer, inner, 0.0, t), HIGHLIGHT_COLOR,
                           flat_shading=True, cast_shadow=False, receive_shadow=False))
    nodes.add(box_message(f"{BIN_HIGHLIGHT}/opening", (sx - 2 * K.BIN_WALL, sy - 2 * K.BIN_WALL, 0.003),
                          HIGHLIGHT_COLOR, opacity=BIN_OPENING_OPACITY, side="double", cast_shadow=False,
                          receive_shadow=False))
    return nodes


def trial_nodes(scene: Scene, existing: Iterable[str]) -> SceneNodes:
    """A trial's part of the scene: its items, its obstacles (high complexity), the target item's shape and what
    marks it (``CREATED_VISIBLE``): the arrow and tag over it, its outline and the pad under it."""
    nodes = SceneNodes(existing)
    for box in scene_boxes(scene):
        if box.name.startswith(("/items/", "/obstacles/")):
            nodes.shape(box)
    nodes.shape(next(b for b in body_shapes(scene) if b.name == TARGET_GEOM))
    target = scene.target
    x, y, tip, _ = arrow_axis(scene)
    bottom = float(target.center[2]) - target.height / 2
    pad = target.width + 0.05
    nodes.add(box_message(TARGET_SLOT, (pad, pad, 0.004), HIGHLIGHT_COLOR, cast_shadow=False),
              position=(x, y, bottom + 0.002), visible=CREATED_VISIBLE[TARGET_SLOT])
    m = HALO_MARGIN
    halo = {"side": "back", "cast_shadow": False, "receive_shadow": False}
    if target.shape == "cylinder":
        nodes.add(cylinder_message(TARGET_HALO, target.width / 2 + m, target.height + 2 * m, HIGHLIGHT_COLOR, **halo),
                  visible=CREATED_VISIBLE[TARGET_HALO])
    else:
        nodes.add(box_message(TARGET_HALO, [float(v) + 2 * m for v in target.size], HIGHLIGHT_COLOR, **halo),
                  visible=CREATED_VISIBLE[TARGET_HALO])
    nodes.add(frame_message(TARGET_MARKER), position=(x, y, tip), visible=CREATED_VISIBLE[TARGET_MARKER])
    vertices, faces = arrow_mesh(ARROW_HEAD, ARROW_HEAD_RADIUS, ARROW_SHAFT, ARROW_SHAFT_RADIUS)
    nodes.add(mesh_message(TARGET_ARROW, vertices, faces, HIGHLIGHT_COLOR, flat_shading=True, cast_shadow=False,
                           receive_shadow=False))
    # drawn over everything, at a constant size on screen; hidden with its parent
    nodes.add(viser_messages.LabelMessage(TARGET_LABEL, viser_messages.LabelProps(
        text=LABEL_TEXT, font_size_mode="screen", font_screen_scale=LABEL_SCALE, font_scene_height=0.075,
        depth_test=False, anchor="bottom-center")), position=(0.0, 0.0, ARROW_HEAD + ARROW_SHAFT + 0.02))
    return nodes


REPLAY_DONE: Message = viser_messages.ReplayDoneMessage().as_serializable_dict([])


class SceneView:
    """The scene of one session as viser messages: what a viewer that connects gets (``replay``), and what turns a
    connected viewer's scene into another trial's (``show_trial``).

    Not thread-safe: the event loop's (``server.viewer.manager``).
    """

    def __init__(self, scene: Scene):
        static = static_nodes(scene)
        self._static_names = frozenset(static.names)
        self._static = Serialized.of([*preamble(), *static.messages])
        self.scene: Scene | None = None
        self._trial = Serialized()
        self._trial_roots: list[str] = []
        self.show_trial(scene)

    def replay(self, current: list[Message]) -> list[bytes]:
        """The wire frames a viewer that connects gets: what viser's server would replay (the preamble and the static
        nodes, then the trial's nodes and the end of the replay), then ``current`` (what moves, as it is now), then
        the scene's stamp (``stamp_frame``)."""
        return [pack(self._static.messages, self._static.buffers),
                pack([*self._trial.messages, REPLAY_DONE], self._trial.buffers),
                *([pack(current)] if current else []), self.stamp_frame()]

    def show_trial(self, scene: Scene) -> bytes | None:
        """Show the items, obstacles and target of ``scene``: the wire frame that removes the trial shown (its stamp
        included) from a connected viewer and creates this one; None if it is already shown. The new stamp comes
        after, once the robot rests where the trial starts (``stamp_frame``)."""
        if self.scene is not None and self.scene.seed == scene.seed and self.scene.complexity == scene.complexity:
            return None
        nodes = trial_nodes(scene, self._static_names)
        trial = Serialized.of(nodes.messages)
        shown = [] if self.scene is None else [stamp_node(self.scene.stamp)]
        removals = Serialized.of(viser_messages.RemoveSceneNodeMessage(name) for name in [*shown, *self._trial_roots])
        self._trial, self._trial_roots, self.scene = trial, nodes.roots(), scene
        return pack([*removals.messages, *trial.messages], trial.buffers)  # (removals carry no binary buffers)

    def stamp_frame(self) -> bytes:
        """The wire frame that creates the shown scene's stamp: an empty frame named ``stamp_node(scene.stamp)``.

        Sent after everything the scene's first picture needs (its nodes, the robot at rest), so a page that finds
        the stamp in the 3D client's scene when a frame begins knows that frame draws this scene (viser's client
        applies messages in order). Resending it is harmless: a node created again replaces itself."""
        assert self.scene is not None
        return pack(Serialized.of([frame_message(stamp_node(self.scene.stamp))]).messages)


def stamp_node(stamp: str) -> str:
    """The scene node whose presence in a 3D client says which scene it holds (``experiment.world.scene_stamp``)."""
    return f"{STAMP_PREFIX}{stamp}"


@functools.cache
def arrow_mesh(head: float, head_radius: float, shaft: float, shaft_radius: float,
               segments: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A closed arrow pointing down -z with its tip at the origin: a cone (``head`` long) under a shaft (made once:
    every trial's marks use it; read-only).

    Faces wind counter-clockwise seen from outside (three.js front faces).
    """
    a = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    top = head + shaft
    vertices = np.concatenate([
        [[0.0, 0.0, 0.0]],  # 0: the tip
        ring * head_radius + (0, 0, head),  # 1..n: the head's rim
        ring * shaft_radius + (0, 0, head),  # n+1..2n: the shaft's foot
        ring * shaft_radius + (0, 0, top),  # 2n+1..3n: the shaft's top
        [[0.0, 0.0, head], [0.0, 0.0, top]],  # 3n+1, 3n+2: centres of the head's back and the shaft's top
    ])
    n = segments
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces.append((0, 1 + j, 1 + i))  # cone side (normals out and down)
        faces.append((3 * n + 1, 1 + i, 1 + j))  # the head's back (faces up)
        faces.append((n + 1 + i, n + 1 + j, 2 * n + 1 + j))  # shaft side
        faces.append((n + 1 + i, 2 * n + 1 + j, 2 * n + 1 + i))
        faces.append((3 * n + 2, 2 * n + 1 + i, 2 * n + 1 + j))  # shaft top (faces up)
    out = vertices.astype(np.float32), np.asarray(faces, dtype=np.uint32)
    for array in out:
        array.flags.writeable = False
    return out


def frame_mesh(outer: tuple[float, float], inner: tuple[float, float], z0: float,
               z1: float) -> tuple[np.ndarray, np.ndarray]:
    """A rectangular ring (a picture frame) lying flat: half sizes ``outer`` and ``inner``, from z0 up to z1."""
    ox, oy = outer
    ix, iy = inner
    corners = [(-ox, -oy), (ox, -oy), (ox, oy), (-ox, oy), (-ix, -iy), (ix, -iy), (ix, iy), (-ix, iy)]
    vertices = np.array([(cx, cy, z) for z in (z0, z1) for cx, cy in corners], dtype=np.float32)
    faces = []
    for i in range(4):
        j = (i + 1) % 4
        o0, o1, i0, i1 = i, j, 4 + i, 4 + j  # bottom layer; +8 for the top
        faces += [(o0 + 8, o1 + 8, i1 + 8), (o0 + 8, i1 + 8, i0 + 8)]  # top (up)
        faces += [(o0, i1, o1), (o0, i0, i1)]  # bottom (down)
        faces += [(o0, o1, o1 + 8), (o0, o1 + 8, o0 + 8)]  # outer wall (out)
        faces += [(i0, i1 + 8, i1), (i0, i0 + 8, i1 + 8)]  # inner wall (towards the middle)
    return vertices, np.asarray(faces, dtype=np.uint32)
