import json

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from experiment import defaults
from experiment.instruments import BUILTIN_QUESTIONNAIRES, SCHAEFER_14, SHELF_TRUST_RELIANCE
from experiment.questionnaires import AnswerError, Item, Questionnaire, Scale, reverse_code, score, validate_answers

MID = (defaults.SCHAEFER_SCALE_MIN + defaults.SCHAEFER_SCALE_MAX) / 2
schaefer_values = st.sampled_from(SCHAEFER_14.scale.points())
schaefer_answers = st.fixed_dictionaries({i: schaefer_values for i in SCHAEFER_14.item_ids})


def likert(**overrides):
    doc = {"id": "mine", "title": "Mine", "instructions": "Rate.", "scale": {"min": 1, "max": 7, "step": 1},
           "items": [{"id": "a", "text": "A"}, {"id": "b", "text": "B", "reverse_coded": True}]}
    return Questionnaire.model_validate(doc | overrides)


# --- built-ins --------------------------------------------------------------------------

def test_shelf_questionnaire():
    q = SHELF_TRUST_RELIANCE
    assert q.item_ids == ["trust", "reliance"]
    assert q.item("trust").text == "To what extent do you trust the automation in this scenario?"
    assert q.item("reliance").text == "To what extent did you rely on the automation in this scenario?"
    assert q.scale.points() == list(range(defaults.SHELF_SCALE_MIN, defaults.SHELF_SCALE_MAX + 1))
    assert q.scale.anchors == {defaults.SHELF_SCALE_MIN: "Not at all", defaults.SHELF_SCALE_MAX: "Completely"}
    assert validate_answers(q, {"trust": 7, "reliance": 10}) == {"trust": 7.0, "reliance": 10.0}
    with pytest.raises(ValueError, match="no score"):
        score(q, {"trust": 7, "reliance": 10})


def test_schaefer_items():
    q = SCHAEFER_14
    assert len(q.items) == 14
    assert q.item_ids[:3] == ["function_successfully", "act_consistently", "reliable"]
    assert q.item_ids[-1] == "provide_feedback"
    assert [i.id for i in q.items if i.reverse_coded] == ["have_errors", "unresponsive", "malfunction"]
    assert q.scale.n_points == 11 and q.scale.unit == "%"
    assert "percentage of the time" in q.instructions


def test_builtins_round_trip_as_data():
    for q in BUILTIN_QUESTIONNAIRES.values():
        assert Questionnaire.model_validate(json.loads(q.model_dump_json())) == q


# --- scoring ---------------------------------------------------------------------------

def test_schaefer_score_of_all_midpoints_is_the_midpoint():
    assert score(SCHAEFER_14, dict.fromkeys(SCHAEFER_14.item_ids, MID)) == MID


def test_reverse_items_flip():
    best = {i.id: defaults.SCHAEFER_SCALE_MIN if i.reverse_coded else defaults.SCHAEFER_SCALE_MAX
            for i in SCHAEFER_14.items}
    assert score(SCHAEFER_14, best) == defaults.SCHAEFER_SCALE_MAX
    assert score(SCHAEFER_14, dict.fromkeys(SCHAEFER_14.item_ids, defaults.SCHAEFER_SCALE_MAX)) == pytest.approx(
        defaults.SCHAEFER_SCALE_MAX * 11 / 14)
    assert reverse_code(SCHAEFER_14, "malfunction", 30) == 70
    assert reverse_code(SCHAEFER_14, "reliable", 30) == 30
    assert reverse_code(likert(), "b", 2) == 6  # 7 + 1 - 2


@given(answers=schaefer_answers)
def test_score_is_the_mean_of_reverse_coded_values(answers):
    coded = [reverse_code(SCHAEFER_14, i, v) for i, v in answers.items()]
    assert score(SCHAEFER_14, answers) == pytest.approx(sum(coded) / len(coded))
    assert defaults.SCHAEFER_SCALE_MIN <= score(SCHAEFER_14, answers) <= defaults.SCHAEFER_SCALE_MAX


@given(answers=schaefer_answers)
def test_reverse_coding_twice_is_identity(answers):
    for item in SCHAEFER_14.items:
        once = reverse_code(SCHAEFER_14, item, answers[item.id])
        assert reverse_code(SCHAEFER_14, item, once) == answers[item.id]


# --- answer validation ---------------------------------------------------------------------

@pytest.mark.parametrize(("change", "message"), [
    ({"trust": None}, "missing item 'trust'"),
    ({"mood": 3}, "unknown item 'mood'"),
    ({"trust": 11}, "off the scale 0–10"),
    ({"trust": -1}, "off the scale"),
    ({"trust": 2.5}, "not on a step of 1"),
    ({"trust": "7"}, "not a number"),
    ({"trust": True}, "not a number"),
    ({"trust": float("nan")}, "not a finite number"),
])
def test_invalid_answers_say_what_is_wrong(change, message):
    answers = {"trust": 5, "reliance": 5} | change
    answers = {k: v for k, v in answers.items() if v is not None}
    with pytest.raises(AnswerError, match=message):
        validate_answers(SHELF_TRUST_RELIANCE, answers)


def test_answer_error_lists_every_problem():
    with pytest.raises(AnswerError) as caught:
        validate_answers(SCHAEFER_14, {"reliable": 55, "extra": 10})
    assert len(caught.value.problems) == 13 + 1 + 1
    assert isinstance(caught.value, ValueError)


def test_schaefer_steps_of_ten():
    answers = dict.fromkeys(SCHAEFER_14.item_ids, 40) | {"dependable": 45}
    with pytest.raises(AnswerError, match="'dependable': 45 is not on a step of 10"):
        score(SCHAEFER_14, answers)
    with pytest.raises(AnswerError, match="off the scale"):
        reverse_code(SCHAEFER_14, "have_errors", 110)


def test_fractional_steps():
    q = likert(scale={"min": 0, "max": 1, "step": 0.1})
    assert validate_answers(q, {"a": 0.3, "b": 0.7}) == {"a": 0.3, "b": 0.7}
    assert reverse_code(q, "b", 0.3) == pytest.approx(0.7)


# --- questionnaire validation --------------------------------------------------------------

@pytest.mark.parametrize(("overrides", "message"), [
    ({"scale": {"min": 5, "max": 5, "step": 1}}, "must be less than max"),
    ({"scale": {"min": 0, "max": 10, "step": 3}}, "does not divide the range"),
    ({"scale": {"min": 0, "max": 10, "step": 0}}, "greater than 0"),
    ({"scale": {"min": 0, "max": 10, "step": 1, "anchors": {11: "x"}}}, "anchor 11"),
    ({"items": [{"id": "a", "text": "A"}, {"id": "a", "text": "B"}]}, "repeated: a"),
    ({"items": []}, "at least 1 item"),
    ({"items": [{"id": "bad id", "text": "A"}]}, "should match pattern"),
    ({"items": [{"id": "a", "text": "A", "weight": 2}]}, "Extra inputs"),
    ({"scoring": "sum"}, "'mean' or 'none'"),
])
def test_invalid_questionnaires_say_what_is_wrong(overrides, message):
    with pytest.raises(ValidationError, match=message):
        likert(**overrides)


def test_lab_defined_questionnaire():
    q = likert()
    assert score(q, {"a": 7, "b": 1}) == 7
    assert q.scale.points() == [1, 2, 3, 4, 5, 6, 7]
    with pytest.raises(KeyError, match="no item 'c'"):
        q.item("c")
    assert isinstance(q.items[0], Item) and isinstance(q.scale, Scale)


def test_a_partial_page_is_checked_like_a_whole_one_but_may_leave_items_out():
    assert validate_answers(SCHAEFER_14, {"reliable": 70}, partial=True) == {"reliable": 70.0}
    with pytest.raises(AnswerError) as error:
        validate_answers(SCHAEFER_14, {"reliable": 75, "nope": 1}, partial=True)
    assert set(error.value.problems) == {"unknown item 'nope'", "item 'reliable': 75 is not on a step of 10 from 0"}
    with pytest.raises(AnswerError, match="missing item"):
        validate_answers(SCHAEFER_14, {"reliable": 70})


def test_built_in_questionnaires_have_plain_headings_for_participants():
    assert SCHAEFER_14.heading != SCHAEFER_14.title and "HRI" not in SCHAEFER_14.heading
    custom = SCHAEFER_14.model_copy(update={"participant_title": None})
    assert custom.heading == SCHAEFER_14.title  # a lab's questionnaire without one shows its title
