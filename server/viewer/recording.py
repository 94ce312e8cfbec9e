"""A reconstructed trial (``experiment.replay.Replay``) as a viser recording: what the participant's 3D view showed.

The scene's nodes are the live view's (``server.viewer.scene``: the static parts, the trial's items, obstacles and
marks) and every frame is what ``server.viewer.live.LiveView`` would send for the state shown at that moment (the
moving frames, the marks, the camera preset), so the replay looks like the participant's view. They are recorded with
viser's own serializer (``StateSerializer``, as ``ViserServer.get_scene_serializer`` records a live server, but fed
by a handler with no clients and no server thread) and played by its client's playback mode
(``server.viewer.replay_page``).

Every ``CLOCK_S`` the recording also runs a line of JavaScript (viser's ``RunJavascriptMessage``, part of a
recording) that tells the page around the player the replay's time, so its timeline follows the player as it plays,
loops, is paused or is scrubbed.
"""

from __future__ import annotations

import math
from typing import Any

from viser import _messages as viser_messages
from viser.infra import StateSerializer
from viser.infra._infra import WebsockMessageHandler

from experiment.replay import Replay
from server.viewer.live import LiveView
from server.viewer.scene import preamble, static_nodes, trial_nodes
from server.viewer.wire import Message

#: Frames a second while something moves (the world loop's default rate: as the participant's view got them).
FRAME_HZ = 30.0
#: How often the recording tells the page its time (s).
CLOCK_S = 0.1
#: Positions and quaternions are kept to this many decimals (0.1 mm, 1e-4 of a unit quaternion: nothing a viewer can
#: see): the recording is ~15 % smaller.
DECIMALS = 4


class _NoClients:
    """The message buffer of a handler nobody is connected to."""

    def push(self, message: viser_messages.Message) -> None:
        pass


class Recorder(WebsockMessageHandler):
    """A viser message handler with no clients: what it is sent goes to its serializers only."""

    def get_message_buffer(self) -> Any:  # viser types it as its async buffer; only ``push`` is called
        return _NoClients()


def record(replay: Replay, *, hz: float = FRAME_HZ) -> bytes:
    """The replay as a viser recording (``StateSerializer.serialize``: zstd-compressed msgpack)."""
    recorder = Recorder()
    serializer: StateSerializer = recorder.get_message_serializer(
        filter=lambda message: message.include_in_scene_serialization)
    static = static_nodes(replay.scene)
    for message in (*preamble(), *static.messages, *trial_nodes(replay.scene, static.names).messages):
        recorder.queue_message(message)
    live = LiveView(replay.scene, view=replay.view_at(0.0))
    _send(recorder, live.set_view(live.view))
    steps = max(1, math.ceil(replay.duration * hz))
    clock_every = max(1, round(CLOCK_S * hz))
    for i in range(steps + 1):
        t = min(i / hz, replay.duration)
        messages: list[Message] = []
        if (view := replay.view_at(t)) != live.view:
            messages += live.set_view(view)
        changes, frame = live.update(replay.state_at(t))
        messages += changes + frame
        _send(recorder, messages)
        if i % clock_every == 0 or i == steps:
            recorder.queue_message(viser_messages.RunJavascriptMessage(clock_script(t)))
        if i < steps:
            serializer.insert_sleep(min((i + 1) / hz, replay.duration) - t)
    return serializer.serialize()


def clock_script(t: float) -> str:
    """What the recording runs to tell the page around the player the replay's time (s)."""
    return f"window.parent.postMessage({{trustlabReplayTime:{t:.3f}}},'*')"


def _send(recorder: Recorder, messages: list[Message]) -> None:
    """Messages as ``server.viewer.live`` builds them (dicts as viser serialises them), sent as viser's objects."""
    for message in messages:
        fields = {key: _rounded(value) for key, value in message.items() if key not in ("type", "owner")}
        recorder.queue_message(getattr(viser_messages, message["type"])(**fields))


def _rounded(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, DECIMALS)
    if isinstance(value, tuple) and value and all(isinstance(v, float) for v in value):
        return tuple(round(v, DECIMALS) for v in value)
    return value
