"""The teleoperation socket's messages (``/api/p/{token}/teleop``), both directions, as typed models.

Published as JSON Schema at ``/api/schema/teleop.json``; a client needs nothing else to steer.

How it works: the client sends its *input state* — what is held now (a TCP velocity or joint rates,
or nothing) and a one-shot gripper action — whenever it changes, and a keep-alive while anything is
held (every ``keepalive_s``). The server holds the latest input and moves the arm on its own clock:
the arm moves as far per second whether a page sends 2 or 60 messages a second. When no message has
arrived for ``deadman_s`` the held motion stops (a stalled page never leaves the arm moving) until
the next message — a keep-alive resumes it, an input replaces it; a closed socket stops it at once. The server pushes a
``world`` message whenever the world changed (at most ``world_hz`` a second) and says ``over`` when the teleoperation
has ended.

Conversation::

    server: hello (stage, trial, teleop setup: scene, limits, world, guidance)   -- on connect
    client: input {seq, ee_velocity | joint_velocity | neither, gripper?}         -- on every change
    client: view {seq, usable}                    -- optional: no usable view yet (the time limit waits), or now one
    server: ack {seq, ok, error?}                                                 -- one per client message
    client: keepalive {seq}                                                       -- while input is held
    server: world {input_seq, world, guidance, events, time_left_ms}              -- as the arm moves
    server: over {reason, trial_recorded}                                         -- then the socket closes

A connection while the trial is not being teleoperated gets ``hello`` with ``teleop: null`` and is
closed (code 1000). An unknown, finished or abandoned session is closed with code 4404.

Bounds: every message is JSON text of at most 4 KiB (a larger frame, past 64 KiB, closes the socket
with 1009); numbers are finite JSON numbers within the bounds the schema states (``seq`` a whole number
up to 2^53-1); anything else, a binary frame included, is answered with ``ack`` ``ok: false`` and the
reason, and the socket serves on. A page of another origin is refused (1008, before the handshake
completes); a failure of the server while handling a message closes the socket with 1011 (reconnect).

Frames: world x towards the shelf, y to the left (as seen from behind the robot), z up; metres,
radians, seconds; quaternions (w, x, y, z).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, TypeAdapter, model_validator

from experiment.flow import TrialStage
from experiment.task import Complexity
from experiment.world.teleop import TeleopCommand
from server.strict_json import WHOLE_FLOAT_AS_INT

PROTOCOL_VERSION = 2
Vec3 = tuple[float, float, float]

#: Bounds of the client's numbers: a JavaScript integer for counters, a clock reading within ±10^13 ms (both
#: performance.now() and Date.now() fit), and rates far past any limit (they are clamped to the limits anyway).
MAX_SEQ = 2**53 - 1
MAX_CLIENT_MS = 1e13
MAX_RATE = 1000.0
Seq = Annotated[int, Field(ge=0, le=MAX_SEQ, description="The client's message counter (echoed in the ack and in "
                                              "world messages); a JavaScript integer"), WHOLE_FLOAT_AS_INT]
ClientMs = Annotated[float | None, Field(None, ge=-MAX_CLIENT_MS, le=MAX_CLIENT_MS, description=(
    "The client's clock (performance.now()) when it was sent"))]
Rate = Annotated[float, Field(ge=-MAX_RATE, le=MAX_RATE)]


class _Message(BaseModel):
    """Every message, both ways: unknown fields and non-finite numbers (NaN, Infinity, 1e309) are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# -- client → server ---------------------------------------------------------------------------------------------
class _ClientMessage(_Message):
    """A client's message: read as strictly as an HTTP body (a number is a JSON number, never ``"1"`` or ``true``)."""

    model_config = ConfigDict(strict=True)


class InputMessage(_ClientMessage):
    """What the participant holds now. Sent whenever it changes; replaces the previously held input."""

    type: Literal["input"]
    seq: Seq
    client_ms: ClientMs
    ee_velocity: tuple[Rate, Rate, Rate] | None = Field(
        None, description="TCP velocity (m/s, world frame) to hold; clamped to limits.max_ee_speed. "
                          "The gripper is kept pointing down.")
    joint_velocity: tuple[Rate, Rate, Rate, Rate] | None = Field(
        None, description="Joint rates (rad/s) of j1 (yaw about the mast), j2, j3, j4 to hold; each clamped to "
                          "limits.max_joint_speed")
    gripper: Literal["open", "close"] | None = Field(
        None, description="A one-shot gripper action, applied once on receipt (not held)")

    _command: TeleopCommand = PrivateAttr()

    @model_validator(mode="after")
    def _as_command(self) -> InputMessage:
        self._command = TeleopCommand(self.ee_velocity, self.joint_velocity, self.gripper)  # its checks: not both
        return self

    @property
    def command(self) -> TeleopCommand:
        """The input as the world holds it (checked once, here)."""
        return self._command


class KeepAliveMessage(_ClientMessage):
    """Sent while an input is held (at least every ``limits.keepalive_s``): the input is still held."""

    type: Literal["keepalive"]
    seq: Seq
    client_ms: ClientMs


class ViewMessage(_ClientMessage):
    """Whether the participant can see the arm now (optional). A page that reconnects before it has a usable view (a
    reload in the middle of a teleoperation, while its 3D view loads) says ``usable: false``: the time limit then
    stands still until ``usable: true`` or the socket closes, for at most ``limits.max_view_wait_s`` per
    teleoperation in all (the trial records the time, ``teleop_view_wait_ms``). A client that never sends it is
    timed as before."""

    type: Literal["view"]
    seq: Seq
    client_ms: ClientMs
    usable: bool


ClientMessage = Annotated[InputMessage | KeepAliveMessage | ViewMessage, Field(discriminator="type")]
CLIENT_MESSAGE = TypeAdapter(ClientMessage)


# -- server → client ---------------------------------------------------------------------------------------------
class TrialRef(_Message):
    """Which trial (``experiment.flow.TrialRef``, on the wire) and its complexity."""

    practice: bool
    block: int
    trial: int
    complexity: Complexity


class BoxInfo(_Message):
    name: str
    center: Vec3
    size: Vec3 = Field(description="Full extents along x, y, z (m), axis-aligned")


class TargetInfo(_Message):
    """The item to collect."""

    slot: int = Field(description="Shelf slot: tier * 4 + column (tier 0 bottom, 1 top; column 0 far right)")
    description: str = Field(description='In words, e.g. "the purple can on the top shelf, far left"')
    color: str
    shape: Literal["can", "box"]
    center: Vec3 = Field(description="Centre of the item standing in its slot")
    size: Vec3
    grasp_point: Vec3 = Field(description="Where the TCP must be for the gripper to grasp it")


class BinInfo(_Message):
    """The bin on the robot's base, at the parked pose (the base does not move while teleoperating)."""

    opening_center: Vec3 = Field(description="Centre of the opening at rim height")
    opening_size: tuple[float, float] = Field(description="Inner size of the opening along the base's x and y (m)")
    rim_z: float
    yaw: float = Field(description="The base's yaw: the opening's x axis in the world")
    release_point: Vec3 = Field(description="A TCP position from which opening the gripper drops the carried "
                                            "item into the bin")


class SceneInfo(_Message):
    complexity: Literal["low", "high"]
    seed: str = Field(description="62-bit scene seed as a decimal string (JavaScript numbers hold 53 bits)")
    target: TargetInfo
    target_slot: int
    obstacles: list[BoxInfo] = Field(description="Boxes in front of the shelf (high complexity only)")
    shelf: list[BoxInfo] = Field(description="The shelf's boards and panels")
    other_items: list[BoxInfo]
    bin: BinInfo
    clear_height: float = Field(description="TCP height (m) at which a carried item clears the obstacles and the bin")


class Limits(_Message):
    max_ee_speed: float = Field(description="m/s; faster ee_velocity is clamped")
    max_joint_speed: float = Field(description="rad/s; faster joint rates are clamped")
    grasp_radius: float = Field(description="m: closing with the TCP this close to the grasp point grasps")
    align_radius: float = Field(description="m: closing within this distance first moves the gripper onto the "
                                            "grasp point (0: no such assistance)")
    speedup: float = Field(description="Simulated seconds per real second (1 except in sped-up test studies)")
    deadman_s: float = Field(description="A held input stops after this long without a message")
    keepalive_s: float = Field(description="Send a keepalive at least this often while an input is held")
    world_hz: float = Field(description="World messages per second at most")
    rate_limit_hz: float = Field(description="Client messages per second allowed (a small burst above)")
    max_view_wait_s: float = Field(description="Seconds the time limit may stand still in all, this teleoperation, "
                                               "while the client says its view is not usable (view messages)")
    view_wait_left_s: float = Field(description="What is left of max_view_wait_s now")


class ItemView(_Message):
    mode: Literal["on_shelf", "grasped", "in_bin", "dropped"]
    position: Vec3
    wxyz: tuple[float, float, float, float]


class WorldView(_Message):
    t: float = Field(description="Simulated time (s) since the teleoperation began")
    base: Vec3 = Field(description="x, y (m), yaw (rad)")
    joints: tuple[float, float, float, float]
    gripper: float = Field(description="Finger gap now (m)")
    gripper_target: float = Field(description="Commanded finger gap (m): 0.1 open, the item's width while holding")
    tcp: Vec3 = Field(description="Tool centre point (between the fingertips)")
    item: ItemView


GuidanceStepName = Literal["open_gripper", "move_above_item", "lower", "close_gripper", "lift", "turn_to_bin",
                           "move_over_bin", "release", "wait_for_item", "done"]


class GuidanceView(_Message):
    """What to do next, from the world state (``experiment.world.guidance``)."""

    step: GuidanceStepName
    text: str
    can_grasp: bool = Field(description="Closing the gripper now would grasp the item")
    over_bin: bool = Field(description="The carried item is over the bin opening: opening the gripper deposits it")
    blocked: bool = Field(description="The last motion was refused because the arm would hit something")
    grasp_distance: float
    to_grasp: Vec3 = Field(description="Grasp point minus TCP (m)")
    to_bin: Vec3 = Field(description="Release point over the bin minus TCP (m)")


class TutorialInfo(_Message):
    try_number: int = Field(description="Which try of the guided first teleoperation this is (from 1)")
    max_tries: int


class TeleopSetup(_Message):
    scene: SceneInfo
    limits: Limits
    time_limit_s: float
    time_left_ms: float
    tutorial: TutorialInfo | None = Field(description="Set while this is the guided practice teleoperation")
    world: WorldView
    guidance: GuidanceView


class HelloMessage(_Message):
    type: Literal["hello"] = "hello"
    protocol: int = PROTOCOL_VERSION
    stage: TrialStage | None = Field(
        description="The stage of the session's current trial (None between trials)")
    trial: TrialRef | None
    teleop: TeleopSetup | None = Field(description="Set when the trial is being teleoperated; else the socket closes")


class AckMessage(_Message):
    type: Literal["ack"] = "ack"
    seq: int | None = Field(description="The acknowledged message's seq (None if it could not be read)")
    ok: bool
    error: str | None = None


WorldEvent = Literal["aligned", "grasped", "deposited", "dropped", "blocked", "item_reset"]


class WorldMessage(_Message):
    type: Literal["world"] = "world"
    input_seq: int | None = Field(description="seq of the latest input the server holds")
    server_ms: float = Field(description="Server time since the teleoperation began (ms)")
    world: WorldView
    guidance: GuidanceView
    events: list[WorldEvent] = Field(description="What happened since the previous world message")
    moving: bool = Field(description="A motion input is held now (false after the dead-man stop)")
    time_left_ms: float


class OverMessage(_Message):
    """The teleoperation has ended; the socket closes after this."""

    type: Literal["over"] = "over"
    reason: Literal["deposited", "time_limit", "ended"] = Field(
        description="deposited: the item reached the bin; time_limit: the time ran out; ended: the trial was "
                    "resolved elsewhere (another tab) or moved on")
    trial_recorded: bool = Field(description="This socket's deposit completed the trial (in the database)")
    retry: bool = Field(False, description="A guided practice try ran out of time and a new try begins: "
                                           "reconnect to continue from the ready pose")


ServerMessage = Annotated[HelloMessage | AckMessage | WorldMessage | OverMessage, Field(discriminator="type")]
SERVER_MESSAGE = TypeAdapter(ServerMessage)


def json_schema() -> dict:
    """The socket's contract: one JSON Schema with both directions' messages."""
    client = CLIENT_MESSAGE.json_schema(ref_template="#/$defs/{model}")
    server = SERVER_MESSAGE.json_schema(ref_template="#/$defs/{model}")
    defs = {**client.pop("$defs", {}), **server.pop("$defs", {})}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "/api/schema/teleop.json",
        "title": "trustlab teleoperation socket",
        "description": (__doc__ or "").strip(),
        "properties": {"client_to_server": client, "server_to_client": server},
        "$defs": defs,
    }
