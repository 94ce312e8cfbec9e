"""The 3D scene of one participant session, drawn by its own loopback ``ViserServer``.

Built from the world's primitives (``experiment.world.render``): ``scene_boxes``
gives the floor, the shelf, the other items and the obstacles in world
coordinates; ``body_shapes`` gives the robot's (and the target item's) shapes
relative to the moving frames of ``link_poses``, which are created once under
their ``FRAME_NAMES`` and then only moved (30 Hz, one ``atomic`` block a tick).

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
  (a rim frame and a translucent plane), shown only while the item is held.

The scene is created once per session server and the trial's part rebuilt when the trial changes; viser
replays it to every viewer that connects. What moves (the frames' poses, which marks show, a follow camera)
does not go through viser's server: ``server.viewer.live`` sends it. The marks are created as a trial starts
(``CREATED_VISIBLE``: the target's shown, the bin's hidden).
"""

from __future__ import annotations

import contextlib
import math
import threading
import typing
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import rich
import viser
from viser._assignable_props_api import AssignablePropsBase

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
from experiment.world.path import ready_joints
from experiment.world.state import shelf_item_state
from server.viewer.cameras import VIEW_FOV_DEG, world_camera

TARGET_GEOM = "/items/target/geom"
TARGET_SLOT = "/target_slot"
TARGET_MARKER = "/target_marker"
TARGET_ARROW = "/target_marker/arrow"
TARGET_LABEL = "/target_marker/label"
TARGET_HALO = "/items/target/halo"
BIN_HIGHLIGHT = "/robot/base/bin_highlight"
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
GRID_COLOR = (185, 188, 182)
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


def _prop_hints_of_class(handle: Any) -> dict[str, Any]:
    """The type hints of a handle's props class, worked out once per class."""
    props_class = type(handle._impl.props)
    hints = _PROP_HINTS.get(props_class)
    if hints is None:
        hints = _PROP_HINTS[props_class] = typing.get_type_hints(props_class)
    return hints


# viser 1.1.1 works out a scene handle's props' type hints (``typing.get_type_hints``) once per handle: every node
# a trial's scene creates paid for it again, half of the then viewer thread's share of the interpreter lock at 100
# participants (py-spy). The hints depend on the props class alone, so they are kept per class (viser is pinned;
# tests/server/test_viewer_live.py checks that this still replaces viser's own).
_PROP_HINTS: dict[type, dict[str, Any]] = {}
AssignablePropsBase._prop_hints = property(_prop_hints_of_class)  # type: ignore[assignment]


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
    q = tuple(float(v) for v in ready_joints())
    return WorldState(0.0, scene.start, q, K.GRIPPER_MAX, K.GRIPPER_MAX, shelf_item_state(scene))  # type: ignore[arg-type]


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


class SceneView:
    """The viser scene of one session: static parts, per-trial parts, the moving frames at their start pose.

    Not thread-safe: call it from one thread (the event loop: ``server.viewer.manager``), except
    for ``__init__``, which may run in a worker thread before the view is shared.
    """

    def __init__(self, server: viser.ViserServer, scene: Scene):
        self.server = server
        self.scene: Scene | None = None
        self._frames: dict[str, Any] = {}
        self._trial_nodes: list[Any] = []
        self._configure()
        self._build_static(scene)
        self.show_trial(scene)

    # -- building ------------------------------------------------------------------------
    def _configure(self) -> None:
        server = self.server
        server.gui.configure_theme(show_logo=False, show_share_button=False, dark_mode=False, brand_color=BRAND_COLOR,
                                   control_width="small")
        server.gui.main_panel.minimize()  # 1.1.1 cannot remove it; the client page we serve hides it with CSS
        server.scene.set_up_direction("+z")
        server.scene.configure_default_lights(enabled=True, cast_shadow=True)
        cam = server.initial_camera  # every new client's first view, and viser's "reset view"
        cam.position, cam.look_at = world_camera(MARKER_HEIGHT)
        cam.up = (0.0, 0.0, 1.0)
        cam.fov = math.radians(VIEW_FOV_DEG["world"])

    def _build_static(self, scene: Scene) -> None:
        api = self.server.scene
        boxes = scene_boxes(scene)
        floor = next(b for b in boxes if b.name == "/floor")
        self._add_shape(floor, cast_shadow=False)
        (x0, y0), (x1, y1) = K.FLOOR_BOUNDS
        api.add_grid("/floor_grid", width=x1 - x0, height=y1 - y0, cell_size=0.25, section_size=1.0,
                     cell_color=GRID_COLOR, section_color=(150, 152, 146), position=((x0 + x1) / 2, (y0 + y1) / 2, 0.001),
                     shadow_opacity=0.2)
        for box in boxes:
            if box.name.startswith("/shelf/"):
                self._add_shape(box)
        start = link_poses(start_state(scene))
        for name in FRAME_NAMES:
            p, q = start[name]
            self._frames[name] = api.add_frame(name, show_axes=False, position=tuple(p), wxyz=tuple(q))
        for box in body_shapes(scene):
            if box.name != TARGET_GEOM:
                self._add_shape(box)
        self._build_bin_highlight()

    def _build_bin_highlight(self) -> None:
        """The bin's opening on the base (in the base frame, so it follows the base for free), hidden."""
        api = self.server.scene
        bx, by = K.BIN_XY
        sx, sy, _ = K.BIN_SIZE
        api.add_frame(BIN_HIGHLIGHT, show_axes=False, position=(bx, by, K.BIN_RIM), visible=CREATED_VISIBLE[BIN_HIGHLIGHT])
        band, t = BIN_RIM_BAND, BIN_RIM_THICKNESS
        outer = (sx / 2 + (band - K.BIN_WALL) / 2, sy / 2 + (band - K.BIN_WALL) / 2)
        inner = (outer[0] - band, outer[1] - band)
        vertices, faces = frame_mesh(outer, inner, 0.0, t)
        api.add_mesh_simple(f"{BIN_HIGHLIGHT}/rim", vertices, faces, color=HIGHLIGHT_COLOR, flat_shading=True,
                            cast_shadow=False, receive_shadow=False)
        api.add_box(f"{BIN_HIGHLIGHT}/opening", color=HIGHLIGHT_COLOR,
                    dimensions=(sx - 2 * K.BIN_WALL, sy - 2 * K.BIN_WALL, 0.003), position=(0.0, 0.0, 0.0),
                    opacity=BIN_OPENING_OPACITY, side="double", cast_shadow=False, receive_shadow=False)

    def _add_shape(self, box: Box, *, cast_shadow: bool = True) -> Any:
        api = self.server.scene
        center = tuple(float(v) for v in box.center)
        wxyz = tuple(float(v) for v in box.wxyz)
        color = tuple(int(c) for c in box.color)
        if box.shape == "cylinder":
            return api.add_cylinder(box.name, radius=float(box.size[0]) / 2, height=float(box.size[2]), color=color,
                                    radial_segments=24, position=center, wxyz=wxyz, cast_shadow=cast_shadow)
        return api.add_box(box.name, color=color, dimensions=tuple(float(v) for v in box.size), position=center,
                           wxyz=wxyz, cast_shadow=cast_shadow)

    def show_trial(self, scene: Scene) -> bool:
        """Show the items, obstacles and target of ``scene`` (no-op if it is already shown); True if rebuilt."""
        if self.scene is not None and self.scene.seed == scene.seed and self.scene.complexity == scene.complexity:
            return False
        with self.server.atomic():
            for handle in self._trial_nodes:
                handle.remove()
            self._trial_nodes = []
            for box in scene_boxes(scene):
                if box.name.startswith(("/items/", "/obstacles/")):
                    self._trial_nodes.append(self._add_shape(box))
            geom = next(b for b in body_shapes(scene) if b.name == TARGET_GEOM)
            self._trial_nodes.append(self._add_shape(geom))
            self._add_target_marks(scene)
        self.scene = scene
        return True

    def _add_target_marks(self, scene: Scene) -> None:
        """The arrow and tag over the target, its outline and the pad under it (``CREATED_VISIBLE``)."""
        api = self.server.scene
        target = scene.target
        x, y, tip, _ = arrow_axis(scene)
        bottom = float(target.center[2]) - target.height / 2
        pad = target.width + 0.05
        marks = [api.add_box(TARGET_SLOT, color=HIGHLIGHT_COLOR, dimensions=(pad, pad, 0.004),
                             position=(x, y, bottom + 0.002), cast_shadow=False, visible=CREATED_VISIBLE[TARGET_SLOT])]
        m = HALO_MARGIN
        if target.shape == "cylinder":
            marks.append(api.add_cylinder(TARGET_HALO, radius=target.width / 2 + m, height=target.height + 2 * m,
                                          color=HIGHLIGHT_COLOR, radial_segments=24, side="back", cast_shadow=False,
                                          receive_shadow=False, visible=CREATED_VISIBLE[TARGET_HALO]))
        else:
            marks.append(api.add_box(TARGET_HALO, color=HIGHLIGHT_COLOR, side="back", cast_shadow=False,
                                     receive_shadow=False, visible=CREATED_VISIBLE[TARGET_HALO],
                                     dimensions=tuple(float(v) + 2 * m for v in target.size)))
        marker = api.add_frame(TARGET_MARKER, show_axes=False, position=(x, y, tip),
                               visible=CREATED_VISIBLE[TARGET_MARKER])
        vertices, faces = arrow_mesh(ARROW_HEAD, ARROW_HEAD_RADIUS, ARROW_SHAFT, ARROW_SHAFT_RADIUS)
        api.add_mesh_simple(TARGET_ARROW, vertices, faces, color=HIGHLIGHT_COLOR, flat_shading=True,
                            cast_shadow=False, receive_shadow=False)
        api.add_label(TARGET_LABEL, LABEL_TEXT, position=(0.0, 0.0, ARROW_HEAD + ARROW_SHAFT + 0.02),
                      anchor="bottom-center", depth_test=False, font_screen_scale=LABEL_SCALE)  # drawn over everything; hidden with its parent
        self._trial_nodes += [*marks, marker]


def arrow_mesh(head: float, head_radius: float, shaft: float, shaft_radius: float,
               segments: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A closed arrow pointing down -z with its tip at the origin: a cone (``head`` long) under a shaft.

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
    return vertices.astype(np.float32), np.asarray(faces, dtype=np.uint32)


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
