"""What a teleoperating participant should do next, read off the world state.

``guidance(state, scene, rules)`` names the next step of a grasp-and-deposit
(open the gripper, move above the item, lower, close, lift, turn to the bin,
move over the opening, release) with a sentence for the page (a ``GuidanceMessage``: the
catalogue key of the sentence and its parts, said in the participant's language by ``server.services.wording``)
and the facts a client needs to show progress: whether closing now would grasp, whether the
carried item is over the bin opening, where the grasp point and the bin are
relative to the gripper. ``describe_target(scene)`` names the item to
collect in words ("the purple can on the top shelf, far left").

Pure: the server sends the result with every world message, and a client
needs nothing else to steer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from experiment.world import constants as K
from experiment.world.geometry import wrap_angle
from experiment.world.path import bin_release_point
from experiment.world.robot import arm_points, radial
from experiment.world.scene import ITEM_COLORS, Scene, transfer_height
from experiment.world.state import ItemMode, WorldState, over_bin_opening
from experiment.world.teleop import DEFAULT_RULES, TeleopRules, can_grasp

#: Participant-facing names of the item colours (``scene.ITEM_COLORS``, same order).
COLOR_NAMES = ("dark yellow", "blue", "green", "pink", "yellow", "purple", "orange", "turquoise")
SHAPE_NAMES = {"cylinder": "can", "box": "box"}
TIER_NAMES = ("bottom shelf", "top shelf")
#: Columns from the robot's (and the world camera's) point of view: +y is to its left.
COLUMN_NAMES = ("far right", "right of centre", "left of centre", "far left")
#: Horizontal distance (m) from above the grasp point within which "lower" replaces "move above".
ABOVE_TOLERANCE = 0.03
#: Heading error (rad) about the mast within which the arm counts as turned to the bin.
TURNED_TOLERANCE = 0.35
#: The carried item counts as lifted when its bottom is this far (m) above the height it must clear.
LIFT_MARGIN = 0.0


def N_(key: str) -> str:  # gettext's name: marks a catalogue key (server/locales) for extraction
    return key


#: The keys that move the gripper along the world's horizontal axes (the page's bindings, ``static/js/teleop.js``
#: ACTIONS: W/S along +x/-x, towards and away from the shelf; A/D along +y/-y, the robot's left and right), with
#: which way that is on the screen from behind the robot (the World and End-effector views), as catalogue keys
#: ("W (towards the shelf)").
MOVE_KEYS = {("x", 1): N_("guidance.key.towards_shelf"), ("x", -1): N_("guidance.key.away_from_shelf"),
             ("y", 1): N_("guidance.key.left"), ("y", -1): N_("guidance.key.right")}
#: Which way to turn the arm, with its key ("left (Q)").
TURN_KEYS = {1: N_("guidance.side.left"), -1: N_("guidance.side.right")}


class GuidanceStep(StrEnum):
    OPEN_GRIPPER = "open_gripper"
    MOVE_ABOVE_ITEM = "move_above_item"
    LOWER = "lower"
    CLOSE_GRIPPER = "close_gripper"
    LIFT = "lift"
    TURN_TO_BIN = "turn_to_bin"
    MOVE_OVER_BIN = "move_over_bin"
    RELEASE = "release"
    WAIT_FOR_ITEM = "wait_for_item"
    DONE = "done"


#: The steps in the order a successful teleoperation passes them (for a checklist).
STEP_ORDER = (GuidanceStep.MOVE_ABOVE_ITEM, GuidanceStep.LOWER, GuidanceStep.CLOSE_GRIPPER, GuidanceStep.LIFT,
              GuidanceStep.TURN_TO_BIN, GuidanceStep.MOVE_OVER_BIN, GuidanceStep.RELEASE)


@dataclass(frozen=True, slots=True)
class GuidanceMessage:
    """The guidance's sentence: its catalogue key and its placeholders' values, each a tuple of catalogue keys (said
    as a list: "W (towards the shelf) and A (left)")."""

    key: str
    params: tuple[tuple[str, tuple[str, ...]], ...] = ()


@dataclass(frozen=True, slots=True)
class Guidance:
    step: GuidanceStep
    message: GuidanceMessage
    can_grasp: bool  # closing now would grasp the item
    over_bin: bool  # the carried item is over the bin opening: opening now deposits it
    grasp_distance: float  # m, from the gripper (TCP) to the item's grasp point
    to_grasp: tuple[float, float, float]  # grasp point minus TCP (world frame, m)
    to_bin: tuple[float, float, float]  # release point over the bin minus TCP (world frame, m)
    clear_height: float  # m: TCP height at which a carried item clears the obstacles and the bin rim


@dataclass(frozen=True, slots=True)
class TargetParts:
    """What names the item to collect: indices into COLOR_NAMES, TIER_NAMES, COLUMN_NAMES and its shape (a key of
    SHAPE_NAMES), so that a page in any language can name it (``server.services.wording``)."""

    color: int
    shape: str
    tier: int
    column: int


def target_parts(scene: Scene) -> TargetParts:
    item = scene.target
    tier, column = divmod(item.slot, len(K.SLOT_COLUMNS_Y))
    return TargetParts(ITEM_COLORS.index(tuple(item.color)), item.shape, tier, column)


def describe_target(scene: Scene) -> str:
    """The item to collect in English words, e.g. "the purple can on the top shelf, far left" (records, bots; the
    participant's page names it in the participant's language from ``target_parts``)."""
    p = target_parts(scene)
    return f"the {COLOR_NAMES[p.color]} {SHAPE_NAMES[p.shape]} on the {TIER_NAMES[p.tier]}, {COLUMN_NAMES[p.column]}"


def keys_towards(delta) -> tuple[str, ...]:
    """Which keys move the gripper by the horizontal part of ``delta`` (world frame, m), as catalogue keys: the key of
    the larger component, and that of the other too when it is at least half as large, e.g. "W (towards the shelf)"
    and "A (left)"."""
    dx, dy = float(delta[0]), float(delta[1])
    larger = max(abs(dx), abs(dy))
    return tuple(MOVE_KEYS[(axis, 1 if d > 0 else -1)] for axis, d in (("x", dx), ("y", dy))
                 if larger > 0 and abs(d) >= larger / 2)


def _said(key: str, **params: tuple[str, ...]) -> GuidanceMessage:
    return GuidanceMessage(key, tuple(params.items()))


def color_name(rgb: tuple[int, int, int]) -> str:
    return COLOR_NAMES[ITEM_COLORS.index(tuple(rgb))]


def _vec(a, b) -> tuple[float, float, float]:
    return (float(b[0] - a[0]), float(b[1] - a[1]), float(b[2] - a[2]))


def guidance(state: WorldState, scene: Scene, rules: TeleopRules = DEFAULT_RULES) -> Guidance:
    """The next step for the participant in ``state`` (see the module docstring)."""
    tcp = arm_points(state.base, state.joints).tcp
    grasp = scene.target.grasp_point()
    release = bin_release_point(scene, state.base)
    clear = transfer_height(scene)
    item = state.item
    grasp_ok = can_grasp(state, scene, rules)
    over_bin = item.mode == ItemMode.GRASPED and over_bin_opening(state.base, item.position)
    step, message = _step(state, scene, tcp, grasp, release, clear, grasp_ok, over_bin, rules)
    return Guidance(step, message, grasp_ok, over_bin, math.dist(tcp, grasp), _vec(tcp, grasp), _vec(tcp, release),
                    clear)


def _step(state: WorldState, scene: Scene, tcp, grasp, release, clear: float, grasp_ok: bool, over_bin: bool,
          rules: TeleopRules) -> tuple[GuidanceStep, GuidanceMessage]:
    item = state.item
    if item.mode == ItemMode.IN_BIN:
        return GuidanceStep.DONE, _said(N_("guidance.done"))
    if item.mode == ItemMode.DROPPED:
        return GuidanceStep.WAIT_FOR_ITEM, _said(N_("guidance.item_fell"))
    if item.mode == ItemMode.GRASPED:
        return _carrying(state, tcp, release, clear, over_bin)
    if grasp_ok:
        return GuidanceStep.CLOSE_GRIPPER, _said(N_("guidance.close_gripper"))
    if state.gripper_target < K.GRIPPER_MAX - 1e-6:
        return GuidanceStep.OPEN_GRIPPER, _said(N_("guidance.open_gripper"))
    horizontal = math.dist(tcp[:2], grasp[:2])
    if horizontal > max(ABOVE_TOLERANCE, rules.grasp_radius * 0.75):
        _, heading = radial(state.base, tcp)
        _, goal = radial(state.base, grasp)
        if abs(wrap_angle(goal - heading)) > TURNED_TOLERANCE:
            side = TURN_KEYS[1 if wrap_angle(goal - heading) > 0 else -1]
            return GuidanceStep.MOVE_ABOVE_ITEM, _said(N_("guidance.turn_back"), side=(side,))
        if scene.obstacles and tcp[2] < clear - 0.02:
            return GuidanceStep.MOVE_ABOVE_ITEM, _said(N_("guidance.up_first"), keys=keys_towards(_vec(tcp, grasp)))
        return GuidanceStep.MOVE_ABOVE_ITEM, _said(N_("guidance.move_above"), keys=keys_towards(_vec(tcp, grasp)))
    return GuidanceStep.LOWER, _said(N_("guidance.lower"))


def _carrying(state: WorldState, tcp, release, clear: float, over_bin: bool) -> tuple[GuidanceStep, GuidanceMessage]:
    if over_bin:
        return GuidanceStep.RELEASE, _said(N_("guidance.release"))
    _, heading = radial(state.base, tcp)
    _, goal = radial(state.base, release)
    turned = abs(wrap_angle(goal - heading)) <= TURNED_TOLERANCE
    if tcp[2] < clear - 0.02 and not turned:
        return GuidanceStep.LIFT, _said(N_("guidance.lift"))
    if not turned:
        side = TURN_KEYS[1 if wrap_angle(goal - heading) > 0 else -1]
        return GuidanceStep.TURN_TO_BIN, _said(N_("guidance.turn_to_bin"), side=(side,))
    return GuidanceStep.MOVE_OVER_BIN, _said(N_("guidance.move_over_bin"), keys=keys_towards(_vec(tcp, release)))
