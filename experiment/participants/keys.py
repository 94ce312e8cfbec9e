"""The participant page's keys, and how the page turns the keys held into an input message.

As ``static/js/teleop.js`` (``Teleop.motion``) does: 0.2 m/s per world axis held (0.025 with Shift), each axis
clamped to ±1 × the speed; j1 at 0.6 rad/s (0.1); a joint key takes precedence over the axis keys; G sends "close"
when the gripper is fully open, else "open". ``Keys`` is what a person does at one moment.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

#: Motion actions: world axis (x towards the shelf, y to the left, z up) or joint 1 (yaw about the mast).
ACTIONS = {"x+": ("ee", 0, 1), "x-": ("ee", 0, -1), "y+": ("ee", 1, 1), "y-": ("ee", 1, -1),
           "z+": ("ee", 2, 1), "z-": ("ee", 2, -1), "j1+": ("joint", 0, 1), "j1-": ("joint", 0, -1)}
#: The page's speeds (static/js/teleop.js): m/s per world axis held, rad/s of j1; fine = with Shift.
EE_SPEED, EE_SPEED_FINE = 0.2, 0.025
JOINT_SPEED, JOINT_SPEED_FINE = 0.6, 0.1
#: Finger gap (m) of the fully open gripper (the protocol's ``gripper_target`` when open).
GRIPPER_OPEN = 0.1
#: The page's keys for the actions (for a browser driver).
KEY_CODES = {"x+": "KeyW", "x-": "KeyS", "y+": "KeyA", "y-": "KeyD", "z+": "KeyR", "z-": "KeyF",
             "j1+": "KeyQ", "j1-": "KeyE"}


@dataclass(frozen=True)
class Keys:
    """What the person does at one moment: motion keys held, Shift held, G pressed (with what it means)."""

    held: frozenset[str] = frozenset()
    fine: bool = False
    gripper: str | None = None  # "open" / "close": G pressed now, meaning that (None: not pressed)

    def motion(self) -> dict[str, Any]:
        return input_fields(self.held, self.fine)


# -- the page's mapping from keys to the input message ------------------------------------------------------
def input_fields(held: Iterable[str], fine: bool = False) -> dict[str, Any]:
    """The motion part of an input message for these held keys, as the page's ``Teleop.motion()`` builds it:
    ``{"joint_velocity": [...]}``, ``{"ee_velocity": [...]}`` or ``{}`` (nothing held: stop)."""
    ee, joint = [0.0, 0.0, 0.0], 0.0
    for action in held:
        kind, axis, sign = ACTIONS[action]
        if kind == "ee":
            ee[axis] += sign
        else:
            joint += sign

    def clamp(v: float) -> float:
        return max(-1.0, min(1.0, v))

    if joint != 0:
        return {"joint_velocity": [clamp(joint) * (JOINT_SPEED_FINE if fine else JOINT_SPEED), 0.0, 0.0, 0.0]}
    if any(v != 0 for v in ee):
        speed = EE_SPEED_FINE if fine else EE_SPEED
        return {"ee_velocity": [clamp(v) * speed for v in ee]}
    return {}


def gripper_action(world: Mapping[str, Any] | None) -> str:
    """What the page sends for a press of G with ``world`` shown: close a fully open gripper, else open."""
    return "close" if world is None or world["gripper_target"] >= GRIPPER_OPEN - 1e-6 else "open"


def input_message(seq: int, keys: Keys, world: Mapping[str, Any] | None, client_ms: float | None = None
                  ) -> dict[str, Any]:
    """The input message the page sends for ``keys`` (G's meaning from ``world``, as the page decides it)."""
    message: dict[str, Any] = {"type": "input", "seq": seq, "client_ms": client_ms, **keys.motion()}
    if keys.gripper is not None:
        message["gripper"] = gripper_action(world)
    return message
