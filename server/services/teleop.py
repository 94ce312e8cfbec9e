"""Teleoperation over a websocket: one ``TeleopChannel`` per socket (the protocol: ``server.teleop_messages``).

The channel reads the session's trial from the database, holds the participant's arm in the ``WorldHub``,
turns client messages into held inputs, pushes the world as it changes, and ends the teleoperation: a
deposit completes the trial in the database before ``over`` is sent; the time limit and a trial resolved
elsewhere (another tab, the sweeper) end it too. Inputs and world events are written to the event log in
batches: every socket's together at most ``LOG_FLUSH_S`` apart (``TeleopLogWriter``), and a socket's last ones
when it closes or the trial completes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from datetime import timedelta
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session, load_only

from experiment.engine import PlannedTrial
from experiment.flow import TrialStage
from experiment.world import constants as K
from experiment.world.guidance import color_name, describe_target, guidance, SHAPE_NAMES
from experiment.world.path import bin_release_point
from experiment.world.robot import arm_points
from experiment.world.scene import Scene, scene_boxes, transfer_height
from experiment.world.teleop import TeleopCommand, TeleopRules
from server.units import run_unit, run_unit_blocking
from server.models import Participant, utcnow
from server.services import sessions, trials
from server.services.audit import log_event
from server import strict_json
from server.teleop_messages import (CLIENT_MESSAGE, MAX_SEQ, AckMessage, BinInfo, BoxInfo, GuidanceView, HelloMessage,
                                    InputMessage, ItemView, Limits, OverMessage, SceneInfo, TargetInfo, TeleopSetup,
                                    TrialRef, TutorialInfo, ViewMessage, WorldMessage, WorldView)
from server.world.hub import DEADMAN_S, KEEPALIVE_S, TeleopSession, TrialKey, WorldHub

LOG_FLUSH_S = 1.0
#: A socket's entries that failed this many writes in a row on their own are dropped (a ``log_lost`` entry says how
#: many): entries that can never be written must not be retried for ever.
MAX_LOG_WRITE_FAILURES = 5
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
    trial: TrialRef | None
    planned: PlannedTrial | None
    deadline_in_s: float | None  # until this try's time limit, at the moment it was read
    time_limit_s: float | None
    tries: int
    tutorial: TutorialInfo | None
    rules: TeleopRules
    view_wait_used_s: float = 0.0  # the time limit stood still this long already (teleop_view_wait_ms)

    @property
    def key(self) -> TrialKey | None:
        t = self.trial
        return None if t is None else TrialKey(self.participant_key, t.practice, t.block, t.trial)


def load_context(session: Session, app: Any, token: str) -> TeleopContext:
    """The participant's current trial (raises AppError for an unknown or finished session)."""
    participant, _, runtime = sessions.open_session(session, app.state.runtimes, token)
    sessions.require_active(participant)
    now = utcnow()
    trials.advance(session, participant, runtime, now=now, planner=app.state.world)
    sessions.touch(participant)
    row = trials.current_trial(session, participant)
    config = runtime.config
    tries = (row.teleop_tries or 1) if row is not None else 1
    teleop = row is not None and row.stage == TrialStage.TELEOP
    return TeleopContext(
        participant_key=participant.public_id, study_seed=config.seed, speed=config.timing.animation_speed,
        describe=sessions.describe(participant.step), stage=None if row is None else row.stage,
        trial=None if row is None else TrialRef(practice=row.practice, block=row.block, trial=row.trial,
                                                complexity=row.complexity),
        planned=trials.planned_trial(participant, runtime) if row is not None else None,
        deadline_in_s=(row.teleop_deadline_at - now).total_seconds() if teleop and row.teleop_deadline_at else None,
        time_limit_s=trials.teleop_time_limit_s(config, row) if teleop else None, tries=tries,
        tutorial=TutorialInfo(try_number=tries, max_tries=config.practice.tutorial.max_tries)
        if teleop and row.tutorial else None,
        rules=TeleopRules(row.grasp_radius_m or config.teleop.grasp_radius_m,
                          row.align_radius_m if row is not None and row.align_radius_m is not None
                          else config.teleop.align_radius_m) if teleop else TeleopRules(),
        view_wait_used_s=(row.teleop_view_wait_ms or 0.0) / 1000 if row is not None else 0.0)


class TeleopChannel:
    """One teleoperation socket: what it holds, what it has shown, and when it ends."""

    def __init__(self, app: Any, token: str):
        self.app, self.token = app, token
        self.hub: WorldHub = app.state.world
        self.settings = app.state.settings
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
        self._take(await run_unit(self.app, lambda session: load_context(session, self.app, self.token)))
        return self.hello()

    def _take(self, context: TeleopContext) -> None:
        self.context = context
        key = context.key
        if context.stage != TrialStage.TELEOP or key is None or context.planned is None:
            self.teleop, self.finished = None, True
            return
        scene = self.hub.scene(context.study_seed, context.participant_key, context.planned)
        self.teleop = self.hub.teleop(key, scene, context.rules, context.speed)
        self.app.state.teleop_log.watch(self.token, self.teleop)
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
                                guidance=guidance_view(teleop))
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
            self.hub.release(teleop)
        if (ended := self._view_wait_over(time.monotonic())) is not None:  # a reload again before the view came
            await self.app.state.database.in_thread(
                run_unit_blocking, self.app, lambda session: _shift_teleop_deadline(session, self.token, *ended))
        self.app.state.teleop_log.forget(self.token, teleop)
        if batch := teleop.take_log():
            await self.app.state.database.in_thread(
                run_unit_blocking, self.app, lambda session: _log_batches(session, [(self.token, teleop, batch)]))

    # -- client messages -----------------------------------------------------------------------------------------
    async def receive(self, raw: str) -> list[Any]:
        """The replies to one client message: its ack, and the world (or ``over``) when it changed something."""
        if len(raw) > MAX_MESSAGE_BYTES:
            return [AckMessage(seq=None, ok=False, error=f"message larger than {MAX_MESSAGE_BYTES} bytes")]
        try:
            message = CLIENT_MESSAGE.validate_json(raw)
        except ValidationError as exc:
            if self.teleop is not None and not self.hub.allow(self.teleop):  # refused messages count too
                return [AckMessage(seq=None, ok=False, error="too many messages; slow down")]
            return [AckMessage(seq=_seq_of(raw), ok=False, error=_readable(exc))]
        if (ended := await self._check_current()) is not None:
            return [AckMessage(seq=message.seq, ok=False, error="this teleoperation has ended"), ended]
        teleop = self.teleop
        assert teleop is not None
        if not self.hub.allow(teleop) and not _stops(message):
            # A release is never refused: stopping the arm is cheap and must not wait for the dead-man time.
            return [AckMessage(seq=message.seq, ok=False, error="too many messages; slow down")]
        if isinstance(message, ViewMessage):
            return await self._view(message)
        if not isinstance(message, InputMessage):
            self.hub.keepalive(teleop)
            return [AckMessage(seq=message.seq, ok=True)]
        held = TeleopCommand(ee_velocity=message.ee_velocity, joint_velocity=message.joint_velocity)
        events = self.hub.set_input(teleop, held, message.gripper, seq=message.seq, client_ms=message.client_ms)
        self.holds_input = True
        replies: list[Any] = [AckMessage(seq=message.seq, ok=True)]
        if "deposited" in events:
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
            await run_unit(self.app, lambda session: _shift_teleop_deadline(session, self.token, key, budget, None))
            self.view_wait_since, self.view_wait_provisional_s = now, budget
        return [AckMessage(seq=message.seq, ok=True), self._world_message(now)]

    async def _end_view_wait(self, now: float) -> None:
        if (ended := self._view_wait_over(now)) is not None:
            await run_unit(self.app, lambda session: _shift_teleop_deadline(session, self.token, *ended))

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
        batch = teleop.take_log()
        recorded = await run_unit(self.app, lambda session: _finish(session, self.app, self.token, teleop,
                                                                     batch=batch, elapsed_ms=elapsed_ms))
        self.hub.end_teleop(teleop.key)
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
            self.hub.advance(teleop, now)
        return [self._world_message(now)] if teleop.version != self.shown_version else []

    async def _check_current(self, now: float | None = None) -> OverMessage | None:
        """``over`` when this teleoperation has ended: its time ran out, or it was resolved elsewhere."""
        if self.finished:
            return self._over("ended")
        teleop = self.teleop
        assert teleop is not None
        now = time.monotonic() if now is None else now
        if self.hub.is_current(teleop) and now < self._deadline(now):
            return None
        before = self.context
        assert before is not None
        await self._flush(teleop)
        context = await run_unit(self.app, lambda session: load_context(session, self.app, self.token))
        if context.stage == TrialStage.TELEOP and context.key == before.key:
            if context.tries == before.tries:  # not over yet (the deadline read a moment early): go on
                self._take(context)
                return None
            return self._over("time_limit", retry=True)  # a new guided try: the client reconnects
        key = before.key
        assert key is not None
        timed_out = await run_unit(self.app, lambda session: _timed_out(session, self.token, key))
        self.context = context
        return self._over("time_limit" if timed_out else "ended")

    async def _flush(self, teleop: TeleopSession) -> None:
        if batch := teleop.take_log():
            await run_unit(self.app, lambda session: _log_batches(session, [(self.token, teleop, batch)]))

    def _over(self, reason: str, *, trial_recorded: bool = False, retry: bool = False) -> OverMessage:
        self.finished = True
        return OverMessage(reason=reason, trial_recorded=trial_recorded, retry=retry)

    def _world_message(self, now: float) -> WorldMessage:
        teleop = self.teleop
        assert teleop is not None
        events = teleop.events_since(self.shown_version)
        self.shown_version = teleop.version
        return WorldMessage(input_seq=teleop.input_seq, server_ms=teleop.server_ms(now), world=world_view(teleop.state),
                            guidance=guidance_view(teleop), events=events, moving=teleop.moving,
                            time_left_ms=self._left_ms(now))

    def _left_ms(self, now: float) -> float:
        deadline = self._deadline(now)
        return round(max(0.0, deadline - now) * 1000, 1) if math.isfinite(deadline) else 0.0


# -- what the messages carry -----------------------------------------------------------------------------------------
def _vec(values: Any) -> tuple[float, ...]:
    return tuple(round(float(v), 6) for v in values)


def world_view(state: Any) -> WorldView:
    item = state.item
    return WorldView(t=round(state.t, 6), base=_vec(state.base), joints=_vec(state.joints),
                     gripper=round(state.gripper, 6), gripper_target=round(state.gripper_target, 6),
                     tcp=_vec(arm_points(state.base, state.joints).tcp),
                     item=ItemView(mode=item.mode.value, position=_vec(item.position), wxyz=_vec(item.wxyz)))


def guidance_view(teleop: TeleopSession) -> GuidanceView:
    g = guidance(teleop.state, teleop.scene, teleop.rules)
    return GuidanceView(step=g.step.value, text=g.text, can_grasp=g.can_grasp, over_bin=g.over_bin,
                        blocked=teleop.blocked, grasp_distance=round(g.grasp_distance, 6), to_grasp=_vec(g.to_grasp),
                        to_bin=_vec(g.to_bin))


def _box(box: Any) -> BoxInfo:
    return BoxInfo(name=box.name, center=_vec(box.center), size=_vec(box.size))


def scene_info(scene: Scene, rules: TeleopRules) -> SceneInfo:
    """What a client needs to know of the trial's world to steer: target, obstacles, shelf, bin."""
    target = scene.target
    x, y, yaw = scene.park
    c, s = math.cos(yaw), math.sin(yaw)
    bx, by = K.BIN_XY
    opening = (K.BIN_SIZE[0] - 2 * K.BIN_WALL, K.BIN_SIZE[1] - 2 * K.BIN_WALL)
    others = [b for b in scene_boxes(scene) if b.name.startswith("/items/")]
    return SceneInfo(
        complexity=scene.complexity, seed=str(scene.seed), target_slot=target.slot,
        target=TargetInfo(slot=target.slot, description=describe_target(scene), color=color_name(target.color),
                          shape=SHAPE_NAMES[target.shape], center=_vec(target.center), size=_vec(target.size),
                          grasp_point=_vec(target.grasp_point())),
        obstacles=[_box(b) for b in scene.obstacles], shelf=[_box(b) for b in scene.shelf],
        other_items=[_box(b) for b in others],
        bin=BinInfo(opening_center=(round(x + c * bx - s * by, 6), round(y + s * bx + c * by, 6), K.BIN_RIM),
                    opening_size=opening, rim_z=K.BIN_RIM, yaw=yaw,
                    release_point=_vec(bin_release_point(scene, scene.park))),
        clear_height=round(transfer_height(scene), 6))


class TeleopLogWriter:
    """Writes the new log entries of every open teleoperation together, every ``LOG_FLUSH_S``, in one unit of work.

    One unit a second for each socket, each loading its participant, took 15 % of the server's interpreter lock with
    100 participants teleoperating (py-spy): a unit's fixed cost and an ORM load, a hundred times a second. A socket
    still writes its own last entries when it closes, and a deposit writes them with the trial's completion; the
    database turn is taken in order, so a batch taken here is written before those.
    """

    def __init__(self, app: Any):
        self.app = app
        self._open: dict[tuple[str, int], tuple[str, TeleopSession]] = {}
        self._task: asyncio.Task | None = None
        self._writing: asyncio.Future | None = None  # the last write: ``stop`` waits for it

    def watch(self, token: str, teleop: TeleopSession) -> None:
        self._open[(token, id(teleop))] = (token, teleop)

    def forget(self, token: str, teleop: TeleopSession) -> None:
        self._open.pop((token, id(teleop)), None)

    def start(self) -> None:
        self._task = asyncio.create_task(self._write_forever(), name="teleop-log")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._writing is not None:
            await asyncio.wait([self._writing])
        await self.flush()

    async def _write_forever(self) -> None:
        while True:
            await asyncio.sleep(LOG_FLUSH_S)
            await self.flush()  # what fails is kept for the next round or, past the retries, recorded as a fault

    async def flush(self) -> None:
        """Write every open teleoperation's new entries in one unit; if that fails, each socket's in a unit of its
        own, so that one session's entries that cannot be written never hold back another's."""
        batches = [(token, teleop, batch) for token, teleop in list(self._open.values()) if (batch := teleop.take_log())]
        if not batches or (failure := await self._write(batches)) is None:
            return
        if len(batches) == 1:
            self._not_written(batches[0], failure)
            return
        for done, one in enumerate(batches):
            try:
                failure = await self._write([one])
            except asyncio.CancelledError:
                for later in batches[done + 1:]:  # not tried yet: kept for the flush that ``stop`` makes
                    self._not_written(later, None)
                raise
            if failure is not None:
                self._not_written(one, failure)

    async def _write(self, batches: list[tuple[str, TeleopSession, list[dict[str, Any]]]]) -> Exception | None:
        """Write ``batches`` in one unit of work; the failure, or None when written."""
        writing = self._writing = asyncio.ensure_future(run_unit(self.app, lambda session: _log_batches(session, batches)))
        try:  # shielded: stopping the writer must not cut a write short (its entries would be lost or written twice)
            await asyncio.shield(writing)
        except asyncio.CancelledError:
            raise  # the write goes on by itself; ``stop`` waits for it, then flushes
        except Exception as exc:  # noqa: BLE001 -- the caller keeps the entries or, past the retries, drops them
            return exc
        return None

    def _not_written(self, batch: tuple[str, TeleopSession, list[dict[str, Any]]], failure: Exception | None) -> None:
        """Keep entries that were not written, in order, for the next write; a session whose entries failed
        ``MAX_LOG_WRITE_FAILURES`` times in a row alone loses them (recorded as a fault), not everyone's loop."""
        _, teleop, entries = batch
        if failure is None:
            teleop.log[:0] = entries
            return
        teleop.log_write_failures += 1
        if teleop.log_write_failures < MAX_LOG_WRITE_FAILURES:
            teleop.log[:0] = entries
            return
        teleop.log_write_failures = 0
        self.app.state.faults.record("teleop_log", failure, participant=teleop.participant_key)
        teleop.append_log({"server_ms": teleop.server_ms(time.monotonic()), "event": "log_lost",
                           "entries": len(entries)})


# -- the database side -----------------------------------------------------------------------------------------------
def _finish(session: Session, app: Any, token: str, teleop: TeleopSession, *, batch: list[dict[str, Any]],
            elapsed_ms: float) -> bool:
    """Log ``batch`` and complete the trial, in one transaction; False if it was already resolved (e.g. by the time
    limit)."""
    participant = sessions.participant_by_token(session, token, lock=True)
    _log_entries(session, participant, teleop, batch)
    runtime = sessions.runtime_of(session, app.state.runtimes, participant)
    trial = trials.current_trial(session, participant)
    key = teleop.key
    if trial is None or trial.stage != TrialStage.TELEOP or (trial.practice, trial.block, trial.trial) != (
            key.practice, key.block, key.trial):
        return False
    trials.finish_teleop(session, participant, runtime, trial, success=True, teleop_time_ms=elapsed_ms, now=utcnow())
    return True


def _shift_teleop_deadline(session: Session, token: str, key: TrialKey, by_s: float, waited_s: float | None) -> None:
    """Move the teleoperation's stored deadline by ``by_s`` (while it is still teleoperated) and, at the end of a view
    wait, record the ``waited_s`` (``Trial.teleop_view_wait_ms``, an event)."""
    participant = sessions.participant_by_token(session, token, lock=True)
    trial = trials.find_trial(session, participant, practice=key.practice, block=key.block, trial=key.trial)
    if trial is None:
        return
    if trial.stage == TrialStage.TELEOP and trial.teleop_deadline_at is not None:
        trial.teleop_deadline_at = trial.teleop_deadline_at + timedelta(seconds=by_s)
    if waited_s is not None:
        trial.teleop_view_wait_ms = round((trial.teleop_view_wait_ms or 0.0) + waited_s * 1000, 1)
        log_event(session, participant.study_id, participant.id, "teleop_view_wait", practice=key.practice,
                  block=key.block, trial=key.trial, waited_ms=round(waited_s * 1000, 1))


def _timed_out(session: Session, token: str, key: TrialKey) -> bool:
    """Whether the trial ``key`` ended because its teleoperation ran out of time."""
    participant = sessions.participant_by_token(session, token)
    trial = trials.find_trial(session, participant, practice=key.practice, block=key.block, trial=key.trial)
    return trial is not None and trial.stage == TrialStage.DONE and trial.teleop_success is False


_LOG_COLUMNS = load_only(Participant.token_hash, Participant.study_id, Participant.status, Participant.last_seen_at)


def _log_batches(session: Session, batches: list[tuple[str, TeleopSession, list[dict[str, Any]]]]) -> None:
    """Several sockets' entries, their participants read in one query (only the columns logging needs). A session
    deleted meanwhile (a preview) has nothing to log against: its entries go."""
    hashes = {token: sessions.hash_token(token) for token, _, _ in batches}
    found = session.scalars(select(Participant).where(Participant.token_hash.in_(set(hashes.values())))
                            .options(_LOG_COLUMNS))
    participants = {p.token_hash: p for p in found}
    for token, teleop, batch in batches:
        if (participant := participants.get(hashes[token])) is not None:
            _log_entries(session, participant, teleop, batch)


def _log_entries(session: Session, participant: Participant, teleop: TeleopSession,
                 batch: list[dict[str, Any]]) -> None:
    if not batch:
        return
    sessions.touch(participant)
    key = teleop.key
    log_event(session, participant.study_id, participant.id, "teleop_log", practice=key.practice, block=key.block,
              trial=key.trial, entries=batch)


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
