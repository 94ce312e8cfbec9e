"""The camera presets of the 3D view: where each stands, and every number that decides it.

Pure geometry (numpy and ``experiment.world``; no viser), so it is tested without a server:

- ``frame_points`` places a perspective camera of a given angle (yaw, pitch), field of view and aspect so
  that every given point is in view with a margin, as close as that allows: the tighter of the horizontal
  and vertical fits decides the distance, the other direction is centred. The world and local presets are
  both framed this way.
- **world**: one pose for every trial of every participant (the angle never changes; neither does the
  position). It frames the union of what any trial shows (``world_scene_points``): the shelf, the robot
  with its arm at the ready pose and the bin on it both where it starts a trial (``DRIVE_DISTANCE`` behind
  its parking place: where it stands while the participant decides whether to intervene) and parked in
  front of any column, the obstacles and the target arrow of any slot. So the whole drive to the shelf is in
  view, and during the decision window the robot, the shelf and the target are all in the picture, none
  close to the camera.
- **local** (gripper area): follows the gripper at a fixed angle to the arm's heading, framing the gripper
  and what it works on: the target item while it is on the shelf (so an item on the bottom shelf stays in
  view with the gripper high above it), the bin while the item is held.
- **end effector**: a camera on the hand, behind the palm (on the robot's side) and above it, looking down
  along the tool axis and slightly forward, at a point under the gripper: what is right under the gripper
  is on the view's vertical centre line, around its middle; the fingertips show in the upper part, the
  palm does not block the view, a held item covers only its upper middle.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from itertools import product

import numpy as np

from experiment.world import constants as K
from experiment.world.geometry import Box, quat_rotate, vec3, yaw_of
from experiment.world.path import ready_joints
from experiment.world.render import body_shapes, link_poses
from experiment.world.scene import Scene, build_scene, shelf_boxes, slot_position
from experiment.world.state import WorldState, as_joints, shelf_item_state

Vec3 = tuple[float, float, float]
Pose = tuple[Vec3, tuple[float, float, float, float]]
Numbers = Sequence[float] | np.ndarray  # a sequence or a 1-D array
VIEWS = ("world", "local", "end_effector")


@dataclass(frozen=True)
class Framing:
    """The design choices of a framed camera.

    ``yaw_deg``: heading of the line of sight (world: 0 looks along +x, at the shelf's front; local: relative
    to the arm's heading; positive turns it towards +y, i.e. the camera stands to the right);
    ``pitch_deg``: its elevation (negative: looking down); ``vfov_deg``: vertical field of view;
    ``margin``: share of the view's half-width and half-height kept free on every side;
    ``aspect``: width / height of the view it is framed for.
    """

    yaw_deg: float
    pitch_deg: float
    vfov_deg: float
    margin: float
    aspect: float


#: The page's 3D view: static/css/participant.css gives .viewer an aspect-ratio of 16 / 10 (848x530 at
#: 1280x720, 1488x928 at 1920x1080); its max-height only ever makes it wider, which adds room at the sides.
PAGE_ASPECT = 16 / 10

#: The world preset. Behind the robot and to its right (the mast's side, so the arm does not hide the bin on
#: the base's rear left), 28 deg off the shelf's axis: into the shelf's tiers, with depth, and the keys' moves
#: read on screen as the instructions say (W into the picture, A to the left). 34 deg down: over the obstacles
#: (at most 0.10 m above the item they stand before) onto the lower tier and into the bin. 45 deg vertical field
#: of view (viser's 75 deg default draws the near robot large and the shelf small). Framing the robot at its
#: start too puts the camera about 2.1 m from the nearest part of it (it stood 0.7 m from the arm before, which
#: then filled a corner of the view while the robot itself was out of it).
WORLD_FRAMING = Framing(yaw_deg=28.0, pitch_deg=-34.0, vfov_deg=45.0, margin=0.04, aspect=PAGE_ASPECT)

#: The local preset: 50 deg to the right of the arm's heading (the arm stays in its vertical plane: from
#: here the forearm covers about half as much of the view as from 35 deg behind, and the items of the
#: target's row still show side by side), 40 deg down (over the obstacles into the lower tier). It frames a
#: cube of ``LOCAL_MIN_HALF`` half size around the tool centre point (m; how close it comes) and what the
#: gripper works on.
LOCAL_FRAMING = Framing(yaw_deg=50.0, pitch_deg=-40.0, vfov_deg=50.0, margin=0.08, aspect=PAGE_ASPECT)
LOCAL_MIN_HALF = 0.18

#: The end-effector preset: the eye this far behind the palm (towards the robot, m) and this far above it
#: (up the tool axis, m), looking at the point of the tool axis this far below the tool centre point (m;
#: 14 deg forward of straight down, which centres the column under the gripper from 0.05 to 0.8 m down).
#: The fingertips show ~20 deg above the view's centre, the palm and the wrist just out of view; a held item
#: covers the upper middle of the view, what is under it shows below. Vertical field of view 65 deg (~46 deg
#: each side horizontally at 16:10): the item under the gripper and its neighbours.
EE_BEHIND, EE_UP, EE_FOCUS, EE_FOV_DEG = 0.08, 0.04, 0.22, 65.0

#: The vertical field of view of each preset (deg), set on the client with the pose.
VIEW_FOV_DEG = {"world": WORLD_FRAMING.vfov_deg, "local": LOCAL_FRAMING.vfov_deg, "end_effector": EE_FOV_DEG}


# --- framing ---------------------------------------------------------------------------------------------

def view_axes(yaw_deg: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit (right, up, forward) (3,) of a camera with z up, looking along yaw/pitch."""
    cy, sy = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    cp, sp = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    return np.array([sy, -cy, 0.0]), np.array([-cy * sp, -sy * sp, cp]), np.array([cp * cy, cp * sy, sp])


def half_tangents(vfov_deg: float, aspect: float) -> tuple[float, float]:
    """tan of the half horizontal and half vertical fields of view."""
    ty = math.tan(math.radians(vfov_deg) / 2)
    return aspect * ty, ty


def frame_points(points: np.ndarray, framing: Framing, aspect: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), look_at (3,)): the closest camera of ``framing``'s angle with every point in view.

    points: (N, 3) world points; aspect: of the view (default: the framing's). In camera coordinates each
    point must satisfy |x| <= tx * depth and |y| <= ty * depth (tx, ty: the half tangents shrunk by the
    margin), which is linear in the camera's position: the closest position is where a pair of opposite
    view planes both touch a point; the other pair is centred on the points. ``look_at`` is on the line of
    sight at the depth of the points' bounding-box centre (what the camera orbits if the participant drags).
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    right, up, forward = view_axes(framing.yaw_deg, framing.pitch_deg)
    tx, ty = half_tangents(framing.vfov_deg, framing.aspect if aspect is None else aspect)
    shrink = 1 - framing.margin
    a, b, c = pts @ right, pts @ up, pts @ forward
    # per axis, the camera's depth along the line of sight may be at most c - |s - offset| / t for every point
    fits = [(float(np.min(c - s / t)), float(np.min(c + s / t)), s, t) for s, t in ((a, tx * shrink), (b, ty * shrink))]
    depth = min((lo + hi) / 2 for lo, hi, _, _ in fits)
    alpha, beta = (_centred(s, c - depth, t * (depth - lo), t * (hi - depth)) for lo, hi, s, t in fits)
    position = alpha * right + beta * up + depth * forward
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    return position, position + forward * float((centre - position) @ forward)


def _centred(s: np.ndarray, depth: np.ndarray, lo: float, hi: float) -> float:
    """The offset in [lo, hi] putting the points' extremes (s - offset) / depth symmetric about the centre.

    For the pair of extreme points i, j, (s_i - o) / d_i + (s_j - o) / d_j = 0 gives o; the extremes may
    change with o, so repeat until they do not (two or three rounds; exact, unlike a bisection, and cheap).
    """
    inverse = 1.0 / depth
    offset = (lo + hi) / 2
    pair = (-1, -1)
    for _ in range(8):
        ratios = (s - offset) * inverse
        i, j = int(np.argmax(ratios)), int(np.argmin(ratios))
        if (i, j) == pair:
            break
        pair = (i, j)
        offset = (s[i] * inverse[i] + s[j] * inverse[j]) / (inverse[i] + inverse[j])
    return min(max(offset, lo), hi)


def project(points: np.ndarray, position, look_at, vfov_deg: float, aspect: float, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(N, 3): each point's horizontal and vertical place in the view (-1..1, edge to edge) and its depth (m)."""
    forward = np.asarray(look_at, dtype=float) - np.asarray(position, dtype=float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=float))
    right /= np.linalg.norm(right)
    rel = np.asarray(points, dtype=float).reshape(-1, 3) - np.asarray(position, dtype=float)
    depth = rel @ forward
    tx, ty = half_tangents(vfov_deg, aspect)
    return np.stack([rel @ right / (depth * tx), rel @ np.cross(right, forward) / (depth * ty), depth], axis=1)


_CORNER_SIGNS = np.array(list(product((-0.5, 0.5), repeat=3)))


def box_corners(box: Box, position: Numbers = (0.0, 0.0, 0.0), wxyz: Numbers = (1.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """(8, 3): the corners of ``box`` (given in its parent frame) placed by the parent's pose."""
    local = (_CORNER_SIGNS * box.size) @ _rotation(box.wxyz).T + box.center
    return local @ _rotation(wxyz).T + np.asarray(position, dtype=float)


def _rotation(wxyz: Numbers) -> np.ndarray:
    """(3, 3) rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# --- world -----------------------------------------------------------------------------------------------

def world_scene_points(marker_height: float) -> np.ndarray:
    """(N, 3): what the world camera shows in every trial.

    The shelf; for every slot, the robot with the arm at the ready pose (base, bin, mast, links, gripper) where
    it starts the trial (``scene.start``, ``DRIVE_DISTANCE`` behind: where it stands while the participant decides)
    and parked for it, the obstacles that can stand before it (their widest, highest spread) and the target
    marker over the tallest item (``marker_height``: from the item's top to the marker's top, m).
    """
    points = [box_corners(box) for box in shelf_boxes()]
    widest, gap = K.OBSTACLE_WIDTH_RANGE[1], K.OBSTACLE_SIDE_GAP_RANGE[1]
    spread = widest / 2 + gap + widest  # the farthest flanking obstacle's outer side from the column
    back = K.SHELF_FRONT_X - K.OBSTACLE_FRONT_GAP
    for slot in range(K.N_SLOTS):
        scene = build_scene("low", 0, target_slot=slot)
        for base in (scene.start, scene.park):
            points.append(robot_points(scene, base))
        x, y, board = slot_position(slot)
        top = board + K.ITEM_HEIGHT_RANGE[1]  # the tallest item the slot can hold
        points.append(np.array(list(product((back - K.OBSTACLE_DEPTH_RANGE[1], back), (y - spread, y + spread),
                                            (0.0, top + K.OBSTACLE_ABOVE_ITEM_RANGE[1])))))
        points.append(np.array([[x, y, top + marker_height]]))
    return np.concatenate(points)


def robot_points(scene: Scene, base: Sequence[float], joints: Sequence[float] | None = None) -> np.ndarray:
    """(N, 3): the corners of the robot's bodies (base, bin, mast, links, gripper; not the item) with its base at
    ``base`` (x, y, yaw) and the arm at ``joints`` (default: the ready pose)."""
    q = as_joints(ready_joints() if joints is None else joints)
    frames = link_poses(WorldState(0.0, vec3(base), q, K.GRIPPER_MAX, K.GRIPPER_MAX, shelf_item_state(scene)))
    return np.concatenate([box_corners(shape, *frames[shape.name.rsplit("/", 1)[0]]) for shape in body_shapes(scene)
                           if not shape.name.startswith("/items/")])


@functools.lru_cache(maxsize=16)
def world_camera(marker_height: float, aspect: float = PAGE_ASPECT) -> tuple[Vec3, Vec3]:
    """(position, look_at) of the world preset, framed for a view of ``aspect``."""
    position, look_at = frame_points(world_scene_points(marker_height), WORLD_FRAMING, aspect)
    return vec3(position), vec3(look_at)


# --- following the gripper -------------------------------------------------------------------------------

def heading_deg(poses: Mapping[str, Pose]) -> float:
    """The arm's heading (deg, about z) from the ``/robot/j1`` frame."""
    return math.degrees(yaw_of(poses["/robot/j1"][1]))


def tcp_of(poses: Mapping[str, Pose]) -> Vec3:
    palm_p, palm_q = poses["/robot/palm"]
    tool = quat_rotate(palm_q, (1.0, 0.0, 0.0))
    return vec3(palm_p[i] + K.TCP_OFFSET * tool[i] for i in range(3))


def local_camera(poses: Mapping[str, Pose], focus: np.ndarray | None = None) -> tuple[Vec3, Vec3]:
    """(position, look_at) of the local preset: the gripper and ``focus`` ((N, 3) points, e.g. the item)."""
    tcp = np.array(tcp_of(poses))
    h = LOCAL_MIN_HALF
    points = tcp + np.array(list(product((-h, h), repeat=3)))
    if focus is not None and len(focus):
        points = np.concatenate([points, np.asarray(focus, dtype=float).reshape(-1, 3)])
    framing = replace(LOCAL_FRAMING, yaw_deg=heading_deg(poses) + LOCAL_FRAMING.yaw_deg)
    position, look_at = frame_points(points, framing)
    return vec3(position), vec3(look_at)


def end_effector_camera(poses: Mapping[str, Pose]) -> tuple[Vec3, Vec3, Vec3]:
    """(position, look_at, up) of the end-effector preset; up is the arm's heading (ahead is up)."""
    palm_p, palm_q = poses["/robot/palm"]
    tool = quat_rotate(palm_q, (1.0, 0.0, 0.0))
    ahead = quat_rotate(palm_q, (0.0, 0.0, 1.0))  # the arm's heading while the tool points down
    eye = vec3(palm_p[i] - EE_UP * tool[i] - EE_BEHIND * ahead[i] for i in range(3))
    look = vec3(palm_p[i] + (K.TCP_OFFSET + EE_FOCUS) * tool[i] for i in range(3))
    return eye, look, vec3(ahead)


def camera_for(view: str, poses: Mapping[str, Pose], *, marker_height: float,
               focus: np.ndarray | None = None) -> tuple[Vec3, Vec3, Vec3]:
    """(position, look_at, up) of a camera preset for the robot in ``poses``."""
    if view == "world":
        return (*world_camera(marker_height), (0.0, 0.0, 1.0))
    if view == "local":
        return (*local_camera(poses, focus), (0.0, 0.0, 1.0))
    if view == "end_effector":
        return end_effector_camera(poses)
    raise ValueError(f"unknown view {view!r}; expected one of {', '.join(VIEWS)}")
