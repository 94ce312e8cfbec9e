"""The participant's state as the page renders it (``GET /api/p/{token}/state``)."""

from __future__ import annotations

from datetime import datetime
from typing import NamedTuple

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig, block_label
from experiment.engine import StudyRuntime
from experiment.events import EventKind
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
from experiment.task import RobotAction
from experiment.world.trial import trial_scene_stamp, trial_target_parts
from server.i18n import Translator
from server.models import Event, Participant, Study, Trial
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
    WithdrawalRead,
)
from server.services import wording
from server.services.surveys import current_page, draft_answers
from server.services.trials import PRACTICE_BLOCK, current_trial, teleop_time_limit_s


def build_state(session: Session, study: Study, participant: Participant, runtime: StudyRuntime, *,
                now: datetime) -> StateRead:
    config, step = runtime.config, participant.step
    ended = participant.status in (ParticipantStatus.ABANDONED, ParticipantStatus.WITHDRAWN)
    timing = config.timing
    tr = wording.translator(participant.language)
    texts = wording.participant_texts(config, participant.language, tr)
    state = StateRead(
        status=participant.status, phase=participant.status if ended else step.phase, step=step,
        score=participant.score, progress=runtime.progress(step, participant.block_order),
        study_title=texts.title, server_time=now, preview=participant.preview, language=participant.language,
        timing={"decision_window_s": timing.decision_window_s, "animation_speed": timing.animation_speed,
                "teleop_time_limit_s": timing.teleop_time_limit_s, "next_item_pause_s": timing.next_item_pause_s},
        teleop_time_limit_s=timing.teleop_time_limit_s,
        tutorial=TutorialRead(max_tries=config.practice.tutorial.max_tries,
                              time_limit_s=config.practice.tutorial.time_limit_s)
        if config.practice.enabled and config.practice.tutorial.enabled else None,
    )
    _show_step(state, session, participant, runtime, now, Wording(tr, texts))
    state.last_trial = _last_trial(session, participant, config)
    state.withdrawal = withdrawal_read(session, participant, config)
    return state


class Wording(NamedTuple):
    """The participant's translator and the study's texts in their language."""

    tr: Translator
    texts: wording.StudyTexts


def _show_step(state: StateRead, session: Session, participant: Participant, runtime: StudyRuntime,
               now: datetime, words: Wording) -> None:
    """What the page shows at the participant's step: nothing of it once they withdrew or went idle."""
    config, step, texts = runtime.config, participant.step, words.texts
    match participant.status, step:
        case ParticipantStatus.WITHDRAWN, _:
            state.completion = _completion(participant, runtime)  # the withdrawn code, when the study has one
        case ParticipantStatus.ABANDONED, _:
            state.completion = _completion(participant, runtime)  # the timed-out code, when the study has one
        case _, ConsentStep():
            state.duration, state.text = _duration(runtime, words.tr), texts.consent
        case _, InstructionsStep():
            state.duration, state.text = _duration(runtime, words.tr), texts.instructions
            state.video_url = config.texts.instructions_video_url
        case _, QuestionnaireStep() | ShelfSurveyStep():
            state.questionnaire = _questionnaire(runtime, participant, words)
        case _, PracticeDoneStep():
            state.scored_part = _scored_part(config, participant, words)
        case _, PracticeStep() | TrialStep():
            trial = current_trial(session, participant)
            if trial is None:
                state.ready_to_start = step.trial_ref._asdict()
            else:
                state.trial = _trial_view(trial, runtime, participant, now, words)
        case _, DebriefStep():
            state.text, state.completion = texts.debrief, _completion(participant, runtime)
            state.final_score = participant.score if config.plays_for_points else None
        case _, DeclinedStep() | ScreenedOutStep():
            state.completion = _completion(participant, runtime)


def _duration(runtime: StudyRuntime, tr: Translator) -> DurationRead:
    estimate = runtime.duration
    return DurationRead(low_minutes=estimate.low_minutes, high_minutes=estimate.high_minutes,
                        text=wording.duration_text(estimate.low_minutes, estimate.high_minutes, tr))


def _trial_view(trial: Trial, runtime: StudyRuntime, participant: Participant, now: datetime,
                words: Wording) -> TrialRead:
    config, tr = runtime.config, words.tr
    expected = _expected_human_action(config, trial)
    if trial.practice:
        n_trials, label = len(config.practice.trials), tr.t("trial.practice_label")
        hint: str | None = tr.t(wording.PRACTICE_HINTS[expected if trial.robot_action == RobotAction.AUTO else None])
    else:
        block = config.block(trial.block_name)
        n_trials, label, hint = block.schedule.n_trials, block_label(words.texts.block_label, trial.block), None
    parts = trial_target_parts(config.seed, participant.public_id, trial.block_name, trial.trial, trial.complexity)
    target = wording.target_description(parts, tr)
    teleop = trial.stage == TrialStage.TELEOP
    return TrialRead(
        practice=trial.practice, block=trial.block, block_label=label, trial=trial.trial, n_trials=n_trials,
        shelf=trial.shelf, complexity=trial.complexity, robot_action=trial.robot_action,
        message=wording.robot_message(trial.robot_action, target, tr), target=target, stage=trial.stage,
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


def _scored_part(config: StudyConfig, participant: Participant, words: Wording) -> ScoredPartRead:
    n_blocks = len(participant.block_order or config.blocks)
    return ScoredPartRead(decision_window_s=config.timing.decision_window_s, plays_for_points=config.plays_for_points,
                          robots=[block_label(words.texts.block_label, i + 1) for i in range(n_blocks)],
                          n_trials=sum(b.schedule.n_trials for b in config.blocks))


def _questionnaire(runtime: StudyRuntime, participant: Participant, words: Wording) -> QuestionnaireRead:
    page = current_page(participant, runtime)
    assert page is not None
    q = runtime.config.questionnaire(page.questionnaire).in_language(participant.language)
    robot = page_robot(runtime.config, page, words.texts.block_label)
    if robot is not None:
        q = q.naming(robot)
    return QuestionnaireRead(id=q.id, title=q.heading, instructions=q.instructions, context=page.context,
                             language=q.language,
                             about=_about(runtime.config, page, words),
                             scale=ScaleRead(**q.scale.model_dump()) if q.scale else None,
                             items=[_item_read(i) for i in q.items],
                             draft=draft_answers(participant, page.questionnaire, page.context))


def _item_read(item: Item) -> ItemRead:
    """An item as the page shows it: never its instructed response or screen-out options."""
    choice = item.kind == "choice"
    return ItemRead(id=item.id, text=item.text, kind=item.kind, required=item.required,
                    max_length=item.text_limit if item.kind == "text" else None,
                    options=[OptionRead(value=o.value, label=o.label) for o in item.options or []] if choice else None)


def page_robot(config: StudyConfig, page: QuestionnairePage, pattern: str | None = None) -> str | None:
    """The robot (its block's position label, "Robot A"; ``pattern``: the label in the participant's language) a
    questionnaire page belongs to: its block's; at the end of a study of one block, that block's; None before the
    blocks and at the end of a study of several."""
    pattern = pattern or str(config.texts.in_language(config.default_language, config.default_language).block_label)
    if page.block is not None:
        return block_label(pattern, page.block)
    if page.context == END_OF_STUDY and len(config.blocks) == 1:
        return block_label(pattern, 1)
    return None


def _about(config: StudyConfig, page: QuestionnairePage, words: Wording) -> str | None:
    """The line above a questionnaire page saying which robot (block, by its position label) or shelf it is about:
    none before the blocks, none at the end of a study of several blocks, and none for questions that are not
    about the robot (``about_robot``: demographics, comments) but where they follow a shelf."""
    robot = page_robot(config, page, words.texts.block_label)
    if robot is None:
        return None
    if page.shelf is None and not config.questionnaire(page.questionnaire).about_robot:
        return None
    # at the end of a study of one block (page.block None): "the robot you worked with"
    return wording.about_line(robot, page.shelf, just_finished=page.block is not None, tr=words.tr)


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


_WITHDRAWN_BY = (select(Event.payload).where(Event.participant_id == bindparam("participant_id"),
                                               Event.kind == EventKind.WITHDRAWN)
                 .order_by(Event.id.desc()).limit(1))


def withdrawal_read(session: Session, participant: Participant, config: StudyConfig) -> WithdrawalRead:
    """What withdrawing does in the participant's study (config ``privacy``; ``server.services.withdrawal``), and
    who withdrew once they did (sessions withdrawn before the event existed: the researcher, the only one who could)."""
    by = None
    if participant.status == ParticipantStatus.WITHDRAWN:
        payload = session.scalar(_WITHDRAWN_BY, {"participant_id": participant.id})
        by = (payload or {}).get("by", "researcher")
    return WithdrawalRead(data=config.privacy.withdrawal, text=config.privacy.withdrawal_text, by=by)


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
