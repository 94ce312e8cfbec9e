"""The participant's steps: their JSON (stored with the participant, shown by the API) and what each says."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from experiment.flow import (DEBRIEF, PracticeStep, QuestionnairePage, QuestionnaireStep, ShelfSurveyStep, TrialRef,
                             TrialStep, all_steps, parse_step, progress)
from experiment.templates import demo, policy_evaluation

#: Each kind of step as sessions stored it before steps were models (key order as the API showed it).
STORED = [
    '{"phase": "consent"}',
    '{"phase": "instructions"}',
    '{"phase": "practice", "index": 0}',
    '{"phase": "questionnaire", "context": "before", "questionnaire": "schaefer_14"}',
    '{"phase": "trial", "block": 1, "trial": 3}',
    '{"phase": "shelf_survey", "block": 1, "shelf": 1, "trial": 3}',
    '{"phase": "questionnaire", "context": "after:2", "block": 2, "questionnaire": "schaefer_14"}',
    '{"phase": "debrief"}',
    '{"phase": "declined"}',
]


@pytest.mark.parametrize("stored", STORED)
def test_a_stored_step_loads_and_is_written_back_the_same(stored):
    step = parse_step(json.loads(stored))
    assert json.dumps(step.model_dump()) == stored
    assert step.model_dump_json() == stored.replace(", ", ",").replace(": ", ":")


@pytest.mark.parametrize("stored", [{"phase": "intro"}, {"phase": "trial", "block": 1}, {"phase": "debrief", "x": 1}])
def test_a_step_of_another_shape_is_refused(stored):
    with pytest.raises(ValidationError):
        parse_step(stored)


def test_each_step_names_its_trial_and_its_questionnaire_page():
    config = demo()
    assert PracticeStep(index=0).trial_ref == TrialRef(practice=True, block=0, trial=1)
    assert TrialStep(block=2, trial=5).trial_ref == TrialRef(practice=False, block=2, trial=5)
    shelf = ShelfSurveyStep(block=2, shelf=3, trial=9)
    assert shelf.trial_ref is None and shelf.block_position == 2
    assert shelf.questionnaire_page(config) == QuestionnairePage(config.shelf_questionnaire, "shelf:2:3", 2, 3)
    before = QuestionnaireStep(context="before", questionnaire="schaefer_14")
    assert before.block_position is None and before.questionnaire_context == "before"
    assert before.questionnaire_page(config) == QuestionnairePage("schaefer_14", "before")
    assert DEBRIEF.trial_ref is None and DEBRIEF.questionnaire_page(config) is None


def test_the_path_goes_through_every_kind_of_step_once_in_order():
    config = policy_evaluation()
    order = [block.name for block in config.blocks]
    steps = all_steps(config, order)
    assert {step.phase for step in steps} == {"consent", "instructions", "practice", "questionnaire", "trial",
                                              "shelf_survey", "debrief"}
    assert [progress(config, step, order) for step in steps] == [i / (len(steps) - 1) for i in range(len(steps))]
    assert all(parse_step(step.model_dump()) == step for step in steps)


def test_a_runtime_gives_each_order_the_progress_the_flow_gives():
    """``StudyRuntime.progress`` lists each block order's steps once; it must say what ``progress`` says, for every
    order (a reversed one too), for the study's order when none is drawn yet, and for steps off the path."""
    from experiment.engine import StudyRuntime
    from experiment.flow import DeclinedStep, first_step
    config = policy_evaluation()
    runtime = StudyRuntime(config)
    names = [block.name for block in config.blocks]
    for order in (names, names[::-1], None):
        steps = all_steps(config, order or names)
        assert [runtime.progress(step, order) for step in steps] == [progress(config, step, order) for step in steps]
    assert runtime.progress(DEBRIEF, names[::-1]) == 1.0
    assert runtime.progress(DeclinedStep(), names) == progress(config, DeclinedStep(), names) == 1.0
    assert runtime.progress(first_step(), None) == 0.0
