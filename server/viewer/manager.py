"""The 3D views of the participant sessions that have a viewer connected: in the view process when serving with
uvicorn (``server.viewer.process``; the server's side is ``server.viewer.remote``), else in the server's own
process. ``SessionViews`` is what the server's requests ask of either.

Lifecycle: a session's view is created on the first viewer websocket of a valid, active session (``open``), and
stopped when the session finishes, when its last viewer has been gone for ``idle_stop_s``, or on app shutdown
(``close``); stopping it closes its viewer sockets.

A session's view is its scene (``server.viewer.scene.SceneView``: viser's messages, replayed to every viewer that
connects) and what moves in it (``server.viewer.live``), both written by the viewer sockets in viser's wire format.
What the view shows comes from two sources:

- the database, read in units of work every ``poll_s`` (``server.viewer.targets``: two queries per ``POLL_CHUNK``
  sessions, and at once for a session whose trial starts in this process): which trial the participant is at (its
  scene: items, obstacles, target) and its stage. Then, as a step of its own, an attempt under way that the hub is
  not playing (this process restarted, or another process started it) is played back from its start time.
- the world hub, once per 30 Hz tick, on the event loop: while the hub has a world of the trial shown (its attempt
  being played back, its teleoperation), the session's ``LiveView`` turns it into one frame and every viewer socket
  of the session gets it. Otherwise the robot rests: at the trial's start pose (before the attempt, between trials)
  or where teleoperation starts (parked at the shelf); when a world ends (an item deposited by teleoperation) its
  last pose holds until the database says what comes next.

Threads: none of trustlab's own, and none per session. A new trial's nodes are built on the event loop (~40 viser
messages, under a millisecond) and packed once for every viewer of the session; a frame costs tens of microseconds.
Why (and what was measured against it): docs/architecture.md, "The 3D view".
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Protocol, TypeVar

from sqlalchemy.orm import Session

from experiment.engine import StudyRuntime
from experiment.world import build_scene
from server.errors import NotFound
from server.loadmeter import views_skip_too_many
from server.models import Participant, Trial, utcnow
from server.services import sessions, trials
from server.services.studies import RuntimeCache
from server.viewer.live import LiveView, ViewerSink, offer_all
from server.viewer.scene import SceneView, preamble
from server.viewer.targets import LOBBY_SCENE, AttemptUnderWay, Reading, Target, Targets
from server.world.hub import WorldHub
from server.world.playback import LiveWorld

log = logging.getLogger("trustlab.viewer")

#: Stop a session's view this long after its last viewer left (s).
IDLE_STOP_S = 60.0
#: How often the database is read for every session's current trial (s). A trial started in this process is shown
#: at once (``show_started``); the poll catches up with the rest (the next trial's scene between trials, attempts this
#: process did not start, finished sessions).
POLL_S = 1.0
#: Sessions read per unit of work by a poll: a unit holds the event loop, and one reading 100 sessions took 40 to
#: 140 ms at 100 participants (most of the loop's long callbacks); requests get the loop between chunks.
POLL_CHUNK = 20
#: Graceful degradation (``ViewPacer``): for every ``LATE_STEP_PERIODS`` of a world period that the world loop's ticks
#: start late (the event loop is congested), one more tick may pass between view updates, up to
#: ``MAX_TICKS_PER_UPDATE``: a lower frame rate of whole states (nothing lost), so that requests, decisions and
#: teleoperation keep the loop. The views get every other tick while ticks start three quarters of a period late or
#: more (25 ms at 30 Hz), and every tick again as soon as one starts on time; the graded pacer and the other
#: thresholds measured against it: docs/architecture.md, "The 3D view". A share of the period, not a time: at another
#: ``world_hz`` a fixed 25 ms would be several periods (240 Hz) or a quarter of one (10 Hz).
LATE_STEP_PERIODS = 0.75
MAX_TICKS_PER_UPDATE = 2
#: Shedding starts with the ``LATE_TICKS_BEFORE_SHEDDING``-th late tick in a row. From the third was measured and
#: left off (docs/architecture.md, "The 3D view"). The default stays the first.
LATE_TICKS_BEFORE_SHEDDING = 1
#: How often the log says how many ticks the views skipped (a warning: the server is short of capacity), if any.
SHEDDING_REPORT_S = 60.0
#: How much of an earlier tick's lateness the pacer still counts, per tick (0: only the latest tick's).
LATENESS_FADE = 0.0

T = TypeVar("T")


@dataclass
class ViewPacer:
    """Which world ticks update the views: every tick while the ticks start on time, every n-th while they start
    late, n growing with the lateness (the latest tick's, or what remains of an earlier, later one), counted in
    world periods."""

    late_step: float = LATE_STEP_PERIODS
    max_ticks: int = MAX_TICKS_PER_UPDATE
    fade: float = LATENESS_FADE
    late_ticks_before_shedding: int = LATE_TICKS_BEFORE_SHEDDING
    lateness: float = 0.0
    since_update: int = 0
    late_run: int = 0  # late ticks in a row, this one included

    @property
    def ticks_per_update(self) -> int:
        return min(self.max_ticks, 1 + int(self.lateness / self.late_step))

    def due(self, late_periods: float) -> bool:
        """Whether a tick that started ``late_periods`` world periods late updates the views."""
        late = late_periods >= self.late_step
        self.late_run = self.late_run + 1 if late else 0
        counted = late_periods if not late or self.late_run >= self.late_ticks_before_shedding else 0.0
        self.lateness = max(counted, self.lateness * self.fade)
        self.since_update += 1
        if self.since_update < self.ticks_per_update:
            return False
        self.since_update = 0
        return True


class RunUnit(Protocol):
    """Runs a unit of work in the database turn (``server.db.units.Database.run``)."""

    def __call__(self, work: Callable[[Session], T]) -> Awaitable[T]: ...


@dataclass(eq=False)
class ViewerSession:
    """A participant session's view: its scene, what moves in it and its viewer sockets (the event loop's)."""

    participant_id: int
    public_id: str
    view: SceneView
    live: LiveView
    sinks: set[ViewerSink] = field(default_factory=set)
    viewers: int = 0
    gone_since: float = field(default_factory=time.monotonic)
    finished: bool = False
    closed: bool = False

    def send(self, changes: list[Any], frame: list[Any]) -> None:
        offer_all(self.sinks, changes, frame)

    def send_packed(self, data: bytes) -> None:
        for sink in self.sinks:
            sink.offer_packed(data)


@dataclass(frozen=True)
class ViewStatus:
    """What a process's 3D views hold and who watches them."""

    watched: frozenset[str]  # public ids of the sessions with a viewer socket open
    # participant id -> (seed, complexity) of the scene held with a client connected
    holds: dict[int, tuple[object, str]]
    viewers: dict[int, int]  # participant id -> viewer sockets that get what moves
    ticks_seen: int
    ticks_skipped: int


class SessionViews(abc.ABC):
    """What a process that serves participants asks of their 3D views, wherever the views are served: in this
    process (``ViewerManager``) or in a view process of its own (``server.viewer.remote.RemoteViewers``)."""

    def __init__(self, hub: WorldHub, run_unit: RunUnit, runtimes: RuntimeCache):
        self.hub = hub
        self._run_unit = run_unit
        self._runtimes = runtimes
        self._targets = Targets()

    async def lookup(self, token: str) -> tuple[int, str]:
        """(participant id, public id) of an active session; raises AppError (404/409/410) otherwise."""
        if not 16 <= len(token) <= 128:
            raise NotFound("unknown session link; please use the link you were given")

        def find(session: Any) -> tuple[int, str]:
            participant = sessions.participant_by_token(session, token)
            sessions.require_active(participant)
            return participant.id, participant.public_id
        return await self._run_unit(find)

    def target_of_started(self, participant: Participant, trial: Trial, runtime: StudyRuntime) -> Target | None:
        """(in the start's unit of work) What the session's view shows for a trial that has just started, from the
        unit's own rows: no query. None if that cannot be told (logged): the start goes on, the poll catches up."""
        try:
            ref = participant.step.trial_ref
            assert ref is not None
            return self._targets.target(participant, {(participant.id, ref): trial}, lambda: runtime)
        except Exception:
            log.exception("cannot tell what participant %s's viewer should show", participant.public_id)
            return None

    # -- what the views of the sessions do and report (event loop) -----------------------------
    @abc.abstractmethod
    def start(self) -> None:
        """(Re)arm in the running loop (the app's start-up)."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Stop everything (the app's shutdown)."""

    @abc.abstractmethod
    def viewer_count(self) -> int:
        """3D view sockets open."""

    @abc.abstractmethod
    async def show_started(self, participant_id: int, target: Target) -> bool:
        """Show a trial that has just started in this process at once (not at the next poll). True when the
        session's viewer then holds its scene with a client connected: the start's answer says so
        (``scene_in_viewer``), so the page's first 3D report after drawing counts and a second report per trial is
        not needed."""

    @abc.abstractmethod
    def holds_scene(self, participant_id: int, seed: object, complexity: str) -> bool:
        """Whether the session's viewer holds the scene of ``seed`` and ``complexity`` with a client connected
        (viser sends a connected client every scene change at once: a page whose 3D view draws is then drawing
        this scene)."""

    @abc.abstractmethod
    def set_view(self, participant_id: int, view: str) -> int:
        """Camera preset for a participant's viewers (remembered for later ones); returns the viewers moved."""

    ticks_seen = 0  # world ticks the views saw, and skipped (``ViewPacer``): the load report's
    ticks_skipped = 0


class ViewerManager(SessionViews):
    """Participant id → the session's view; the viewer sockets open and release theirs here."""

    def __init__(self, hub: WorldHub, run_unit: RunUnit, runtimes: RuntimeCache, *,
                 idle_stop_s: float = IDLE_STOP_S, poll_s: float = POLL_S):
        super().__init__(hub, run_unit, runtimes)
        self.idle_stop_s = idle_stop_s
        self.poll_s = poll_s
        #: Attempts that began less than this long ago (s) are not planned and played back here: their server is
        #: sending the playback (0: this process's hub is the server's own, which plays them as they begin)
        self.announced_playback_s = 0.0
        self._sessions: dict[int, ViewerSession] = {}  # event loop's view
        self._views: dict[int, str] = {}  # camera preset per participant, kept across server restarts
        self._create_lock: asyncio.Lock | None = None
        self._poller: asyncio.Task | None = None
        self._closing = False
        self._listening: WorldHub | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.pacer = ViewPacer()
        self._tick_due: bool | None = None  # the pacer's word on the tick being computed (``_wanted``)
        self.ticks_skipped = 0
        self.ticks_seen = 0
        self._shedding_reported = (time.monotonic(), 0, 0)  # (when, ticks seen, ticks skipped) at the last report
        #: Worlds another process computes (a view process: the teleoperations of the server's sessions), shown as
        #: they arrive (``show_worlds``)
        self.remote_worlds: dict[str, LiveWorld] = {}
        #: Called (on the event loop) when what the views hold or who watches changed (a view process reports it)
        self.on_change: Callable[[], None] | None = None

    def start(self) -> None:
        """(Re)arm the manager in the running loop (views, the poll and the tick listener start with the first
        viewer)."""
        self._closing = False
        self._create_lock = asyncio.Lock()
        self._loop = asyncio.get_running_loop()

    def sessions(self) -> list[ViewerSession]:
        return list(self._sessions.values())

    def session_of(self, participant_id: int) -> ViewerSession | None:
        return self._sessions.get(participant_id)

    # -- reading and playback (units of work on the event loop, as participants' requests: server.db.units) ---
    async def read_targets(self, participant_ids: list[int]) -> Reading:
        """Every listed session's current trial and stage, and the attempts under way: two queries, read only."""
        return await self._run_unit(lambda session: self._targets.read(session, participant_ids, self._runtimes))

    async def play_attempts(self, attempts: list[AttemptUnderWay]) -> None:
        """Play back the attempts under way that the hub is not playing: this process did not start them (it
        restarted, or another worker of a group resolved the decision window: the sweeper runs on one worker only),
        and the view should show the arm moving. A unit of work only when there is one to play."""
        now = utcnow()
        missing = [attempt for attempt in attempts if not self._hub_plays(attempt)
                   and not self._announced(attempt, now)]
        if not missing:
            return

        def play(session: Session) -> None:
            for attempt in missing:
                try:
                    runtime = sessions.runtime_of(session, self._runtimes, attempt.participant)
                    trials.play_attempt(attempt.trial, attempt.participant, runtime, self.hub, now=utcnow())
                except Exception:  # the view shows the arm at rest; the next poll tries again
                    log.exception("cannot play back participant %s's attempt", attempt.participant.public_id)
        await self._run_unit(play)

    def _announced(self, attempt: AttemptUnderWay, now: datetime) -> bool:
        """Whether the attempt began so recently that its playback is still on its way from the server (a view
        process: ``announced_playback_s``), rather than one no one will send."""
        decided = attempt.trial.decided_at
        return decided is not None and (now - decided).total_seconds() < self.announced_playback_s

    def _hub_plays(self, attempt: AttemptUnderWay) -> bool:
        live = self.hub.world_of(attempt.participant.public_id)
        return live is not None and live.scene_seed == attempt.scene_seed

    # -- viewers (event loop) ----------------------------------------------------------------
    def viewer_count(self) -> int:
        """3D view sockets open."""
        return sum(vs.viewers for vs in self._sessions.values() if not vs.closed)

    async def open(self, token: str) -> tuple[ViewerSession, ViewerSink]:
        """A new viewer of the session behind ``token`` (starting its view if needed) and its socket's sink, which
        starts with the scene's replay and the whole current state, then gets what moves."""
        if self._closing:
            raise NotFound("the server is shutting down")
        pid, public_id = await self.lookup(token)
        if self._create_lock is None:
            self._create_lock = asyncio.Lock()
        async with self._create_lock:
            vs = self._sessions.get(pid)
            if vs is None or vs.closed:
                vs = await self._start(pid, public_id)
            vs.viewers += 1
        world = self.remote_worlds.get(vs.public_id) or self.hub.world_of(vs.public_id)
        if world is not None and world.scene_seed == vs.live.scene.seed:
            vs.send(*vs.live.follow(world.state))
        sink = ViewerSink()
        sink.start(vs.view.replay(vs.live.whole()))
        vs.sinks.add(sink)
        if self._poller is None or self._poller.done():
            self._poller = asyncio.create_task(self._poll_forever(), name="viewer-poll")
        self._changed()
        return vs, sink

    def release(self, vs: ViewerSession, sink: ViewerSink) -> None:
        vs.sinks.discard(sink)
        vs.viewers = max(0, vs.viewers - 1)
        if vs.viewers == 0:
            vs.gone_since = time.monotonic()
        self._changed()

    def set_view(self, participant_id: int, view: str) -> int:
        self._views[participant_id] = view
        vs = self._sessions.get(participant_id)
        if vs is None or vs.closed:
            return 0
        vs.send(vs.live.set_view(view), [])
        return sum(sink.ready for sink in vs.sinks)

    async def _start(self, pid: int, public_id: str) -> ViewerSession:
        reading = await self.read_targets([pid])
        await self.play_attempts(reading.attempts)
        target = reading.targets[pid]
        if not target.active:
            raise NotFound("this session is finished")
        scene = target.scene if target.scene is not None else build_scene(*LOBBY_SCENE)
        await asyncio.to_thread(preamble)  # (taken once per process from a viser server: blocks)
        vs = ViewerSession(pid, public_id, SceneView(scene),
                           LiveView(scene, self._views.get(pid, "world"), target.stage))
        self._listen()
        self._sessions[pid] = vs
        log.info("3D view of %s started", public_id)
        return vs

    # -- the background poll (event loop) ----------------------------------------------------
    async def _poll_forever(self) -> None:
        while True:
            await asyncio.sleep(self.poll_s)
            try:
                await self.poll_once()
            except Exception:  # keep polling; the next round retries
                log.exception("viewer poll failed")
            self.report_shedding()

    def report_shedding(self, now: float | None = None) -> None:
        """Every ``SHEDDING_REPORT_S``: a warning if the views skipped as large a share of the ticks since the last
        report as makes the dashboard warn (``server.loadmeter.views_skip_too_many``: the event loop was congested,
        the server is short of capacity for its participants). A few skipped ticks below that are the pacer at work."""
        now = time.monotonic() if now is None else now
        since, seen, skipped = self._shedding_reported
        if now - since < SHEDDING_REPORT_S:
            return
        self._shedding_reported = (now, self.ticks_seen, self.ticks_skipped)
        n_skipped, n_seen = self.ticks_skipped - skipped, self.ticks_seen - seen
        if n_seen > 0 and views_skip_too_many(n_skipped / n_seen):
            log.warning("3D views skipped %d of %d world ticks (%.1f %%) in the last %.0f s: the event loop serving "
                        "them was late (short of capacity for its participants); views showed a lower frame rate",
                        n_skipped, n_seen, 100 * n_skipped / n_seen, now - since)

    async def poll_once(self) -> None:
        """Read every session's trial, play attempts the hub is not playing, update scenes, stop finished and idle
        sessions."""
        live = [vs for vs in self._sessions.values() if not vs.closed]
        for start in range(0, len(live), POLL_CHUNK):
            await self._update(live[start:start + POLL_CHUNK])
        self._changed()

    async def show_started(self, participant_id: int, target: Target) -> bool:
        vs = self._sessions.get(participant_id)
        if vs is None or vs.closed or self._closing or target.scene is None:
            return False
        self._apply_target(vs, target)
        self._changed()
        return self.holds_scene(participant_id, target.scene.seed, target.scene.complexity)

    def holds_scene(self, participant_id: int, seed: object, complexity: str) -> bool:
        return self._held_scene(self._sessions.get(participant_id)) == (seed, complexity)

    @staticmethod
    def _held_scene(vs: ViewerSession | None) -> tuple[object, str] | None:
        """(seed, complexity) of the scene the session's viewer holds with a client connected, if any."""
        if vs is None or vs.closed or vs.view.scene is None or not any(sink.ready for sink in vs.sinks):
            return None
        return vs.view.scene.seed, vs.view.scene.complexity

    def status(self) -> ViewStatus:
        """What the views hold and who watches them (a view process reports it to its server)."""
        live = [vs for vs in self._sessions.values() if not vs.closed]
        return ViewStatus(watched=frozenset(vs.public_id for vs in live if vs.sinks),
                          holds={vs.participant_id: held for vs in live if (held := self._held_scene(vs)) is not None},
                          viewers={vs.participant_id: sum(sink.ready for sink in vs.sinks) for vs in live if vs.sinks},
                          ticks_seen=self.ticks_seen, ticks_skipped=self.ticks_skipped)

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change()

    async def _update(self, live: list[ViewerSession]) -> None:
        reading = await self.read_targets([vs.participant_id for vs in live])
        await self.play_attempts(reading.attempts)
        targets = reading.targets
        now = time.monotonic()
        for vs in live:
            if vs.closed:
                continue
            target = targets.get(vs.participant_id)
            if target is None or not target.active:
                vs.finished = True
                await self._stop(vs)
            elif vs.viewers == 0 and now - vs.gone_since > self.idle_stop_s:
                await self._stop(vs)
            else:
                self._apply_target(vs, target)

    async def _stop(self, vs: ViewerSession) -> None:
        if vs.closed:
            return
        vs.closed = True
        if self._sessions.get(vs.participant_id) is vs:
            del self._sessions[vs.participant_id]
        for sink in vs.sinks:
            sink.close()
        log.info("3D view of %s stopped", vs.public_id)

    async def close(self) -> None:
        """Stop the poll and every session's view (app shutdown)."""
        self._closing = True
        await cancel_and_wait(self._poller)
        self._poller = None
        for vs in list(self._sessions.values()):
            await self._stop(vs)
        self._unlisten()

    # -- the hub's ticks ------------------------------------------------------------------------
    def _listen(self) -> None:
        """Follow the hub's ticks (it computes only the worlds of sessions with a viewer)."""
        if self._listening is None:
            self._listening = self.hub
            self._listening.add_tick_listener(self._on_tick, self._wanted)

    def _unlisten(self) -> None:
        if self._listening is not None:
            self._listening.remove_tick_listener(self._on_tick)
            self._listening = None

    def _pacer_due(self) -> bool:
        """The pacer's word on the tick under way, from how late it started as a share of the world period."""
        return self.pacer.due(self.hub.late_s / self.hub.period_s)

    def _wanted(self) -> list[str]:
        """The participants whose worlds a viewer shows (read on the ticking thread; a copy is atomic); none on a
        tick that the pacer leaves out (the hub then computes no world for the views)."""
        self._tick_due = self._pacer_due()
        if not self._tick_due:
            return []
        return [vs.public_id for vs in self._sessions.copy().values() if vs.sinks]

    def _on_tick(self, worlds: dict[str, LiveWorld]) -> None:
        """(event loop) Show every watched session's world of the trial shown; each viewer gets one frame."""
        loop = self._loop
        if loop is not None and not _on_loop(loop):  # a tick run by hand off the loop (tests)
            loop.call_soon_threadsafe(self._on_tick, worlds)
            return
        due, self._tick_due = self._tick_due, None
        if due is None:  # a tick that did not ask what is wanted (by hand)
            due = self._pacer_due()
        self.ticks_seen += 1
        if not due:
            self.ticks_skipped += 1
            return
        self.show_worlds(worlds)

    def show_worlds(self, worlds: dict[str, LiveWorld]) -> None:
        """(event loop) Show these worlds in their sessions' views; each viewer gets one frame."""
        for vs in list(self._sessions.values()):
            live = worlds.get(vs.public_id)
            # the hub keeps a finished attempt's playback until the participant's next world begins: the scene
            # seed tells whether the world is this trial's
            if vs.closed or not vs.sinks or live is None or live.scene_seed != vs.live.scene.seed:
                continue
            try:
                vs.send(*vs.live.follow(live.state))
            except Exception:
                log.exception("viewer update of %s failed", vs.public_id)

    def _apply_target(self, vs: ViewerSession, target: Target) -> None:
        """(event loop) Show the trial and stage the database says: a new trial's nodes to every viewer."""
        if target.scene is not None and not vs.closed:
            try:
                change = vs.view.show_trial(target.scene)  # (None for the trial shown)
            except Exception:  # the view keeps the previous trial (the start says so); the next poll tries again
                log.exception("cannot show %s's trial in its viewer", vs.public_id)
                return
            if change is not None:
                vs.send_packed(change)
            vs.live.show_trial(target.scene)
        else:
            change = None
        vs.live.stage = target.stage
        if target.stage is None:
            vs.live.live = False
        vs.send(*vs.live.rest())
        if change is not None:  # last: a client holding the stamp has the whole first picture of the trial
            vs.send_packed(vs.view.stamp_frame())


async def cancel_and_wait(task: asyncio.Task | None) -> None:
    """Cancel ``task`` (if any) and wait until it has ended."""
    if task is None:
        return
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def _on_loop(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False
