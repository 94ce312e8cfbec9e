"""The numbers that define the robot world: dimensions, limits, speeds, timings.

None of these values come from the paper: it ran a ROS-Gazebo world whose
dimensions it does not give. They were chosen here so that a 4-DOF arm can
reach every shelf slot from above, so that the obstacles of high complexity
stand between the robot and the target item, and so that an attempt lasts
about 6-10 s. Change them here only; every module reads them from here.

Frames and units: world frame with z up and the floor at z = 0, the shelf's
front face at ``SHELF_FRONT_X`` facing -x (towards the robot). Lengths in
metres, angles in radians, times in seconds, speeds in m/s or rad/s.
"""

from __future__ import annotations

import math

# --- shelf unit (x measured from its front face, y from its centre line) ----
SHELF_FRONT_X = 2.0
FLOOR_BOUNDS = ((-2.0, -3.0), (3.5, 3.0))  # (x, y) corners of the visible floor
SHELF_CENTER_Y = 0.0
SHELF_WIDTH = 1.30  # outside width along y
SHELF_DEPTH = 0.50  # depth of the boards along x
SHELF_HEIGHT = 0.95  # height of the uprights and back panel
PANEL = 0.03  # thickness of uprights, back panel, boards and riser
LOWER_BOARD_TOP = 0.40  # top surface of the lower (front) tier
UPPER_BOARD_TOP = 0.75  # top surface of the upper (back) tier
UPPER_SETBACK = 0.25  # the upper tier starts this far behind the front face
SLOT_COLUMNS_Y = (-0.45, -0.15, 0.15, 0.45)  # item centre y per column
SLOT_TIERS_X = (0.12, 0.375)  # item centre depth behind the front, per tier
SLOT_TIERS_Z = (LOWER_BOARD_TOP, UPPER_BOARD_TOP)  # board top per tier
N_SLOTS = len(SLOT_COLUMNS_Y) * len(SLOT_TIERS_X)  # slot = tier * 4 + column
ITEM_FILL_PROBABILITY = 0.8  # chance that a non-target slot holds an item
ITEM_WIDTH_RANGE = (0.06, 0.08)  # box side or cylinder diameter
ITEM_HEIGHT_RANGE = (0.10, 0.15)

# --- obstacles (high complexity only): boxes standing on the floor ----------
OBSTACLE_COUNT_RANGE = (2, 3)  # inclusive
OBSTACLE_FRONT_GAP = 0.02  # gap between an obstacle's back face and the shelf
OBSTACLE_DEPTH_RANGE = (0.10, 0.14)
OBSTACLE_WIDTH_RANGE = (0.14, 0.24)
OBSTACLE_ABOVE_ITEM_RANGE = (0.05, 0.10)  # main blocker top above item top
OBSTACLE_SIDE_GAP_RANGE = (0.0, 0.04)  # y gap between main and flanking boxes
OBSTACLE_SIDE_HEIGHT_RANGE = (0.6, 1.0)  # flanking box height / main height

# --- mobile base (base frame: origin on the floor, x forward) --------------
BASE_LENGTH = 0.56
BASE_WIDTH = 0.48
BASE_BOTTOM = 0.04  # ground clearance of the body
BASE_TOP = 0.34
WHEEL_RADIUS = 0.06
WHEEL_WIDTH = 0.04
WHEEL_X = 0.18  # |x| of the axles in the base frame
MAST_XY = (0.18, -0.10)  # mast axis in the base frame (front right)
MAST_WIDTH = 0.08
MAST_TOP = 0.92  # height of joint 1 (yaw)
J1_HOUSING_DIAMETER = 0.10
SHOULDER_Z = 1.05  # height of joint 2 (shoulder pitch), on the yaw axis
BIN_XY = (-0.12, 0.10)  # bin centre in the base frame (rear left)
BIN_SIZE = (0.26, 0.26, 0.18)  # outer size; it stands on the base top
BIN_WALL = 0.015
BIN_RIM = BASE_TOP + BIN_SIZE[2]
BIN_FLOOR = BASE_TOP + BIN_WALL
MAST_STANDOFF = 0.28  # parked: mast axis this far in front of the shelf
DRIVE_DISTANCE = 1.5  # the base starts this far behind its parked pose

# --- arm ---------------------------------------------------------------------
UPPER_ARM = 0.50  # j2 -> j3
FOREARM = 0.45  # j3 -> j4
WRIST_LINK = 0.08  # j4 -> palm
TCP_OFFSET = 0.06  # palm -> tool centre point (between the fingers)
TOOL_LENGTH = WRIST_LINK + TCP_OFFSET  # j4 -> TCP
FINGER_LENGTH = 0.08  # from the palm along the tool axis
PALM_HALF_WIDTH = 0.06
LINK_RADII = {  # collision capsule radii
    "/robot/j2": 0.045, "/robot/j3": 0.04, "/robot/j4": 0.03,
    "/robot/palm": 0.02, "/robot/finger_left": 0.01, "/robot/finger_right": 0.01,
}
FINGER_RADIUS = LINK_RADII["/robot/finger_left"]
JOINT_LOWER = (-3.0, -0.6, -2.8, -3.0)  # j1 yaw, j2, j3, j4 pitch
JOINT_UPPER = (3.0, 2.0, 0.2, 1.2)  # j3 <= 0.2 keeps the elbow up
TOOL_PITCH = -math.pi / 2  # held by Cartesian IK: gripper points down
GRIPPER_MAX = 0.10  # fully open finger gap
GRIPPER_SPEED = 0.25  # finger gap change per second
READY_TCP = (0.30, 1.12)  # (radial distance from the mast axis, height)

# --- teleoperation -----------------------------------------------------------
MAX_EE_SPEED = 0.30
MAX_JOINT_SPEED = 1.2
MAX_TELEOP_DT = 0.5  # longer steps are refused (they could tunnel)
# The gripper's workspace under Cartesian control: above these the arm straightens into a singular pose
# (wrist at its limit) from which the keys no longer move the gripper the way they say.
TCP_MAX_Z = 1.40  # highest TCP (m); every obstacle and the bin are cleared well below it
TCP_MAX_REACH = 0.80  # farthest TCP from the mast axis (m); the deepest shelf slot is about 0.66 m away
IK_DAMPING = 0.03  # damped least squares lambda
TOOL_PITCH_WEIGHT = 0.3  # metres per radian: weight of the pitch-holding row
TOOL_PITCH_GAIN = 3.0  # 1/s: how fast the pitch error is corrected
GRASP_DEPTH = 0.03  # TCP is this far below the item top when grasping
GRASP_RADIUS = 0.04  # TCP within this of the grasp point -> closing grasps
RESPAWN_DELAY = 2.0  # a dropped item returns to its slot after this time
GRAVITY = 9.81
ITEM_INSET = 0.005  # the held item's collision capsule is this much smaller

# --- autonomous attempt ------------------------------------------------------
SAMPLE_RATE = 60.0  # Hz of the precomputed trajectory (linear in between)
PREGRASP_HEIGHT = 0.10  # TCP above the grasp point before descending
TRANSFER_MIN_Z = 0.80  # lowest TCP height while carrying the item
CLEARANCE = 0.06  # carried item bottom above the highest obstacle
RETRACT_RADIUS = 0.25  # TCP radius from the mast while swinging to the bin
SWING_MIN_Z = 0.95  # lowest TCP height while swinging (forearm clears the uprights)
FAIL_RETRACT_RADIUS = 0.20  # the failing straight path ends this close to the mast
FAIL_RELEASE_DELAY = 0.15  # the item falls this long after the arm hits
RELEASE_ABOVE_RIM = 0.05  # item bottom above the bin rim at release
P_COLLISION_HIGH = 0.8  # failure mode "collision" in high complexity
FAIL_LIFT = 0.05  # a failing attempt lifts the item only this much
SETTLE_RISE = 0.08  # after releasing, the gripper rises this much
DURATIONS = {  # seconds at animation speed 1
    "drive": 2.2, "approach": 1.1, "descend": 0.7, "close": 0.4,
    "lift": 0.7, "retract": 0.6, "swing": 1.3, "to_bin": 0.7,
    "release": 0.35, "settle": 0.6, "fail_lift": 0.3, "fail_move": 1.2, "fail_hold": 1.5,
}
