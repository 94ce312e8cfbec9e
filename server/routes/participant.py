"""Participant API: the token in the path is the only key to a session."""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter, BackgroundTasks, Body, Depends, Request

from experiment.flow import SceneView, TrialRef, TrialStage
from server import strict_json
from server.bodies import StrictJsonRoute
from server.deps import IdempotencyKey, ParticipantContext, ServicesDep, Token, UnitsDep, open_participant
from server.errors import AddressBusy, Conflict, NotFound, RateLimited, StudyFull
from server.i18n import N_
from server.models import Trial, utcnow
from server.schemas import (
    AnswersCreate,
    ConsentCreate,
    DraftRead,
    DraftUpdate,
    EventsCreate,
    HeartbeatUpdate,
    InterventionCreate,
    JoinCreate,
    JoinRead,
    OkRead,
    SceneShownCreate,
    StateRead,
    TrialCreate,
    TrialSceneRead,
    WithdrawCreate,
    error_responses,
)
from server.services import joining, presentation, sessions, surveys, trials, withdrawal
from server.services.audit import log_client_event
from server.services.state import build_state
from server.services.studies import get_study
from server.viewer.targets import Target

router = APIRouter(route_class=StrictJsonRoute, prefix="/api", tags=["participant"])

#: A step of the session: unknown link, out of order or finished, or the session is over.
SESSION_ERRORS = error_responses(404, 409, 410)


def _state(ctx: ParticipantContext) -> StateRead:
    return build_state(ctx.session, ctx.study, ctx.participant, ctx.runtime, now=ctx.now)


def limit_joins(slug: str, request: Request, services: ServicesDep) -> None:
    """429 with Retry-After past the join rate limits: per client address, then per study."""
    by_address, by_study = services.join_limits.by_address, services.join_limits.by_study
    address = request.client.host if request.client else "unknown"
    for limiter, key, source in ((by_address, address, "from this address"), (by_study, slug, "for this study")):
        if wait := limiter.take(key):
            raise RateLimited(f"too many joins {source} (at most {limiter.per_minute:.0f} a minute); "
                              f"retry in {math.ceil(wait)} s", retry_after_s=math.ceil(wait))


@router.post("/studies/{slug}/join", response_model=JoinRead, status_code=200,
             responses=error_responses(404, 409, 410, 429, 503), dependencies=[Depends(limit_joins)])
async def join(slug: str, request: Request, services: ServicesDep, units: UnitsDep,
               body: Annotated[JoinCreate | None, Body()] = None) -> JoinRead:
    """Start a session, or resume this person's: a known external id (e.g. PROLIFIC_PID) with the browser's
    ``resume_key`` it joined with, or the same Prolific SESSION_ID / MTurk assignmentId. The id alone is no key: a
    join with it and without that proof gets a new session marked as a duplicate (a data-quality flag).

    Recruitment parameters come as query parameters of the join link or in the body. A new session past the
    study's cap on active participants (config ``recruitment.max_active_participants``; consented sessions, and
    unconsented ones seen in the last ``unconsented_place_hold_s``) is refused with 503, ``Retry-After`` and code
    ``study_full``; under a cap, a join from an address already holding ``max_unconsented_per_address`` unconsented
    sessions with 429 and code ``address_busy``. A returning participant is never refused. A study that is still a
    draft refuses with 409 and code ``study_not_open``, a closed one with 410.
    """
    params = dict(request.query_params) | (body.params if body else {})
    settings = services.settings
    runtimes, base_url = services.runtimes, settings.base_url()
    admission = joining.Admission(unconsented_hold_s=settings.unconsented_place_hold_s,
                                  max_unconsented_per_address=settings.max_unconsented_per_address)

    def work(session) -> JoinRead | StudyFull | AddressBusy:
        study = get_study(session, slug)
        now = utcnow()
        arrival = joining.JoinRequest(resume_key=(body.resume_key if body else None) or joining.new_resume_key(),
                                      address=request.client.host if request.client else None, now=now,
                                      accept_language=request.headers.get("accept-language"))
        try:
            participant, token, created = joining.join(session, study, params, runtimes, arrival, admission)
        except (StudyFull, AddressBusy) as refusal:
            return refusal  # returned, not raised: the unit commits the refusal's event
        runtime = sessions.runtime_of(session, runtimes, participant)
        state = build_state(session, study, participant, runtime, now=now)
        return JoinRead(token=token, participant_url=f"{base_url}/p/{token}", created=created,
                        resume_key=arrival.resume_key, state=state)
    joined = await units.run(work)
    if isinstance(joined, StudyFull | AddressBusy):
        raise joined
    return joined


@router.get("/p/{token}/state", response_model=StateRead, responses=error_responses(404))
async def get_state(token: Token, services: ServicesDep, units: UnitsDep) -> StateRead:
    """What the page must show now; a reload resumes exactly here. A session whose data were deleted (withdrawn)
    shows its end: phase ``withdrawn``."""
    try:
        return await units.participant(token, _state)
    except NotFound:
        runtimes = services.runtimes
        deleted = await units.run(lambda session: withdrawal.deleted_state(session, runtimes, token, utcnow()))
        if deleted is None:
            raise
        return deleted


@router.post("/p/{token}/withdraw", response_model=StateRead, responses=error_responses(404, 422))
async def withdraw(body: WithdrawCreate, token: Token, services: ServicesDep, units: UnitsDep) -> StateRead:
    """Withdraw from the study (the page's "Withdraw from the study", after its confirmation), at any step: the
    session ends with outcome ``withdrawn`` (its code and redirect, config ``completion``) and the data are kept
    (marked withdrawn and excluded, personal fields erased) or deleted, as the study's ``privacy.withdrawal`` says.
    Answers the page's end state (phase ``withdrawn``).

    Naturally idempotent: a repeat answers the same state, also once the data were deleted (the session link is
    recognised by a keyed hash in the deletion's audit line; the redirect then has no external id).
    """
    runtimes, hub = services.runtimes, services.hub

    def work(session) -> StateRead:
        try:
            ctx = open_participant(session, runtimes, hub, token)
        except NotFound:
            deleted = withdrawal.deleted_state(session, runtimes, token, utcnow())
            if deleted is None:
                raise
            return deleted
        state, _ = withdrawal.withdraw(session, ctx.study, ctx.participant, ctx.runtime, by="participant",
                                       reason=None, now=ctx.now)
        return state
    return await units.run(work)


@router.post("/p/{token}/consent", response_model=StateRead, responses=SESSION_ERRORS)
async def consent(body: ConsentCreate, token: Token, units: UnitsDep, key: IdempotencyKey = None) -> StateRead:
    def act(ctx: ParticipantContext) -> StateRead:
        sessions.consent(ctx.session, ctx.participant, ctx.runtime, agree=body.agree, now=ctx.now)
        return _state(ctx)
    return await units.participant(token, act, key=key, body=body)


@router.post("/p/{token}/instructions/done", response_model=StateRead, responses=SESSION_ERRORS)
async def instructions_done(token: Token, units: UnitsDep, key: IdempotencyKey = None) -> StateRead:
    def act(ctx: ParticipantContext) -> StateRead:
        sessions.finish_instructions(ctx.session, ctx.participant, ctx.runtime, ctx.now)
        return _state(ctx)
    return await units.participant(token, act, key=key, body={"action": "instructions_done"})


@router.post("/p/{token}/practice/done", response_model=StateRead, responses=SESSION_ERRORS)
async def practice_done(token: Token, units: UnitsDep, key: IdempotencyKey = None) -> StateRead:
    """Continue from the page between the practice and the scored trials (phase ``practice_done``), which says
    that the practice is over, that choices count from now on and how long the decision window is."""
    def act(ctx: ParticipantContext) -> StateRead:
        sessions.finish_practice(ctx.session, ctx.participant, ctx.runtime, ctx.now)
        return _state(ctx)
    return await units.participant(token, act, key=key, body={"action": "practice_done"})


@router.post("/p/{token}/trials/start", response_model=StateRead, responses=SESSION_ERRORS)
async def start_trial(body: TrialCreate, token: Token, services: ServicesDep, units: UnitsDep,
                      background: BackgroundTasks) -> StateRead:
    """Start the trial the session is at (naturally idempotent: a repeat returns the same trial).

    A trial that starts presenting is shown in this process's 3D viewer of the session before the answer, which
    says whether the viewer holds its scene with a client connected (``trial.scene_in_viewer``): the page's first
    3D report after drawing can then open the decision window."""
    viewers = services.viewers

    def work(ctx: ParticipantContext) -> tuple[StateRead, int, Target | None]:
        trial = trials.start_trial(ctx.session, ctx.study, ctx.participant, ctx.runtime, body.ref, now=ctx.now)
        # plan the attempt now, not when the window closes
        if trial.stage in (TrialStage.PRESENTING, TrialStage.DECISION):
            planned = trials.planned_trial(ctx.participant, ctx.runtime)
            background.add_task(ctx.planner.prepare_attempt, ctx.runtime.config.seed, ctx.participant.public_id,
                                planned, trials.autonomous_success(ctx.runtime, ctx.participant, planned))
        shown = None
        if trial.stage == TrialStage.PRESENTING:
            shown = viewers.target_of_started(ctx.participant, trial, ctx.runtime)
        return _state(ctx), ctx.participant.id, shown
    state, participant_id, shown = await units.participant(token, work)
    if shown is not None and state.trial is not None:
        state.trial.scene_in_viewer = await viewers.show_started(participant_id, shown)
    return state


@router.post("/p/{token}/trials/intervene", response_model=StateRead, responses=SESSION_ERRORS)
async def intervene(body: InterventionCreate, token: Token, units: UnitsDep, key: IdempotencyKey = None) -> StateRead:
    """Press Intervene during the decision window (409 once the window has closed)."""
    def act(ctx: ParticipantContext) -> StateRead:
        trials.intervene(ctx.session, ctx.participant, ctx.runtime, _trial_at(ctx, body.ref),
                         window_opened_ms=body.window_opened_ms, pressed_ms=body.pressed_ms, now=ctx.now,
                         planner=ctx.planner)
        return _state(ctx)
    return await units.participant(token, act, key=key, body=body)


@router.post("/p/{token}/trials/shown", response_model=StateRead, responses=SESSION_ERRORS)
async def scene_shown(body: SceneShownCreate, token: Token, services: ServicesDep, units: UnitsDep) -> StateRead:
    """The page shows the current trial's scene: its decision window opens now (naturally idempotent: a repeat
    returns the same window).

    A report from a view counts only with the trial's ``scene_stamp``: the page proves that the frame on screen
    was drawn from this trial's scene (see ``SceneShownCreate.scene_stamp``); any other report leaves the trial
    ``presenting`` and the page reports again. Without a report that counts, the window opens
    ``timing.scene_wait_s`` after the trial started, and the trial records that (``window_opened_by``).
    """
    def work(ctx: ParticipantContext) -> StateRead:
        trial = _trial_at(ctx, body.ref)
        if body.view == "text" or body.scene_stamp == presentation.trial_stamp(ctx.participant, ctx.runtime, trial):
            trials.scene_shown(ctx.session, ctx.participant, ctx.runtime, trial, view=SceneView(body.view), now=ctx.now,
                               client_time_ms=body.client_time_ms, planner=ctx.planner)
        state = _state(ctx)
        if body.view == "3d" and state.trial is not None:
            state.trial.scene_in_viewer = presentation.viewer_holds_trial(services.viewers, ctx.participant,
                                                                          ctx.runtime,
                                                                          trial)
        return state
    return await units.participant(token, work)


@router.get("/p/{token}/trials/scene", response_model=TrialSceneRead, responses=SESSION_ERRORS)
async def trial_scene(token: Token, units: UnitsDep) -> TrialSceneRead:
    """The current trial's scene and the robot parked at the shelf, for the 2-D helper view before teleoperation
    (409 between trials)."""
    def work(ctx: ParticipantContext) -> TrialSceneRead:
        trial = trials.current_trial(ctx.session, ctx.participant)
        if trial is None:
            raise Conflict(f"no trial has started; the session is at {sessions.describe(ctx.participant.step)}",
                           step=ctx.participant.step)
        return presentation.scene_for_helper(ctx.participant, ctx.runtime, trial)
    return await units.participant(token, work)


def _trial_at(ctx: ParticipantContext, ref: TrialRef) -> Trial:
    trial = trials.current_trial(ctx.session, ctx.participant)
    if trial is None or trial.ref != ref:
        name = ref.describe()
        past = trials.find_trial(ctx.session, ctx.participant, ref)
        where = f"the session is at {sessions.describe(ctx.participant.step)}"
        if past is not None and past.human_action == "rely":
            raise Conflict(f"the decision window has closed: {name} is over (the robot attempted it); {where}",
                           message=N_("errors.window_closed"), step=ctx.participant.step)
        raise Conflict(f"{name} is not the current trial; {where}", step=ctx.participant.step)
    return trial


@router.post("/p/{token}/answers", response_model=StateRead, responses=SESSION_ERRORS)
async def answer(body: AnswersCreate, token: Token, units: UnitsDep, key: IdempotencyKey = None) -> StateRead:
    """Answer the questionnaire on screen (all items at once): numbers for rating items, text for text items, an
    option's value for choice items; optional items may be left out.

    A page the session is no longer at (a stale tab's) is refused with 409; its ``answered_elsewhere`` says
    whether that page was already answered (in another tab or window). A page may end the session: an eligibility
    question answered with a screen-out option, or failed attention checks reaching the study's ``attention``
    rule, give phase ``screened_out`` with that outcome's completion code and redirect.
    """
    def act(ctx: ParticipantContext) -> StateRead:
        surveys.submit(ctx.session, ctx.participant, ctx.runtime, questionnaire_id=body.questionnaire,
                       answers=body.answers, now=ctx.now, context=body.context)
        return _state(ctx)
    return await units.participant(token, act, key=key, body=body)


@router.put("/p/{token}/answers/draft", response_model=DraftRead, responses=error_responses(404, 409, 410, 422))
async def save_draft(body: DraftUpdate, token: Token, units: UnitsDep) -> DraftRead:
    """Keep the answers given so far on the questionnaire page on screen (replaces the previous draft), so a
    reload restores them (the state's ``questionnaire.draft``); 409 when the session is not at that page."""
    def work(ctx: ParticipantContext) -> DraftRead:
        return DraftRead(**surveys.save_draft(ctx.session, ctx.participant, ctx.runtime,
                                              questionnaire_id=body.questionnaire, context=body.context,
                                              answers=body.answers))
    return await units.participant(token, work)


@router.post("/p/{token}/heartbeat", response_model=OkRead, responses=error_responses(404, 410))
async def heartbeat(body: HeartbeatUpdate, token: Token, units: UnitsDep) -> OkRead:
    """The page is still open (410 once the session was abandoned or withdrawn: the page then reloads its state)."""
    def work(ctx: ParticipantContext) -> OkRead:
        sessions.require_not_ended(ctx.participant)
        return OkRead()
    return await units.participant(token, work)


@router.post("/p/{token}/events", response_model=OkRead, responses=error_responses(404, 410, 413, 429))
async def events(body: EventsCreate, token: Token, services: ServicesDep, units: UnitsDep) -> OkRead:
    """Client-side events (camera changes, key presses, blur/focus), appended to the log.

    Budgeted per session (``server.services.events``): past the request rate 429 with Retry-After; past the
    session's budget of stored events or payload bytes 413 with code ``event_budget_spent`` (the batch is not
    stored; the study goes on, nothing in it depends on events).
    """
    budget = services.event_budget
    budget.take_request(token)
    payload_bytes = sum(len(strict_json.dumps(event.payload)) for event in body.events)

    def work(ctx: ParticipantContext) -> OkRead:
        sessions.require_not_ended(ctx.participant)
        budget.spend(ctx.session, ctx.participant.id, len(body.events), payload_bytes)
        for event in body.events:
            log_client_event(ctx.session, ctx.study.id, ctx.participant.id, event.kind,
                             client_time_ms=event.client_time_ms, payload=event.payload)
        return OkRead()
    return await units.participant(token, work)
