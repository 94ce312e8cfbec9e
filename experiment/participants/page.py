"""The participant page between the person and the teleoperation socket: its loop, and what it sends.

``ClientLoop`` is a starved page whose one loop runs at a fixed rate, or a page that takes keys as they come and
sends keep-alives on a timer (``benchmarks/bench_teleop.py`` runs both); the messages are those of
``static/js/teleop.js`` (``experiment.participants.keys.input_message``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from experiment.participants.keys import input_message
from experiment.participants.person import HumanModel

#: How often a page that is not starved looks at the keyboard and redraws (s): about a display frame.
PAGE_FRAME_S = 0.04


@dataclass
class ClientLoop:
    """The page between the person and the socket; each call returns the messages to send.

    Two ways to use it (``benchmarks/bench_teleop.py`` runs both):

    - a page whose one loop runs at a fixed rate (a starved page): call ``tick`` at that rate. It shows the
      latest world message to the person, sends an input message when the held keys changed (or G was
      pressed), and a keep-alive when ``keepalive_s`` has passed since the last message while motion is held.
    - a page that handles keys and draws as they come but whose timer sends at a fixed rate: call
      ``tick(now, latest, keepalive=False)`` every ``PAGE_FRAME_S`` and ``keepalive(now)`` at the rate (one
      keep-alive per timer tick while motion is held).

    A world message that says the arm is not moving although the server holds this client's latest input
    (``moving`` false, ``input_seq`` its own: the dead-man time passed while the loop stalled) makes it send
    the held motion again; so does a refused input (``ack``: e.g. too many messages).
    """

    human: HumanModel
    keepalive_s: float
    seq: int = 0
    sent_motion: dict[str, Any] = field(default_factory=dict)
    last_send: float = -1e9
    input_seq: int = -1  # seq of the last input message sent
    resent_for: Any = None
    inputs: int = 0
    keepalives: int = 0
    resends: int = 0  # inputs sent again after a dead-man stop
    refused: int = 0  # messages the server refused
    refused_input: bool = False  # the latest input was refused: send the input state again

    def tick(self, now: float, latest: Mapping[str, Any] | None, keepalive: bool = True) -> list[dict[str, Any]]:
        if latest is not None:
            self.human.see(now, latest)
        keys = self.human.keys(now)
        motion = keys.motion()
        world = latest["world"] if latest is not None else None
        if (motion != self.sent_motion or keys.gripper is not None or self._stopped(latest, motion)
                or self.refused_input):
            self.refused_input = False
            self.seq += 1
            self.sent_motion, self.last_send, self.input_seq = motion, now, self.seq
            self.inputs += 1
            return [input_message(self.seq, keys, world, client_ms=now * 1000)]
        if keepalive and now - self.last_send >= self.keepalive_s - 1e-6:
            return self.keepalive(now)
        return []

    def _stopped(self, latest: Mapping[str, Any] | None, motion: Mapping[str, Any]) -> bool:
        """The server holds this client's latest input but says the arm is not moving: the dead-man time
        passed (a stalled loop); the motion still held is sent again (once per such world message)."""
        if (not motion or latest is None or latest.get("type") != "world" or latest.get("moving", True)
                or latest is self.resent_for or (latest.get("input_seq") or -1) < self.input_seq):
            return False
        self.resent_for = latest
        self.resends += 1
        return True

    def ack(self, message: Mapping[str, Any]) -> None:
        """An ack from the server: a refused input (e.g. too many messages) is sent again at the next tick."""
        if not message.get("ok", True):
            self.refused += 1
            if message.get("seq") == self.input_seq:
                self.refused_input = True

    def keepalive(self, now: float) -> list[dict[str, Any]]:
        """A keep-alive, when motion is held."""
        if not self.sent_motion:
            return []
        self.seq += 1
        self.last_send = now
        self.keepalives += 1
        return [{"type": "keepalive", "seq": self.seq, "client_ms": now * 1000}]
