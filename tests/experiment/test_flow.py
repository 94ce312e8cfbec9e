"""The participant's steps: their JSON (stored with the participant, shown by the API) and what each says."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from experiment.config import PracticeConfig, StudyConfig, validate_document
from experiment.flow import (
    DEBRIEF,
    PRACTICE_DONE,
    PracticeStep,
    QuestionnairePage,
    QuestionnaireStep,
    ShelfSurveyStep,
    TrialRef,
    TrialStep,
    all_steps,
    next_step,
    parse_step,
    progress,
)
from experiment.templates import demo, model_estimation, policy_evaluation

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
    '{"phase": "practice_done"}',
    '{"phase": "questionnaire", "context": "end", "questionnaire": "demographics"}',
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
    assert {step.phase for step in steps} == {"consent", "instructions", "practice", "practice_done", "questionnaire",
                                              "trial", "shelf_survey", "debrief"}
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


# --- issue 37: a step between practice and the scored trials; questionnaires at the end of the study ---------

def test_practice_ends_with_its_own_step_before_anything_scored():
    config = policy_evaluation()
    order = [block.name for block in config.blocks]
    steps = all_steps(config, order)
    done = steps.index(PRACTICE_DONE)
    assert steps[done - 1] == PracticeStep(index=len(config.practice.trials) - 1)
    assert not any(step.trial_ref and not step.trial_ref.practice for step in steps[:done])  # nothing scored before
    assert steps[done + 1] == QuestionnaireStep(context="before", questionnaire="schaefer_14")
    assert next_step(config, PRACTICE_DONE) == steps[done + 1]  # no block order needed yet
    assert steps.count(PRACTICE_DONE) == 1
    no_practice = config.model_copy(update={"practice": PracticeConfig(enabled=False)})
    assert PRACTICE_DONE not in all_steps(no_practice, order)  # no practice, nothing to end


def end_config(base: StudyConfig, *ids: str) -> StudyConfig:
    return validate_document(base.model_dump(mode="json") | {"questionnaires_end": list(ids)})


@pytest.mark.parametrize("order", [["trust_aware", "trust_agnostic"], ["trust_agnostic", "trust_aware"]])
def test_questionnaires_at_the_end_come_after_every_block_whatever_the_order(order):
    config = end_config(policy_evaluation(), "demographics", "comments")
    steps = all_steps(config, order)
    assert steps[-3:] == [QuestionnaireStep(context="end", questionnaire="demographics"),
                          QuestionnaireStep(context="end", questionnaire="comments"), DEBRIEF]
    last_trial = max(i for i, step in enumerate(steps) if isinstance(step, TrialStep))
    assert steps[last_trial].block == 2 and steps[last_trial + 2] == QuestionnaireStep(
        context="after:2", block=2, questionnaire="schaefer_14")  # the paper's Schaefer after each block stays
    end = steps[-3]
    assert end.block_position is None and end.questionnaire_page(config) == QuestionnairePage("demographics", "end")
    assert [progress(config, step, order) for step in steps] == [i / (len(steps) - 1) for i in range(len(steps))]
    # the built-ins named by id are added to the study's questionnaires (the stored document holds what is asked)
    assert {"demographics", "comments"} <= {q.id for q in config.questionnaires}


def test_a_questionnaire_placed_after_one_block_lands_mid_study_for_the_other_order():
    """Why the end placement exists: after block X is the end only for the orders where X comes last."""
    base = policy_evaluation().model_dump(mode="json")
    base["blocks"][1]["questionnaires_after"] = ["schaefer_14", "demographics"]
    config = validate_document(base)
    for order, last in ((["trust_aware", "trust_agnostic"], True), (["trust_agnostic", "trust_aware"], False)):
        steps = all_steps(config, order)
        demographics = next(i for i, s in enumerate(steps) if getattr(s, "questionnaire", None) == "demographics")
        assert (steps[demographics + 1] == DEBRIEF) is last


@pytest.mark.parametrize("field, value, reason", [
    ("questionnaires_end", ["demographics", "demographics"], "repeated: demographics"),
    ("questionnaires_before", ["schaefer_14", "schaefer_14"], "repeated: schaefer_14"),
    ("questionnaires_end", ["no_such_questionnaire"], "unknown questionnaire id 'no_such_questionnaire'"),
    ("questionnaires_end", ["shelf_trust_reliance_named"], "names the robot"),
    ("questionnaires_before", ["shelf_trust_reliance_named"], "names the robot"),
])
def test_a_placement_that_cannot_work_is_refused_with_its_reason(field, value, reason):
    with pytest.raises(ValidationError, match=reason):
        validate_document(demo().model_dump(mode="json") | {field: value})


def test_a_study_of_one_block_may_ask_about_its_robot_at_the_end():
    config = end_config(model_estimation(), "shelf_trust_reliance_named", "demographics")
    assert all_steps(config, ["estimation"])[-3].context == "end"
