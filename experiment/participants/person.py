"""A person at the participant page's keyboard, around the teleoperation strategy (``Operator``).

What is seen reaches the decision a reaction time later (lognormal, a few hundred ms), with perceptual noise of a few
mm; keys are held, not steered, so a key is released late when the delay is misjudged (overshoot); the person
anticipates the motion of the keys held (a learned display lag, from when the arm was seen to start moving after a
press, and the page's rhythm: how often its picture changes and it takes keys in), slows down (Shift) farther out on
a jerky page, believes the eyes when the picture stops changing although keys are held, and sometimes hesitates when
the instruction changes. Deterministic for a seed.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from experiment.participants.keys import EE_SPEED, JOINT_SPEED, Keys
from experiment.participants.mast import as_vector, heading_of, wrap_angle
from experiment.participants.teleoperator import COARSE_BAND, TURN_COARSE, Operator, View


@dataclass(frozen=True)
class HumanParams:
    reaction_s: float = 0.30  # median delay from seeing to acting
    reaction_sigma: float = 0.25  # its lognormal spread
    noise_m: float = 0.003  # perceptual noise (sd per axis) on positions
    noise_rad: float = 0.01  # on the arm's heading
    speed_belief_sd: float = 0.08  # how wrong the person's sense of the keys' speeds is (relative)
    initial_lag_s: float = 0.15  # the display lag a person expects before seeing how the page responds
    hesitation_p: float = 0.15  # chance of pausing when the instruction changes
    hesitation_s: tuple[float, float] = (0.3, 1.2)
    cycle_s: float = 0.04  # how often the person re-decides


@dataclass
class _Percept:
    available: float  # when it reaches the decision (seen + reaction)
    seen: float  # when the page showed it
    world: Mapping[str, Any]
    guidance: Mapping[str, Any]
    tcp: np.ndarray  # as perceived (with noise)
    heading: float


@dataclass
class _LagProbe:
    pressed: float
    direction: np.ndarray | None  # ee direction pressed (None: a turn)
    turn: float
    speed: float  # m/s or rad/s
    tcp: np.ndarray
    heading: float


class HumanModel:
    """A person at the keyboard: ``see(now, message)`` what the page shows, ``keys(now)`` what is held.

    ``message`` is a world message or the hello's ``teleop`` setup (dicts with ``world`` and ``guidance``).
    Time is the caller's clock (s); call ``keys`` as often as the page would look at the keyboard.
    """

    def __init__(self, setup: Mapping[str, Any], seed: int, params: HumanParams | None = None):
        self.params = params or HumanParams()
        self.rng = random.Random(seed)
        self.operator = Operator(setup)
        p = self.params
        self.speed_belief = max(0.5, self.rng.gauss(1.0, p.speed_belief_sd))
        self.lag = p.initial_lag_s
        self.lag_samples: list[float] = []
        self.queue: list[_Percept] = []
        self.current: _Percept | None = None
        self.last_message: Any = None
        self.last_new: float | None = None
        self.frame_s = 1 / 15  # how often the page's picture changes while the arm moves (as the person sees it)
        self.frames: list[float] = []
        self.bias = np.zeros(3)
        self.bias_heading = 0.0
        self.brain_t: float | None = None
        self.held = self.wanted = Keys()
        self.last_call: float | None = None
        self.calls: list[float] = []
        self.cadence = 0.0  # how often the page takes keys in (s), as the person experiences it
        self.history: list[tuple[float, Keys]] = [(-1e9, Keys())]  # (since, keys) as decided
        self.hesitate_until = -1e9
        self.last_step: str | None = None
        self.pending_gripper: str | None = None
        self.probe: _LagProbe | None = None
        self.decisions = 0

    # -- perception ----------------------------------------------------------------------------------
    def see(self, now: float, message: Mapping[str, Any]) -> None:
        last = self.last_message
        if message is last or (last is not None and message["world"] == last["world"]
                               and message["guidance"] == last["guidance"]):
            return  # the same picture
        self.last_message = message
        if self.last_new is not None and now - self.last_new < 1.0:
            self.frames = (self.frames + [now - self.last_new])[-6:]
            self.frame_s = float(np.median(self.frames))
            self._bands()
        self.last_new = now
        p = self.params
        delay = p.reaction_s * math.exp(self.rng.gauss(0.0, p.reaction_sigma))
        available = max(now + delay, self.queue[-1].available if self.queue else -1e9)
        keep = math.exp(-0.3)  # a slowly wandering misjudgement of where the gripper is
        fresh = np.array([self.rng.gauss(0, p.noise_m) for _ in range(3)])
        self.bias = self.bias * keep + fresh * math.sqrt(1 - keep**2)
        self.bias_heading = (self.bias_heading * keep
                             + self.rng.gauss(0, p.noise_rad) * math.sqrt(1 - keep**2))
        world = message["world"]
        self.queue.append(_Percept(available, now, world, message["guidance"], as_vector(world["tcp"]) + self.bias,
                                   heading_of(world) + self.bias_heading))

    def _perceive(self, t: float) -> bool:
        """Take in what has reached the decision by ``t``; whether anything new did."""
        new = False
        while self.queue and self.queue[0].available <= t:
            percept = self.queue.pop(0)
            self.current, new = percept, True
            self.operator.see(percept.tcp, percept.world)
            self._learn_lag(percept)
        return new

    def _learn_lag(self, percept: _Percept) -> None:
        probe = self.probe
        if probe is None or percept.seen <= probe.pressed:
            return
        if percept.guidance.get("blocked") or percept.seen - probe.pressed > 2.0:
            self.probe = None  # it did not move as pressed: nothing to learn from
            return
        if probe.direction is not None:
            moved = float(np.dot(percept.tcp - probe.tcp, probe.direction))
            threshold = 0.01
        else:
            moved = wrap_angle(percept.heading - probe.heading) * probe.turn
            threshold = 0.04
        if moved > threshold:
            # seen at `seen`, it had moved for moved / speed since the press took effect
            self.lag_samples.append(min(1.5, max(0.0, percept.seen - probe.pressed - moved / probe.speed)))
            self.lag = max(0.05, float(np.median(self.lag_samples[-5:])))
            self.probe = None

    # -- anticipation ----------------------------------------------------------------------------------
    def _velocity(self, keys: Keys) -> tuple[np.ndarray, float]:
        motion = keys.motion()
        if "joint_velocity" in motion:
            return np.zeros(3), motion["joint_velocity"][0] * self.speed_belief
        if "ee_velocity" in motion:
            return as_vector(motion["ee_velocity"]) * self.speed_belief, 0.0
        return np.zeros(3), 0.0

    def _anticipate(self, percept: _Percept, t: float) -> tuple[np.ndarray, float, bool]:
        """Where the person believes the gripper is when a key change made at ``t`` takes effect: what was
        seen, moved on by the keys held since (shifted by the lag the person expects); and whether it has come
        to rest."""
        tcp, heading = percept.tcp.copy(), percept.heading
        shown_until = percept.seen - self.lag  # the picture shows the keys held up to about then
        arrives = self._effective(t)  # where it will be when a change made now takes effect
        blocked = bool(percept.guidance.get("blocked"))  # it did not move as the keys said: believe the eyes
        # keys held long enough ago that a new picture should have shown the motion, yet none came: not moving
        window = self.lag + 2 * max(self.frame_s, self.cadence) + 0.5
        if self.last_new is not None and t - self.last_new > window:
            for i, (since, keys) in enumerate(self.history):
                until = self.history[i + 1][0] if i + 1 < len(self.history) else math.inf
                if keys.held and since < t - window and until > self.last_new - self.lag + 0.05:
                    blocked = True
        settled = not blocked
        for i, (since, keys) in enumerate(self.history):
            until = self.history[i + 1][0] if i + 1 < len(self.history) else math.inf
            if keys.held and until > shown_until - 0.1:  # the picture may still show it moving
                settled = False
            lo, hi = max(since, shown_until), min(until, arrives)
            if hi <= lo or blocked:
                continue
            v, w = self._velocity(keys)
            tcp += v * (hi - lo)
            heading += w * (hi - lo)
        return tcp, heading, settled

    # -- acting --------------------------------------------------------------------------------------
    def keys(self, now: float) -> Keys:
        """The keys held at ``now`` (a G press is reported once).

        Call it whenever the page takes keys in (its loop, or the test driver's poll): what the person decided
        since the last call is what the page gets now; decisions in between that were undone never reach it.
        """
        cycle = self.params.cycle_s
        if self.last_call is not None and 0 < now - self.last_call < 2.0:
            self.calls = (self.calls + [now - self.last_call])[-6:]
            self.cadence = float(np.median(self.calls))
            self._bands()
        if self.brain_t is None:
            self.brain_t = now
        while self.brain_t <= now + 1e-9:
            self._think(self.brain_t)
            self.brain_t += cycle
        self.last_call = now
        self._hold(now, self.wanted)
        gripper, self.pending_gripper = self.pending_gripper, None
        return Keys(self.held.held, self.held.fine, gripper)

    def _bands(self) -> None:
        """A jerky page (pictures or key handling far apart) makes the person slow down (Shift) farther out:
        full speed only while a whole step of the page's rhythm lands closer to the goal."""
        step = max(self.frame_s, self.cadence)
        self.operator.coarse_band = max(COARSE_BAND, 0.75 * EE_SPEED * step)
        self.operator.coarse_turn = max(TURN_COARSE, 0.75 * JOINT_SPEED * step)

    def _think(self, t: float) -> None:
        self._perceive(t)
        percept = self.current
        if percept is None:
            return
        step = percept.guidance["step"]
        if step != self.last_step:
            if self.last_step is not None and self.rng.random() < self.params.hesitation_p:
                low, high = self.params.hesitation_s
                self.hesitate_until = t + self.rng.uniform(low, high)
            self.last_step = step
        if t < self.hesitate_until:
            self.wanted = Keys()
            return
        tcp, heading, settled = self._anticipate(percept, t)
        view = View(tcp, heading, percept.world, percept.guidance, settled)
        decided = self.operator.decide(view, t)
        self.decisions += 1
        if decided.gripper is not None:
            self.pending_gripper = decided.gripper
        self.wanted = Keys(decided.held, decided.fine)

    def _effective(self, t: float) -> float:
        """When a key change decided at ``t`` reaches the arm, as the person has come to expect: at the page's
        next look at the keyboard."""
        if self.last_call is None:
            return t
        return max(t, self.last_call + self.cadence)

    def _hold(self, t: float, keys: Keys) -> None:
        """The page takes ``keys`` in at ``t``."""
        if keys == self.held:
            return
        was_idle = not self.held.held
        self.held = keys
        idle_since = self.history[-1][0]
        self.history.append((t, keys))
        if len(self.history) > 200:
            self.history = self.history[-100:]
        self.probe = None  # a new press from rest shows the lag; any other change spoils the measurement
        if keys.held and was_idle and idle_since < t - 0.3 and self.current is not None:
            motion = keys.motion()
            if "ee_velocity" in motion:
                v = as_vector(motion["ee_velocity"])
                speed = float(np.linalg.norm(v))
                self.probe = _LagProbe(t, v / speed, 0.0, speed, self.current.tcp, self.current.heading)
            elif "joint_velocity" in motion:
                w = motion["joint_velocity"][0]
                self.probe = _LagProbe(t, None, math.copysign(1.0, w), abs(w), self.current.tcp,
                                       self.current.heading)

    @property
    def phase(self) -> str:
        return self.operator.phase
