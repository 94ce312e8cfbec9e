"""The participant's state as the page renders it (``GET /api/p/{token}/state``)."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig, block_label
from experiment.engine import StudyRuntime
from experiment.flow import (
    END_OF_STUDY,
    ConsentStep,
    DebriefStep,
    DeclinedStep,
    InstructionsStep,
    ParticipantStatus,
    PracticeDoneStep,
    PracticeStep,
    QuestionnairePage,
    QuestionnaireStep,
    ScreenedOutStep,
    ShelfSurveyStep,
    TrialStage,
    TrialStep,
)
from experiment.outcomes import outcome_of_status, redirect_link
from experiment.questionnaires import Item
from experiment.task import HumanAction, RobotAction
from experiment.world.trial import trial_scene_stamp, trial_target
from server.models import Participant, Study, Trial
from server.schemas import (
    CompletionRead,
    DurationRead,
    ItemRead,
    OptionRead,
    QuestionnaireRead,
    ScaleRead,
    ScoredPartRead,
    StateRead,
    TrialRead,
    TrialResultRead,
    TutorialRead,
    TutorialTryRead,
)
from server.services.surveys import current_page, draft_answers
from server.services.trials import PRACTICE_BLOCK, current_trial, teleop_time_limit_s

MESSAGES = {
    RobotAction.AUTO: "I will collect {target} myself.",
    RobotAction.ASK: "I need your help with {target}.",
}
PRACTICE_HINTS: dict[str | None, str] = {  # keyed by HumanAction (a str) or None
    HumanAction.RELY: "Practice: let the robot try this one. Do not press Intervene.",
    HumanAction.INTERVENE: "Practice: press Intervene before the countdown ends, then collect the item yourself.",
    None: "Practice: the robot asks for help. Move the arm to the item, close the gripper, then drop it in the bin.",
}


def build_state(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, *,
                now: datetime) -> StateRead:
    config, step = runtime.config, participant.step
    ended = participant.status in (ParticipantStatus.ABANDONED, ParticipantStatus.WITHDRAWN)
    timing = config.timing
    state = StateRead(
        status=participant.status, phase=participant.status if ended else step.phase, step=step,
        score=participant.score, progress=runtime.progress(step, participant.block_order),
        study_title=config.texts.title, server_time=now, preview=participant.preview, language=participant.language,
        timing={"decision_window_s": timing.decision_window_s, "animation_speed": timing.animation_speed,
                "teleop_time_limit_s": timing.teleop_time_limit_s, "next_item_pause_s": timing.next_item_pause_s},
        teleop_time_limit_s=timing.teleop_time_limit_s,
        tutorial=TutorialRead(max_tries=config.practice.tutorial.max_tries,
                              time_limit_s=config.practice.tutorial.time_limit_s)
        if config.practice.enabled and config.practice.tutorial.enabled else None,
    )
    _show_step(state, session, participant, runtime, now)
    state.last_trial = _last_trial(session, participant, config)
    return state


def _show_step(state: StateRead, session: Session, participant: Participant, runtime: StudyRuntime,
               now: datetime) -> None:
    """What the page shows at the participant's step: nothing of it once they withdrew or went idle."""
    config, step = runtime.config, participant.step
    match participant.status, step:
        case ParticipantStatus.WITHDRAWN, _:
            pass
        case ParticipantStatus.ABANDONED, _:
            state.completion = _completion(participant, runtime)  # the timed-out code, when the study has one
        case _, ConsentStep():
            state.duration, state.text = _duration(runtime), config.texts.consent
        case _, InstructionsStep():
            state.duration, state.text = _duration(runtime), config.texts.instructions
            state.video_url = config.texts.instructions_video_url
        case _, QuestionnaireStep() | ShelfSurveyStep():
            state.questionnaire = _questionnaire(runtime, participant)
        case _, PracticeDoneStep():
            state.scored_part = _scored_part(config, participant)
        case _, PracticeStep() | TrialStep():
            trial = current_trial(session, participant)
            if trial is None:
                state.ready_to_start = step.trial_ref._asdict()
            else:
                state.trial = _trial_view(trial, runtime, participant, now)
        case _, DebriefStep():
            state.text, state.completion = config.texts.debrief, _completion(participant, runtime)
            state.final_score = participant.score if config.plays_for_points else None
        case _, DeclinedStep() | ScreenedOutStep():
            state.completion = _completion(participant, runtime)


def _duration(runtime: StudyRuntime) -> DurationRead:
    estimate = runtime.duration
    return DurationRead(low_minutes=estimate.low_minutes, high_minutes=estimate.high_minutes, text=estimate.text)


def _trial_view(trial: Trial, runtime: StudyRuntime, participant: Participant, now: datetime) -> TrialRead:
    config = runtime.config
    expected = _expected_human_action(config, trial)
    if trial.practice:
        n_trials, label = len(config.practice.trials), "Practice"
        hint = PRACTICE_HINTS[expected if trial.robot_action == RobotAction.AUTO else None]
    else:
        block = config.block(trial.block_name)
        n_trials, label, hint = block.schedule.n_trials, block_label(config.texts.block_label, trial.block), None
    target = trial_target(config.seed, participant.public_id, trial.block_name, trial.trial, trial.complexity)
    teleop = trial.stage == TrialStage.TELEOP
    return TrialRead(
        practice=trial.practice, block=trial.block, block_label=label, trial=trial.trial, n_trials=n_trials,
        shelf=trial.shelf, complexity=trial.complexity, robot_action=trial.robot_action,
        message=MESSAGES[trial.robot_action].format(target=target), target=target, stage=trial.stage,
        human_action=trial.human_action,
        decision_window_s=config.timing.decision_window_s if trial.robot_action == RobotAction.AUTO else None,
        decision_ms_left=_ms_left(trial.decision_deadline_at, now) if trial.stage == TrialStage.DECISION else None,
        scene_wait_ms_left=_ms_left(trial.scene_deadline_at, now) if trial.stage == TrialStage.PRESENTING else None,
        scene_stamp=trial_scene_stamp(config.seed, participant.public_id, trial.block_name, trial.trial,
                                      trial.complexity)
        if trial.stage in (TrialStage.PRESENTING, TrialStage.DECISION) else None,
        attempt_ms_left=_ms_left(trial.attempt_end_at, now) if trial.stage == TrialStage.ATTEMPT else None,
        teleop_ms_left=_ms_left(trial.teleop_deadline_at, now) if teleop else None,
        teleop_time_limit_s=teleop_time_limit_s(config, trial) if teleop else None,
        tutorial=TutorialTryRead(try_number=trial.teleop_tries or 1, max_tries=config.practice.tutorial.max_tries)
        if teleop and trial.tutorial else None,
        hint=hint, expected_human_action=expected,
    )


def _expected_human_action(config: StudyConfig, trial: Trial) -> str | None:
    """What a practice trial asks the participant to do when the robot tries by itself (None: no instruction)."""
    if not trial.practice or trial.robot_action != RobotAction.AUTO or trial.trial > len(config.practice.trials):
        return None
    return config.practice.trials[trial.trial - 1].human_action_hint


def _ms_left(deadline: datetime | None, now: datetime) -> float | None:
    return None if deadline is None else max(0.0, (deadline - now).total_seconds() * 1000)


def _scored_part(config: StudyConfig, participant: Participant) -> ScoredPartRead:
    n_blocks = len(participant.block_order or config.blocks)
    return ScoredPartRead(decision_window_s=config.timing.decision_window_s, plays_for_points=config.plays_for_points,
                          robots=[block_label(config.texts.block_label, i + 1) for i in range(n_blocks)],
                          n_trials=sum(b.schedule.n_trials for b in config.blocks))


def _questionnaire(runtime: StudyRuntime, participant: Participant) -> QuestionnaireRead:
    page = current_page(participant, runtime)
    assert page is not None
    q = runtime.config.questionnaire(page.questionnaire).in_language(participant.language)
    robot = page_robot(runtime.config, page)
    if robot is not None:
        q = q.naming(robot)
    return QuestionnaireRead(id=q.id, title=q.heading, instructions=q.instructions, context=page.context,
                             language=q.language,
                             about=_about(runtime.config, page),
                             scale=ScaleRead(**q.scale.model_dump()) if q.scale else None,
                             items=[_item_read(i) for i in q.items],
                             draft=draft_answers(participant, page.questionnaire, page.context))


def _item_read(item: Item) -> ItemRead:
    """An item as the page shows it: never its instructed response or screen-out options."""
    choice = item.kind == "choice"
    return ItemRead(id=item.id, text=item.text, kind=item.kind, required=item.required,
                    max_length=item.text_limit if item.kind == "text" else None,
                    options=[OptionRead(value=o.value, label=o.label) for o in item.options or []] if choice else None)


def page_robot(config: StudyConfig, page: QuestionnairePage) -> str | None:
    """The robot (its block's position label, "Robot A") a questionnaire page belongs to: its block's; at the end
    of a study of one block, that block's; None before the blocks and at the end of a study of several."""
    if page.block is not None:
        return block_label(config.texts.block_label, page.block)
    if page.context == END_OF_STUDY and len(config.blocks) == 1:
        return block_label(config.texts.block_label, 1)
    return None


def _about(config: StudyConfig, page: QuestionnairePage) -> str | None:
    """The line above a questionnaire page saying which robot (block, by its position label) or shelf it is about:
    none before the blocks, none at the end of a study of several blocks, and none for questions that are not
    about the robot (``about_robot``: demographics, comments) but where they follow a shelf."""
    robot = page_robot(config, page)
    if robot is None:
        return None
    if page.shelf is not None:
        return f"You have just finished shelf {page.shelf} with {robot}."
    if not config.questionnaire(page.questionnaire).about_robot:
        return None
    if page.block is None:  # at the end of a study of one block
        return f"These questions are about {robot}, the robot you worked with."
    return f"These questions are about {robot}, the robot you have just worked with."


def _completion(participant: Participant, runtime: StudyRuntime) -> CompletionRead | None:
    """The code the session ended with and the outcome's redirect (experiment.outcomes); None without either."""
    outcome = outcome_of_status(participant.status)
    if outcome is None:
        return None
    code = participant.completion_code
    url = redirect_link(runtime.config.completion.redirect_template(outcome), outcome=outcome, code=code,
                        external_id=participant.external_id)
    if code is None and url is None:
        return None
    return CompletionRead(outcome=outcome, code=code, redirect_url=url,
                          compensation=participant.compensation if runtime.config.compensation.defined else None,
                          currency=runtime.config.compensation.currency)


_LAST_DONE_TRIAL = (select(Trial).where(Trial.participant_id == bindparam("participant_id"),
                                        Trial.stage == TrialStage.DONE)
                    .order_by(Trial.completed_at.desc(), Trial.id.desc()).limit(1))


def _last_trial(session: Session, participant: Participant, config: StudyConfig) -> TrialResultRead | None:
    trial = session.scalar(_LAST_DONE_TRIAL, {"participant_id": participant.id})
    if trial is None:
        return None
    expected = _expected_human_action(config, trial)
    return TrialResultRead(practice=trial.practice, block=trial.block, trial=trial.trial, complexity=trial.complexity,
                           robot_action=trial.robot_action, human_action=trial.human_action or "",
                           outcome=trial.outcome or "none", experience=trial.experience or "",
                           reward=trial.reward or 0.0, score=trial.score or 0.0, teleop_success=trial.teleop_success,
                           failure_mode=trial.failure_mode, expected_human_action=expected,
                           hint_followed=None if expected is None else trial.human_action == expected)


__all__ = ["build_state", "PRACTICE_BLOCK"]
