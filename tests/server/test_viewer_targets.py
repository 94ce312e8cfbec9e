"""What a session's 3D view shows (server.viewer.targets), decided from plain rows: no database, no viser."""

import pytest

from experiment.engine import StudyRuntime
from experiment.flow import (
    ConsentStep,
    DebriefStep,
    InstructionsStep,
    ParticipantStatus,
    PracticeStep,
    QuestionnaireStep,
    ShelfSurveyStep,
    TrialRef,
    TrialStage,
    TrialStep,
)
from experiment.templates import demo_fast
from experiment.world.trial import trial_scene
from server.models import Participant, Trial
from server.services.trials import PRACTICE_BLOCK
from server.viewer.targets import Target, Targets, step_scene

PUBLIC_ID = "P-viewer-targets"


@pytest.fixture(scope="module")
def runtime() -> StudyRuntime:
    return StudyRuntime(demo_fast())


def participant(step, *, block_order=None, status=ParticipantStatus.ACTIVE) -> Participant:
    return Participant(id=7, public_id=PUBLIC_ID, study_version_id=3, status=status, step=step,
                       block_order=block_order)


def open_trial(block: int, trial: int, block_name: str, complexity: str, stage: TrialStage) -> Trial:
    return Trial(participant_id=7, practice=block == 0, block=block, block_name=block_name, trial=trial,
                 complexity=complexity, stage=stage)


def target(runtime: StudyRuntime, someone: Participant, *rows: Trial) -> Target:
    trials = {(row.participant_id, row.ref): row for row in rows}
    return Targets().target(someone, trials, lambda: runtime)


def same_scene(scene, expected) -> bool:
    return (scene.seed, scene.complexity, scene.target_slot) == (expected.seed, expected.complexity,
                                                                 expected.target_slot)


def test_a_practice_step_shows_its_practice_trial_before_it_starts(runtime):
    shown = target(runtime, participant(PracticeStep(index=1)))
    complexity = runtime.config.practice.trials[1].complexity
    assert shown.active and shown.stage is None
    assert same_scene(shown.scene, trial_scene(runtime.config.seed, PUBLIC_ID, PRACTICE_BLOCK, 2, complexity))


def test_a_trial_step_shows_its_open_trial_with_its_stage(runtime):
    order = [block.name for block in runtime.config.blocks]
    row = open_trial(2, 3, order[1], "high", TrialStage.DECISION)
    shown = target(runtime, participant(TrialStep(block=2, trial=3), block_order=order), row)
    assert shown.active and shown.stage == TrialStage.DECISION
    assert same_scene(shown.scene, trial_scene(runtime.config.seed, PUBLIC_ID, order[1], 3, "high"))


def test_a_trial_step_without_its_row_shows_the_planned_trial(runtime):
    order = [block.name for block in runtime.config.blocks]
    planned = next(t for t in runtime.plan(PUBLIC_ID, order) if (t.block, t.trial) == (1, 2))
    shown = target(runtime, participant(TrialStep(block=1, trial=2), block_order=order))
    assert shown.active and shown.stage is None
    assert same_scene(shown.scene, trial_scene(runtime.config.seed, PUBLIC_ID, planned.block_name, 2,
                                               planned.complexity))


def test_a_trial_step_before_the_block_order_is_drawn_keeps_the_scene(runtime):
    someone = participant(TrialStep(block=1, trial=1))
    assert step_scene(someone, None, runtime) is None
    assert target(runtime, someone) == Target(True)


@pytest.mark.parametrize("step", [ConsentStep(), InstructionsStep(), DebriefStep(),
                                  QuestionnaireStep(context="before", questionnaire="trust"),
                                  ShelfSurveyStep(block=1, shelf=1, trial=4)])
def test_steps_that_run_no_trial_keep_the_scene(runtime, step):
    assert target(runtime, participant(step, block_order=["a", "b"])) == Target(True)


@pytest.mark.parametrize("status", [ParticipantStatus.COMPLETED, ParticipantStatus.DECLINED])
def test_an_inactive_session_shows_nothing(runtime, status):
    assert target(runtime, participant(PracticeStep(index=0), status=status)) == Target(False)


def test_a_steps_scene_is_worked_out_once(runtime):
    """The poll asks for the study's runtime (a query) only when a session's step changes."""
    targets, asked = Targets(), []

    def runtime_of() -> StudyRuntime:
        asked.append(1)
        return runtime

    someone = participant(PracticeStep(index=0))
    first = targets.target(someone, {}, runtime_of)
    row = open_trial(0, 1, PRACTICE_BLOCK, runtime.config.practice.trials[0].complexity, TrialStage.ATTEMPT)
    assert targets.target(someone, {(7, TrialRef(True, 0, 1)): row}, runtime_of) == Target(True, first.scene,
                                                                                TrialStage.ATTEMPT)
    assert len(asked) == 1
    targets.target(participant(PracticeStep(index=1)), {}, runtime_of)
    assert len(asked) == 2
