"""What moves in a session's 3D view: built on the event loop, written by the viewer sockets to the browsers.

A session's ``SceneView`` holds the scene's nodes: the static parts, the trial's items, obstacles and marks,
replayed to every viewer that connects (``server.viewer.scene``). Everything that changes while a trial runs:

- ``LiveView`` (one per session, event loop only) turns a world state into viser messages: the poses of
  the moving frames (``FRAME_NAMES`` and the target item) and, in the follow camera presets, the camera; which
  marks show (the target's while the item is on the shelf, the arrow not while the palm is at it, the bin's
  while the item is held), as a change.
- ``ViewerSink`` (one per viewer socket) holds what is still to be written to it: first the scene's replay, then
  in order the scene's changes (a new trial's nodes, packed once for every viewer of the session) and the
  changes of marks, and, merged, the newest pose of every frame that moved and the newest camera, sent together
  as one wire frame (``server.viewer.wire``). A socket that cannot keep up gets fewer, larger frames and loses
  nothing.

Messages are plain dicts as ``Message.as_serializable_dict`` gives them (building viser's message objects and
serialising them costs ~10x more per frame).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from experiment.world import FRAME_NAMES, ItemMode, Scene, WorldState, body_shapes, teleop_start_state
from server.viewer.cameras import VIEW_FOV_DEG, VIEWS, box_corners, camera_for, world_camera
from server.viewer.scene import (
    BIN_BOX,
    BIN_HIGHLIGHT,
    CREATED_VISIBLE,
    MARKER_HEIGHT,
    TARGET_GEOM,
    TARGET_HALO,
    TARGET_MARKER,
    TARGET_SLOT,
    Pose,
    arrow_axis,
    start_state,
    state_poses,
)
from server.viewer.wire import Message, pack

#: The arrow (and its tag) hides while the palm is this close to it (m), by camera preset: in the end-effector
#: view from farther away (seen from above, its head covers the item under it: with the gripper at the ready
#: pose over a bottom-shelf item the palm is 0.24 m from it), in the others only as the arm reaches it (it
#: would pass through it). It shows again this much farther away. The outline and the pad stay.
MARKER_HIDE_RADIUS = {"world": 0.12, "local": 0.12, "end_effector": 0.35}
MARKER_HIDE_HYSTERESIS = 0.03
#: The frames that move (the robot's links and the target item), in the order a frame lists them.
MOVING = FRAME_NAMES

def _visibility(name: str, visible: bool) -> Message:
    return {"name": name, "visible": visible, "owner": "", "type": "SetSceneNodeVisibilityMessage"}


def camera_messages(eye: Iterable[float], look: Iterable[float], up: Iterable[float], fov: float) -> list[Message]:
    """A camera pose as viser's client camera setters send it (field of view, up, position, look-at)."""
    return [{"fov": fov, "initial": False, "type": "SetCameraFovMessage"},
            {"position": tuple(up), "initial": False, "type": "SetCameraUpDirectionMessage"},
            {"position": tuple(eye), "initial": False, "type": "SetCameraPositionMessage"},
            {"look_at": tuple(look), "initial": False, "type": "SetCameraLookAtMessage"}]


class LiveView:
    """What a session's viewers see move: the trial's scene, the state shown, the camera preset.

    Not thread-safe: the event loop's (the world tick, the poll, the camera route).
    """

    def __init__(self, scene: Scene, view: str = "world", stage: str | None = None):
        self.view = view
        self.stage = stage  # decision | attempt | teleop, or None between trials
        self.live = False  # showing the hub's world (otherwise the robot rests)
        self.frames = 0  # frames built from the hub's worlds
        self.poses: dict[str, Pose] = {}
        self.item_mode = ItemMode.ON_SHELF
        self.near_marker = False
        self.shown = dict(CREATED_VISIBLE)  # what the viewers show of the marks
        self.scene = scene
        self._set_scene(scene)

    # -- what is shown -----------------------------------------------------------------------------------
    def _set_scene(self, scene: Scene) -> None:
        self.scene = scene
        self._arrow_axis = arrow_axis(scene)
        self._target_box = next(b for b in body_shapes(scene) if b.name == TARGET_GEOM)
        # the viser scene rebuilds the trial's marks as they are created
        self.shown.update({name: CREATED_VISIBLE[name] for name in (TARGET_SLOT, TARGET_HALO, TARGET_MARKER)})
        self.item_mode, self.near_marker = ItemMode.ON_SHELF, False

    def show_trial(self, scene: Scene) -> bool:
        """Show ``scene`` (its viser nodes are rebuilt elsewhere); True if it is another trial's."""
        if self.scene.seed == scene.seed and self.scene.complexity == scene.complexity:
            return False
        self._set_scene(scene)
        self.live = False
        return True

    def resting_state(self) -> WorldState:
        """The robot at rest for the stage: at the trial's start pose, or where teleoperation starts."""
        return teleop_start_state(self.scene) if self.stage == "teleop" else start_state(self.scene)

    def update(self, state: WorldState) -> tuple[list[Message], list[Message]]:
        """Show ``state``: (changes of marks, the pose frame); the frame is empty when nothing moved."""
        poses = state_poses(state)
        mode = state.item.mode
        near = mode == ItemMode.ON_SHELF and self._near(poses["/robot/palm"][0])
        self.item_mode, self.near_marker = mode, near
        changes = self._mark_changes()
        new = {name: _pose(poses[name]) for name in MOVING}
        if new == self.poses:
            return changes, []
        old, self.poses = self.poses, new
        frame: list[Message] = []
        for name, (position, wxyz) in new.items():  # only what moved (while teleoperated the base stands still)
            before = old.get(name)
            if before is None or before[0] != position:
                frame.append({"name": name, "position": position, "owner": "", "type": "SetPositionMessage"})
            if before is None or before[1] != wxyz:
                frame.append({"name": name, "wxyz": wxyz, "owner": "", "type": "SetOrientationMessage"})
        return changes, frame + self._follow_camera()

    def follow(self, world_state: WorldState | None) -> tuple[list[Message], list[Message]]:
        """A world tick: show the hub's world of this trial (None: the last pose holds until the poll says what
        comes next)."""
        if world_state is None or self.stage is None:
            return [], []
        self.live = True
        self.frames += 1
        return self.update(world_state)

    def rest(self) -> tuple[list[Message], list[Message]]:
        """Show the robot at rest, unless it follows the hub's world."""
        return ([], []) if self.live else self.update(self.resting_state())

    def whole(self) -> list[Message]:
        """Everything a newly connected viewer needs after the scene's replay: the marks that differ from how
        they were created, every pose, the camera of a follow preset (the world preset is the replay's initial
        camera)."""
        if not self.poses:
            self.update(self.resting_state())
        marks = [_visibility(name, visible) for name, visible in self.shown.items() if visible != CREATED_VISIBLE[name]]
        return marks + self._pose_messages() + self._follow_camera()

    def set_view(self, view: str) -> list[Message]:
        """Switch to a camera preset: the messages that move every viewer's camera (and marks) there."""
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; expected one of {', '.join(VIEWS)}")
        self.view = view
        if not self.poses:
            self.update(self.resting_state())
        palm = self.poses["/robot/palm"][0]
        self.near_marker = self.item_mode == ItemMode.ON_SHELF and self._near(palm)  # its radius depends on the view
        return self._mark_changes() + self._camera(view)

    # -- pieces -------------------------------------------------------------------------------------------
    def _mark_changes(self) -> list[Message]:
        on_shelf = self.item_mode == ItemMode.ON_SHELF
        wanted = {TARGET_SLOT: on_shelf, TARGET_HALO: on_shelf, TARGET_MARKER: on_shelf and not self.near_marker,
                  BIN_HIGHLIGHT: self.item_mode == ItemMode.GRASPED}
        changes = [_visibility(name, visible) for name, visible in wanted.items() if self.shown[name] != visible]
        self.shown.update(wanted)
        return changes

    def _near(self, palm: Any) -> bool:
        """Whether the palm (and the end-effector camera on it) is at the arrow, with some hysteresis."""
        x, y, z0, z1 = self._arrow_axis
        z = palm[2]
        dz = z0 - z if z < z0 else z - z1 if z > z1 else 0.0
        d2 = (palm[0] - x) ** 2 + (palm[1] - y) ** 2 + dz * dz
        r = MARKER_HIDE_RADIUS[self.view] + (MARKER_HIDE_HYSTERESIS if self.near_marker else 0.0)
        return d2 < r * r

    def _pose_messages(self) -> list[Message]:
        out: list[Message] = []
        for name, (position, wxyz) in self.poses.items():
            out.append({"name": name, "position": position, "owner": "", "type": "SetPositionMessage"})
            out.append({"name": name, "wxyz": wxyz, "owner": "", "type": "SetOrientationMessage"})
        return out

    def _follow_camera(self) -> list[Message]:
        return [] if self.view == "world" else self._camera(self.view)

    def _camera(self, view: str) -> list[Message]:
        if view == "world":
            eye, look = world_camera(MARKER_HEIGHT)
            up: Any = (0.0, 0.0, 1.0)
        else:
            eye, look, up = camera_for(view, self.poses, marker_height=MARKER_HEIGHT, focus=self._local_focus())
        return camera_messages(eye, look, up, math.radians(VIEW_FOV_DEG[view]))

    def _local_focus(self) -> np.ndarray | None:
        """What the local camera keeps in view besides the gripper: the item (on the shelf, or where it fell),
        the bin's opening while the item is held, nothing once it is in the bin."""
        if self.view != "local":
            return None
        mode = self.item_mode
        if mode in (ItemMode.ON_SHELF, ItemMode.DROPPED):
            return box_corners(self._target_box, *self.poses["/items/target"])
        if mode == ItemMode.GRASPED:
            return box_corners(BIN_BOX, *self.poses["/robot/base"])
        return None


def _pose(pose: Any) -> Pose:
    p, q = pose
    return (float(p[0]), float(p[1]), float(p[2])), (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


class ViewerSink:
    """What is still to be written to one viewer socket (event loop only).

    Nothing is queued before the sink starts with the scene's replay (``start``): poses for nodes the viewer has
    not created yet would be lost. ``close`` ends it (its session's view stopped).
    """

    def __init__(self) -> None:
        self.ready = False
        self.closed = False
        self.packed: list[bytes] = []  # wire frames to write before the changes and the frame below, in order
        self.changes: list[Message] = []
        self.frame: dict[tuple[str, str], Message] = {}  # pose and camera messages by (type, node): the newest
        self.sent = 0  # wire frames written
        self.merged = 0  # pose frames merged into one not yet written (a slow socket)
        self._wake = asyncio.Event()

    def start(self, replay: list[bytes]) -> None:
        """From now on the viewer gets what changes, after ``replay`` (the scene as it is now)."""
        self.ready = True
        self.packed, self.changes, self.frame = list(replay), [], {}
        self._wake.set()

    def offer(self, changes: list[Message], frame: list[Message]) -> None:
        if not self.ready or not (changes or frame):
            return
        self.changes += changes
        if frame:
            self.merged += bool(self.frame)
            self.frame.update({(m["type"], m.get("name", "")): m for m in frame})
        self._wake.set()

    def offer_packed(self, data: bytes) -> None:
        """A wire frame (a change of the scene), after everything offered before it."""
        if not self.ready:
            return
        if self.changes or self.frame:
            self.packed.append(self._pack_pending())
        self.packed.append(data)
        self._wake.set()

    def close(self) -> None:
        self.closed = True
        self._wake.set()

    async def next(self) -> bytes | None:
        """The next wire frame to write (waits until there is one); None once the sink is closed."""
        while not (self.closed or self.packed or self.changes or self.frame):
            self._wake.clear()
            await self._wake.wait()
        if self.closed:
            return None
        self.sent += 1
        return self.packed.pop(0) if self.packed else self._pack_pending()

    def _pack_pending(self) -> bytes:
        messages, self.changes, self.frame = self.changes + list(self.frame.values()), [], {}
        return pack(messages)


def offer_all(sinks: Iterable[ViewerSink], changes: list[Message], frame: list[Message]) -> None:
    for sink in sinks:
        sink.offer(changes, frame)


__all__ = ["LiveView", "ViewerSink", "camera_messages", "offer_all"]
