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
  the target), ``/obstacles/<i>`` (high complexity only), ``/target_slot`` (a
  pad marking the target's slot), ``/items/target/geom`` (the target item, in
  the moving frame ``/items/target``).
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

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
from experiment.world.geometry import quat_rotate
from experiment.world.path import ready_joints
from experiment.world.state import shelf_item_state

VIEWS = ("world", "local", "end_effector")
TARGET_GEOM = "/items/target/geom"
TARGET_SLOT = "/target_slot"
TARGET_SLOT_COLOR = (255, 196, 0)
GRID_COLOR = (185, 188, 182)
BRAND_COLOR = (40, 110, 190)
#: The world preset (also every new client's first view): behind and to the left of the robot's start.
WORLD_CAMERA = {"position": (-0.95, -2.4, 1.85), "look_at": (1.25, -0.05, 0.6), "up": (0.0, 0.0, 1.0)}
#: The local preset: a camera behind, beside and above the gripper, offset in the arm's heading frame
#: (ahead, left, up; m), looking at the TCP: it sees into the shelf over the obstacles, and the arm,
#: which stays in its vertical plane, is off its line of sight.
LOCAL_OFFSET = (-0.35, -0.25, 0.28)
#: The end-effector preset: an eye-in-hand camera on the palm's front edge (this far ahead of the tool axis and
#: up it, m), looking down the tool axis, tilted back towards the fingers.
EE_AHEAD, EE_UP, EE_TILT = 0.09, 0.06, 0.21
#: A follow camera moves only when its eye or target moved this much (m), to spare messages.
CAMERA_EPS = 0.002

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


def camera_for(view: str, poses: Mapping[str, Pose]) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """(position, look_at, up) of a camera preset for the robot in ``poses``."""
    if view == "world":
        return WORLD_CAMERA["position"], WORLD_CAMERA["look_at"], WORLD_CAMERA["up"]
    palm_p, palm_q = poses["/robot/palm"]
    tool = quat_rotate(palm_q, (1.0, 0.0, 0.0))
    tcp = tuple(palm_p[i] + K.TCP_OFFSET * tool[i] for i in range(3))
    if view == "local":
        _, heading_q = poses["/robot/j1"]
        off = quat_rotate(heading_q, LOCAL_OFFSET)
        return tuple(tcp[i] + off[i] for i in range(3)), tcp, (0.0, 0.0, 1.0)
    if view == "end_effector":
        ahead = quat_rotate(palm_q, (0.0, 0.0, 1.0))  # the arm's heading when the tool points down
        eye = tuple(palm_p[i] - EE_UP * tool[i] + EE_AHEAD * ahead[i] for i in range(3))
        look = tuple(eye[i] + 0.3 * tool[i] - EE_TILT * ahead[i] for i in range(3))
        return eye, look, ahead
    raise ValueError(f"unknown view {view!r}; expected one of {', '.join(VIEWS)}")


# --- the scene -----------------------------------------------------------------------------

class SceneView:
    """The viser scene of one session: static parts, per-trial parts, moving frames, cameras.

    Not thread-safe: call it from one thread (the viewer manager's thread), except
    for ``__init__``, which may run in a worker thread before the view is shared.
    """

    def __init__(self, server: viser.ViserServer, scene: Scene):
        self.server = server
        self.scene: Scene | None = None
        self.view = "world"
        self._frames: dict[str, Any] = {}
        self._sent: dict[str, Pose] = {}
        self._trial_nodes: list[Any] = []
        self._camera_sent: dict[int, tuple[tuple[float, ...], tuple[float, ...]]] = {}
        self._configure()
        self._build_static(scene)
        self.show_trial(scene)
        self.apply_state(start_state(scene))

    # -- building ------------------------------------------------------------------------
    def _configure(self) -> None:
        server = self.server
        server.gui.configure_theme(show_logo=False, show_share_button=False, dark_mode=False, brand_color=BRAND_COLOR,
                                   control_width="small")
        server.gui.main_panel.minimize()  # 1.1.1 cannot remove it; the client page we serve hides it with CSS
        server.scene.set_up_direction("+z")
        server.scene.configure_default_lights(enabled=True, cast_shadow=True)
        cam = server.initial_camera
        cam.position, cam.look_at, cam.up = WORLD_CAMERA["position"], WORLD_CAMERA["look_at"], WORLD_CAMERA["up"]
        cam.fov = math.radians(50.0)

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
            target = scene.target
            x, y, z = (float(v) for v in target.center)
            bottom = z - target.height / 2
            pad = target.width + 0.04
            self._trial_nodes.append(self.server.scene.add_box(
                TARGET_SLOT, color=TARGET_SLOT_COLOR, dimensions=(pad, pad, 0.004), position=(x, y, bottom + 0.002),
                cast_shadow=False))
            geom = next(b for b in body_shapes(scene) if b.name == TARGET_GEOM)
            self._trial_nodes.append(self._add_shape(geom))
        self.scene = scene
        return True

    # -- moving --------------------------------------------------------------------------
    def apply_state(self, state: WorldState) -> None:
        self.apply_poses(state_poses(state))

    def apply_poses(self, poses: Mapping[str, Any]) -> int:
        """Move the robot and target frames (one atomic update); returns how many frames changed."""
        new = pose_tuples(poses)
        changed = [(name, pose, self._sent.get(name)) for name, pose in new.items()
                   if name in self._frames and self._sent.get(name) != pose]
        if not changed:
            return 0
        with self.server.atomic():
            for name, pose, old in changed:  # position and orientation go separately: often only one moves
                _set_pose(self._frames[name], pose[0] if old is None or old[0] != pose[0] else None,
                          pose[1] if old is None or old[1] != pose[1] else None)
                self._sent[name] = pose
        if self.view != "world":
            self._follow(self.server.get_clients().values())
        # no flush(): ending the atomic block wakes viser's sender at once; every extra wake-up is a
        # self-pipe write from this thread, and those GIL hand-offs are what limits many sessions
        return len(changed)

    @property
    def poses(self) -> dict[str, Pose]:
        """The pose last sent for every moving frame."""
        return dict(self._sent)

    # -- cameras -------------------------------------------------------------------------
    def set_view(self, view: str) -> int:
        """Switch every client of this session to a camera preset; returns how many clients there are."""
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; expected one of {', '.join(VIEWS)}")
        self.view = view
        self._camera_sent.clear()
        clients = list(self.server.get_clients().values())
        self._follow(clients, force=True)
        self.server.flush()
        return len(clients)

    def client_connected(self, client: Any) -> None:
        """A (re)connected client starts with the world preset; give it the session's view instead."""
        self._camera_sent.pop(client.client_id, None)
        if self.view != "world" and client.client_id in self.server.get_clients():
            self._follow([client], force=True)

    def client_disconnected(self, client_id: int) -> None:
        self._camera_sent.pop(client_id, None)

    def _follow(self, clients: Any, force: bool = False) -> None:
        if not self._sent:
            return
        eye, look, up = camera_for(self.view, self._sent)
        for client in clients:
            last = self._camera_sent.get(client.client_id)
            if not force and last is not None and math.dist(last[0], eye) < CAMERA_EPS and math.dist(last[1], look) < CAMERA_EPS:
                continue
            try:
                with client.atomic():
                    camera = client.camera
                    camera.up_direction = up
                    camera.position = eye
                    camera.look_at = look
            except (AssertionError, ValueError):  # no camera state yet, or a degenerate pose
                continue
            self._camera_sent[client.client_id] = (eye, look)


def _set_pose(handle: Any, position: Sequence[float] | None, wxyz: Sequence[float] | None) -> None:
    """Set a scene node's position and/or orientation (None: unchanged).

    The public setters (``handle.position = ...``) compare with ``np.allclose``
    and cost ~65 us each (1.3 ms for the 10 moving frames, i.e. 40 ms per 30 Hz
    tick at 30 sessions). This queues the same two messages through the scene's
    owner-stamping queue (viser 1.1.1 internals, pinned in pyproject.toml and
    covered by tests/server/test_viewer.py) and keeps the handle's state in sync;
    it falls back to the public setters if those internals change.
    """
    impl = getattr(handle, "_impl", None)
    api = getattr(impl, "api", None)
    queue = getattr(api, "_queue_scene_message", None)
    if queue is None or not isinstance(getattr(impl, "position", None), np.ndarray):
        if position is not None:
            handle.position = position
        if wxyz is not None:
            handle.wxyz = wxyz
        return
    if position is not None:
        impl.position[:] = position
        queue(viser_messages.SetPositionMessage(impl.name, tuple(position)))
    if wxyz is not None:
        impl.wxyz[:] = wxyz
        queue(viser_messages.SetOrientationMessage(impl.name, tuple(wxyz)))
