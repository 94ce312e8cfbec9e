"""Teleoperation over a websocket: one ``TeleopChannel`` per socket (the protocol: ``server.teleop_messages``).

The channel reads the session's trial from the database, holds the participant's arm in the ``WorldHub``,
turns client messages into held inputs, pushes the world as it changes, and ends the teleoperation: a
deposit completes the trial in the database before ``over`` is sent; the time limit and a trial resolved
elsewhere (another tab, the sweeper) end it too. Inputs and world events reach the event log through
``server.services.teleop_log``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from pydantic import ValidationError
from sqlalchemy.orm import Session

from experiment.engine import PlannedTrial
from experiment.events import EventKind
from experiment.flow import TrialStage
from experiment.world import constants as K
from experiment.world.teleop import TeleopRules, WorldEvent
from server import strict_json
from server.app_services import Services
from server.models import Participant, utcnow
from server.services import sessions, trials
from server.services.audit import log_event
from server.services.studies import RuntimeCache
from server.services.teleop_log import TeleopLogWriter
from server.services.teleop_views import guidance_view, scene_info, world_view
from server.teleop_messages import (
    CLIENT_MESSAGE,
    MAX_SEQ,
    AckMessage,
    HelloMessage,
    InputMessage,
    Limits,
    OverMessage,
    TeleopSetup,
    TrialRef,
    TutorialInfo,
    ViewMessage,
    WorldMessage,
)
from server.world.hub import WorldHub
from server.world.teleop import DEADMAN_S, KEEPALIVE_S, TeleopSession, TrialKey

MAX_MESSAGE_BYTES = 4096
#: Seconds a teleoperation's time limit may stand still in all while the page has no usable view (view messages:
#: a reload while the 3D view loads on a slow laptop takes 5-20 s); past it the clock runs again.
MAX_VIEW_WAIT_S = 30.0

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TeleopContext:
    """The session's current trial as the socket needs it (read in one unit of work)."""

    participant_key: str
    study_seed: int
    speed: float
    describe: str
    stage: TrialStage | None
    trial: TrialRef | None  # as the hello message says it
    key: TrialKey | None  # the world's key of that trial
    planned: PlannedTrial | None
    deadline_in_s: float | None  # until this try's time limit, at the moment it was read
    time_limit_s: float | None
    tries: int
    tutorial: TutorialInfo | None
    rules: TeleopRules
    view_wait_used_s: float = 0.0  # the time limit stood still this long already (teleop_view_wait_ms)
    language: str = "en"  # the participant's (the guidance's words)


def load_context(session: Session, runtimes: RuntimeCache, planner: trials.AttemptPlanner, token: str
                 ) -> TeleopContext:
    """The participant's current trial (raises AppError for an unknown or finished session)."""
    participant, _, runtime = sessions.open_session(session, runtimes, token)
    sessions.require_active(participant)
    now = utcnow()
    trials.advance(session, participant, runtime, now=now, planner=planner)
    sessions.touch(participant)
    row = trials.current_trial(session, participant)
    config = runtime.config
    tries = (row.teleop_tries or 1) if row is not None else 1
    teleop = row if row is not None and row.stage == TrialStage.TELEOP else None  # the trial teleoperated now
    return TeleopContext(
        participant_key=participant.public_id, study_seed=config.seed, speed=config.timing.animation_speed,
        language=participant.language,
        describe=sessions.describe(participant.step), stage=None if row is None else row.stage,
        key=None if row is None else TrialKey(participant.public_id, row.ref),
        trial=None if row is None else TrialRef(practice=row.practice, block=row.block, trial=row.trial,
                                                complexity=row.complexity),
        planned=trials.planned_trial(participant, runtime) if row is not None else None,
        deadline_in_s=((teleop.teleop_deadline_at - now).total_seconds()
                       if teleop is not None and teleop.teleop_deadline_at else None),
        time_limit_s=trials.teleop_time_limit_s(config, teleop) if teleop is not None else None, tries=tries,
        tutorial=TutorialInfo(try_number=tries, max_tries=config.practice.tutorial.max_tries)
        if teleop is not None and teleop.tutorial else None,
        rules=TeleopRules(teleop.grasp_radius_m or config.teleop.grasp_radius_m,
                          teleop.align_radius_m if teleop.align_radius_m is not None
                          else config.teleop.align_radius_m) if teleop is not None else TeleopRules(),
        view_wait_used_s=(row.teleop_view_wait_ms or 0.0) / 1000 if row is not None else 0.0)


class TeleopChannel:
    """One teleoperation socket: what it holds, what it has shown, and when it ends."""

    def __init__(self, services: Services, token: str):
        self.token = token
        self.database, self.runtimes = services.database, services.runtimes
        self.hub: WorldHub = services.hub
        self.log_writer: TeleopLogWriter = services.teleop_log
        self.settings = services.settings
        self.context: TeleopContext | None = None
        self.teleop: TeleopSession | None = None
        self.deadline = math.inf  # monotonic, without a view wait in progress
        self.view_wait_since: float | None = None  # monotonic: the client said it has no usable view
        self.view_wait_left_s = 0.0  # what the time limit may still stand still (MAX_VIEW_WAIT_S in all)
        self.view_wait_provisional_s = 0.0  # added to the stored deadline when the wait began (the sweeper's)
        self.shown_version = -1
        self.holds_input = False  # this socket sent the input the arm holds
        self.finished = False

    # -- the socket's life ---------------------------------------------------------------------------------------
    async def open(self) -> HelloMessage:
        """Read the session and take its arm; ``finished`` when it is not being teleoperated."""
        self._take(await self.database.run(self._load_context))
        return self.hello()

    def _take(self, context: TeleopContext) -> None:
        self.context = context
        key = context.key
        if context.stage != TrialStage.TELEOP or key is None or context.planned is None:
            self.teleop, self.finished = None, True
            return
        scene = self.hub.scene(context.study_seed, context.participant_key, context.planned)
        self.teleop = self.hub.teleop(key, scene, context.rules, context.speed)
        self.log_writer.watch(self.token, self.teleop)
        # (while a view wait is in progress the stored deadline holds its provisional extension: not counted here)
        self.deadline = time.monotonic() + (context.deadline_in_s or 0.0) - self.view_wait_provisional_s
        if self.view_wait_since is None:
            self.view_wait_left_s = max(0.0, MAX_VIEW_WAIT_S - context.view_wait_used_s)
        self.shown_version = self.teleop.version

    def hello(self) -> HelloMessage:
        context, teleop = self.context, self.teleop
        assert context is not None
        setup = None
        if teleop is not None:
            now = time.monotonic()
            setup = TeleopSetup(scene=scene_info(teleop.scene, context.rules), limits=self.limits(teleop),
                                time_limit_s=context.time_limit_s or 0.0, time_left_ms=self._left_ms(now),
                                tutorial=context.tutorial, world=world_view(teleop.state),
                                guidance=guidance_view(teleop, context.language))
        return HelloMessage(stage=context.stage, trial=context.trial, teleop=setup)

    def limits(self, teleop: TeleopSession) -> Limits:
        return Limits(max_ee_speed=K.MAX_EE_SPEED, max_joint_speed=K.MAX_JOINT_SPEED,
                      grasp_radius=teleop.rules.grasp_radius, align_radius=teleop.rules.align_radius,
                      speedup=teleop.speedup, deadman_s=DEADMAN_S, keepalive_s=KEEPALIVE_S,
                      world_hz=self.world_hz(), rate_limit_hz=self.settings.teleop_rate_limit_hz,
                      max_view_wait_s=MAX_VIEW_WAIT_S, view_wait_left_s=round(self.view_wait_left_s, 3))

    def world_hz(self) -> float:
        """World messages a second at most: ``teleop_world_hz``, and no more than the world loop ticks (the socket
        pushes right after a tick) when it runs. A client that closes its loop through the socket needs the rate
        it gets."""
        if self.hub.ticking:
            return min(self.settings.teleop_world_hz, self.settings.world_hz)
        return self.settings.teleop_world_hz

    @property
    def participant_key(self) -> str | None:
        return None if self.context is None else self.context.participant_key

    async def close(self) -> None:
        """The socket is gone: stop the arm this socket moved, and write what it logged (even when cancelled)."""
        teleop = self.teleop
        if teleop is None:
            return
        if self.holds_input:
            self.hub.arms.release(teleop)
        if (ended := self._view_wait_over(time.monotonic())) is not None:  # a reload again before the view came
            await self.database.in_thread(self._shift_deadline_here, *ended)
        await self.log_writer.write_closing(self.token, teleop)

    def _load_context(self, session: Session) -> TeleopContext:
        return load_context(session, self.runtimes, self.hub, self.token)

    def _shift_deadline_here(self, key: TrialKey, by_s: float, waited_s: float | None) -> None:
        """``_shift_teleop_deadline`` in this worker thread."""
        with self.database.begin() as session:
            _shift_teleop_deadline(session, self.token, key, by_s, waited_s)

    # -- client messages -----------------------------------------------------------------------------------------
    async def receive(self, raw: str) -> list[Any]:
        """The replies to one client message: its ack, and the world (or ``over``) when it changed something."""
        if len(raw) > MAX_MESSAGE_BYTES:
            return [AckMessage(seq=None, ok=False, error=f"message larger than {MAX_MESSAGE_BYTES} bytes")]
        try:
            message = CLIENT_MESSAGE.validate_json(raw)
        except ValidationError as exc:
            if self.teleop is not None and not self.hub.arms.allow(self.teleop):  # refused messages count too
                return [AckMessage(seq=None, ok=False, error="too many messages; slow down")]
            return [AckMessage(seq=_seq_of(raw), ok=False, error=_readable(exc))]
        if (ended := await self._check_current()) is not None:
            return [AckMessage(seq=message.seq, ok=False, error="this teleoperation has ended"), ended]
        teleop = self.teleop
        assert teleop is not None
        if not self.hub.arms.allow(teleop) and not _stops(message):
            # A release is never refused: stopping the arm is cheap and must not wait for the dead-man time.
            return [AckMessage(seq=message.seq, ok=False, error="too many messages; slow down")]
        if isinstance(message, ViewMessage):
            return await self._view(message)
        if not isinstance(message, InputMessage):
            self.hub.arms.keepalive(teleop)
            return [AckMessage(seq=message.seq, ok=True)]
        events = self.hub.arms.set_input(teleop, message.command, seq=message.seq, client_ms=message.client_ms)
        self.holds_input = True
        replies: list[Any] = [AckMessage(seq=message.seq, ok=True)]
        if WorldEvent.DEPOSITED in events:
            replies += [self._world_message(time.monotonic()), await self._deposited(teleop)]
        elif message.gripper is not None:
            replies.append(self._world_message(time.monotonic()))
        return replies

    async def _view(self, message: ViewMessage) -> list[Any]:
        """The client has no usable view (the time limit stands still, within what is left of ``MAX_VIEW_WAIT_S``),
        or has one again."""
        now = time.monotonic()
        if message.usable:
            await self._end_view_wait(now)
        elif self.view_wait_since is None and self.view_wait_left_s > 0:
            key, budget = self._key(), self.view_wait_left_s
            # The stored deadline moves by the whole budget now (so the sweeper does not end the teleoperation
            # meanwhile); the part not waited goes back when the view comes or the socket closes.
            await self.database.run(lambda session: _shift_teleop_deadline(session, self.token, key, budget, None))
            self.view_wait_since, self.view_wait_provisional_s = now, budget
        return [AckMessage(seq=message.seq, ok=True), self._world_message(now)]

    async def _end_view_wait(self, now: float) -> None:
        if (ended := self._view_wait_over(now)) is not None:
            await self.database.run(lambda session: _shift_teleop_deadline(session, self.token, *ended))

    def _view_wait_over(self, now: float) -> tuple[TrialKey, float, float] | None:
        """End the view wait in progress: (trial, the stored deadline's correction, seconds waited), or None."""
        if self.view_wait_since is None:
            return None
        waited = min(now - self.view_wait_since, self.view_wait_provisional_s)
        correction = waited - self.view_wait_provisional_s
        self.deadline += waited
        self.view_wait_left_s -= waited
        self.view_wait_since, self.view_wait_provisional_s = None, 0.0
        return self._key(), correction, waited

    def _key(self) -> TrialKey:
        assert self.context is not None and self.context.key is not None
        return self.context.key

    def _deadline(self, now: float) -> float:
        """When the time limit runs out: the deadline, later by the view wait in progress (within its budget)."""
        if self.view_wait_since is None:
            return self.deadline
        return self.deadline + min(now - self.view_wait_since, self.view_wait_provisional_s)

    async def _deposited(self, teleop: TeleopSession) -> OverMessage:
        await self._end_view_wait(time.monotonic())
        elapsed_ms = (time.monotonic() - teleop.started) * 1000
        recorded = await self.log_writer.write_with(
            self.token, teleop, lambda session, participant: _finish(session, self.runtimes, participant, teleop.key,
                                                                     elapsed_ms=elapsed_ms))
        self.hub.arms.end(teleop.key)
        return self._over("deposited", trial_recorded=recorded)

    # -- the server's side ---------------------------------------------------------------------------------------
    async def push_forever(self, send: Any) -> None:
        """Push the world at most ``teleop_world_hz`` a second, each time right after the world loop moved it (every
        n-th tick when the loop ticks faster)."""
        period = 1.0 / self.world_hz()
        ticks_per_push = max(1, math.ceil(self.settings.world_hz * period - 1e-9))
        while not self.finished:
            if self.hub.ticking:
                await self.hub.next_tick(timeout=2 * period, ticks=ticks_per_push)  # a late loop: push anyway
            else:
                await asyncio.sleep(period)
            await send(await self.poll())

    async def poll(self) -> list[Any]:
        """What to push now: the world if it moved, ``over`` when the teleoperation ended."""
        if self.finished:
            return []
        now = time.monotonic()
        if (ended := await self._check_current(now)) is not None:
            return [ended]
        teleop = self.teleop
        assert teleop is not None
        if not self.hub.ticking:  # otherwise the world loop has just moved the arm
            self.hub.arms.advance(teleop, now)
        return [self._world_message(now)] if teleop.version != self.shown_version else []

    async def _check_current(self, now: float | None = None) -> OverMessage | None:
        """``over`` when this teleoperation has ended: its time ran out, or it was resolved elsewhere."""
        if self.finished:
            return self._over("ended")
        teleop = self.teleop
        assert teleop is not None
        now = time.monotonic() if now is None else now
        if self.hub.arms.is_current(teleop) and now < self._deadline(now):
            return None
        before = self.context
        assert before is not None
        await self.log_writer.write(self.token, teleop)
        context = await self.database.run(self._load_context)
        if context.stage == TrialStage.TELEOP and context.key == before.key:
            if context.tries == before.tries:  # not over yet (the deadline read a moment early): go on
                self._take(context)
                return None
            return self._over("time_limit", retry=True)  # a new guided try: the client reconnects
        key = before.key
        assert key is not None
        timed_out = await self.database.run(lambda session: _timed_out(session, self.token, key))
        self.context = context
        return self._over("time_limit" if timed_out else "ended")

    def _over(self, reason: str, *, trial_recorded: bool = False, retry: bool = False) -> OverMessage:
        self.finished = True
        return OverMessage(reason=reason, trial_recorded=trial_recorded, retry=retry)

    def _world_message(self, now: float) -> WorldMessage:
        teleop = self.teleop
        assert teleop is not None
        events = teleop.events_since(self.shown_version)
        self.shown_version = teleop.version
        return WorldMessage(input_seq=teleop.input_seq, server_ms=teleop.server_ms(now), world=world_view(teleop.state),
                            guidance=guidance_view(teleop, self._language()), events=events, moving=teleop.moving,
                            time_left_ms=self._left_ms(now))

    def _language(self) -> str:
        return self.context.language if self.context is not None else "en"

    def _left_ms(self, now: float) -> float:
        deadline = self._deadline(now)
        return round(max(0.0, deadline - now) * 1000, 1) if math.isfinite(deadline) else 0.0


# -- the database side -----------------------------------------------------------------------------------------------
def _finish(session: Session, runtimes: RuntimeCache, participant: Participant, key: TrialKey, *,
            elapsed_ms: float) -> bool:
    """Complete the trial after a deposit (with the teleoperation's last entries: ``TeleopLogWriter.write_with``);
    False if it was already resolved (e.g. by the time limit)."""
    runtime = sessions.runtime_of(session, runtimes, participant)
    trial = trials.current_trial(session, participant)
    if trial is None or trial.stage != TrialStage.TELEOP or trial.ref != key.ref:
        return False
    trials.finish_teleop(session, participant, runtime, trial, success=True, teleop_time_ms=elapsed_ms, now=utcnow())
    return True


def _shift_teleop_deadline(session: Session, token: str, key: TrialKey, by_s: float, waited_s: float | None) -> None:
    """Move the teleoperation's stored deadline by ``by_s`` (while it is still teleoperated) and, at the end of a view
    wait, record the ``waited_s`` (``Trial.teleop_view_wait_ms``, an event)."""
    participant = sessions.participant_by_token(session, token, lock=True)
    trial = trials.find_trial(session, participant, key.ref)
    if trial is None:
        return
    if trial.stage == TrialStage.TELEOP and trial.teleop_deadline_at is not None:
        trial.teleop_deadline_at = trial.teleop_deadline_at + timedelta(seconds=by_s)
    if waited_s is not None:
        trial.teleop_view_wait_ms = round((trial.teleop_view_wait_ms or 0.0) + waited_s * 1000, 1)
        log_event(session, participant.study_id, participant.id, EventKind.TELEOP_VIEW_WAIT, **key.ref._asdict(),
                  waited_ms=round(waited_s * 1000, 1))


def _timed_out(session: Session, token: str, key: TrialKey) -> bool:
    """Whether the trial ``key`` ended because its teleoperation ran out of time."""
    participant = sessions.participant_by_token(session, token)
    trial = trials.find_trial(session, participant, key.ref)
    return trial is not None and trial.stage == TrialStage.DONE and trial.teleop_success is False


def _stops(message: Any) -> bool:
    """Whether ``message`` lets go of every motion (an input with nothing held and no gripper action)."""
    return (isinstance(message, InputMessage) and message.ee_velocity is None and message.joint_velocity is None
            and message.gripper is None)


def _seq_of(raw: str) -> int | None:
    """The seq of a message that failed validation, when it has a readable one (for the ack)."""
    try:
        value = strict_json.loads(raw).get("seq")
    except (strict_json.StrictJsonError, AttributeError):
        return None
    return value if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_SEQ else None


def _readable(exc: ValidationError) -> str:
    first = exc.errors()[0]
    where = ".".join(str(p) for p in first.get("loc", ()))
    return f"invalid message: {where + ': ' if where else ''}{first.get('msg', 'not valid')}"
