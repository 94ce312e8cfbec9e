"""The built-in instruments: items, reverse coding, scores of answer sets worked out by hand, scale checks and
provenance (experiment.instruments)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from experiment import defaults
from experiment.config import StudyConfig
from experiment.instruments import (
    BUILTIN_QUESTIONNAIRES,
    COMMENTS,
    DEMOGRAPHICS,
    JIAN_TRUST_CHECKLIST,
    MUIR_TRUST_RATING,
    SCHAEFER_14,
    SHELF_TRUST_RELIANCE,
    SHELF_TRUST_RELIANCE_NAMED,
    TPS_HRI_40,
    TPS_HRI_ITEMS,
)
from experiment.questionnaires import AnswerError, Questionnaire, answer_columns, reverse_code, score, validate_answers
from experiment.templates import TEMPLATES, template


def reversed_ids(q):
    return {item.id for item in q.items if item.reverse_coded}


# --- TPS-HRI, 40 items and the 14-item subscale --------------------------------------------

def test_tps_hri_40_items():
    q = TPS_HRI_40
    assert len(q.items) == 40 == len(set(q.item_ids))
    assert reversed_ids(q) == {"malfunction", "require_frequent_maintenance", "have_errors", "incompetent",
                               "unresponsive"}
    assert q.item_ids[0] == "act_consistently" and q.item_ids[-1] == "led_astray"
    assert q.item("part_of_the_team").text == "be considered part of the team"
    assert q.scale.points() == list(range(0, 101, 10)) and q.scale.unit == "%"
    assert q.instructions == SCHAEFER_14.instructions == "What percentage of the time will this robot …"


def test_the_subscale_is_made_of_the_40_item_scales_own_items():
    whole = {item.id: item for item in TPS_HRI_40.items}
    assert len(SCHAEFER_14.items) == 14 == len(set(SCHAEFER_14.item_ids))
    assert set(SCHAEFER_14.item_ids) < set(whole)
    for item in SCHAEFER_14.items:
        assert item is whole[item.id] is TPS_HRI_ITEMS[item.id]  # one definition per item
    assert reversed_ids(SCHAEFER_14) == {"have_errors", "unresponsive", "malfunction"}
    assert SCHAEFER_14.scale == TPS_HRI_40.scale


def test_tps_hri_40_score_by_hand():
    # every item 80 %: the five reverse-coded ones count 20, so (35 × 80 + 5 × 20) / 40 = 72.5
    assert score(TPS_HRI_40, dict.fromkeys(TPS_HRI_40.item_ids, 80)) == 72.5
    # the subscale on the same answers: (11 × 80 + 3 × 20) / 14
    assert score(SCHAEFER_14, dict.fromkeys(SCHAEFER_14.item_ids, 80)) == pytest.approx(940 / 14)


def test_tps_hri_40_refuses_off_scale_and_between_step_answers():
    answers = dict.fromkeys(TPS_HRI_40.item_ids, 50)
    with pytest.raises(AnswerError) as error:
        score(TPS_HRI_40, answers | {"led_astray": 110, "incompetent": 45})
    assert set(error.value.problems) == {"item 'led_astray': 110 is off the scale 0–100",
                                         "item 'incompetent': 45 is not on a step of 10 from 0"}


# --- Jian, Bisantz & Drury (2000) ------------------------------------------------------------

def test_jian_items():
    q = JIAN_TRUST_CHECKLIST
    assert len(q.items) == 12 == len(set(q.item_ids))
    assert [item.reverse_coded for item in q.items] == [True] * 5 + [False] * 7  # items 1–5: distrust
    assert q.items[0].text == "The system is deceptive." and q.items[-1].text == "I am familiar with the system."
    assert q.scale.points() == [1, 2, 3, 4, 5, 6, 7]
    assert q.scale.anchors == {1: "Not at all", 7: "Extremely"}


def test_jian_score_by_hand():
    q = JIAN_TRUST_CHECKLIST
    # all 7s: items 1–5 become 1, items 6–12 stay 7 → (5 × 1 + 7 × 7) / 12 = 54 / 12
    assert score(q, dict.fromkeys(q.item_ids, 7)) == 4.5
    # no distrust at all (1s) and full trust (7s) is the top score
    best = {item.id: 1 if item.reverse_coded else 7 for item in q.items}
    assert score(q, best) == 7.0
    # all 1s: items 1–5 become 7 → (5 × 7 + 7 × 1) / 12 = 3.5
    assert score(q, dict.fromkeys(q.item_ids, 1)) == 3.5


def test_jian_refuses_off_scale_answers():
    answers = dict.fromkeys(JIAN_TRUST_CHECKLIST.item_ids, 4)
    with pytest.raises(AnswerError) as error:
        validate_answers(JIAN_TRUST_CHECKLIST, answers | {"deceptive": 0, "trust": 8, "wary": 3.5})
    assert set(error.value.problems) == {"item 'deceptive': 0 is off the scale 1–7",
                                         "item 'trust': 8 is off the scale 1–7",
                                         "item 'wary': 3.5 is not on a step of 1 from 1"}


# --- Muir's single rating ------------------------------------------------------------------

def test_muir_single_rating():
    q = MUIR_TRUST_RATING
    assert q.item_ids == ["trust"] and not reversed_ids(q)
    assert (q.scale.min, q.scale.max, q.scale.step) == (defaults.MUIR_SCALE_MIN, defaults.MUIR_SCALE_MAX, 10)
    assert q.scale.n_points == 11  # a row of buttons a person can use, as the TPS-HRI's percentages
    assert score(q, {"trust": 60}) == 60.0
    for bad in (-10, 110, 63):
        with pytest.raises(AnswerError, match="item 'trust'"):
            score(q, {"trust": bad})


# --- provenance and use in a study ---------------------------------------------------------

@pytest.mark.parametrize("q", list(BUILTIN_QUESTIONNAIRES.values()), ids=list(BUILTIN_QUESTIONNAIRES))
def test_every_built_in_says_where_it_comes_from(q):
    assert q.version and q.scoring_rule
    if q in (DEMOGRAPHICS, COMMENTS):  # our own wording: no citation
        assert q.citation is q.doi is None and "trustlab" in q.title
    else:
        assert q.citation
        assert q.doi or q in (SHELF_TRUST_RELIANCE, SHELF_TRUST_RELIANCE_NAMED)
    assert Questionnaire.model_validate(json.loads(q.model_dump_json())) == q


def test_versions_and_dois():
    assert (TPS_HRI_40.version, SCHAEFER_14.version) == ("40-item", "14-item subscale")
    assert TPS_HRI_40.doi == SCHAEFER_14.doi == "10.1007/978-1-4899-7668-0_10"
    assert JIAN_TRUST_CHECKLIST.doi == "10.1207/S15327566IJCE0401_04"
    assert MUIR_TRUST_RATING.doi == "10.1080/00140139608964474"
    assert set(BUILTIN_QUESTIONNAIRES) == {"shelf_trust_reliance", "shelf_trust_reliance_named", "schaefer_14",
                                           "tps_hri_40", "jian_trust_checklist", "muir_trust_rating", "demographics",
                                           "comments"}


def test_provenance_is_optional_and_left_out_of_dumps_when_missing():
    doc = {"id": "mine", "title": "Mine", "instructions": "Rate.", "scale": {"min": 1, "max": 5, "step": 1},
           "items": [{"id": "a", "text": "A"}]}
    mine = Questionnaire.model_validate(doc)
    assert mine.citation is mine.doi is mine.version is mine.scoring_rule is None
    assert set(mine.model_dump()) == {"id", "title", "participant_title", "instructions", "scale", "items", "scoring"}
    with pytest.raises(ValueError, match="doi"):
        Questionnaire.model_validate(doc | {"doi": "https://doi.org/10.1/x"})
    with pytest.raises(ValueError, match="Extra inputs"):
        Questionnaire.model_validate(doc | {"reference": "Me (2026)"})


def test_the_default_shelf_questions_name_the_robot_and_the_papers_studies_keep_the_papers_words():
    """A study's shelf questions name the robot as its pages do (issue 37); the paper's wording is the built-in
    shelf_trust_reliance, which the paper's two templates keep asking (their science unchanged)."""
    assert StudyConfig.model_fields["questionnaires"].default == [SHELF_TRUST_RELIANCE_NAMED, SCHAEFER_14]
    assert StudyConfig.model_fields["shelf_questionnaire"].default == SHELF_TRUST_RELIANCE_NAMED.id
    assert [item.text for item in SHELF_TRUST_RELIANCE.items] == [
        "To what extent do you trust the automation in this scenario?",
        "To what extent did you rely on the automation in this scenario?"]  # the paper's appendix
    assert [item.text for item in SHELF_TRUST_RELIANCE_NAMED.naming("Robot B").items] == [
        "To what extent do you trust Robot B in this scenario?",
        "To what extent did you rely on Robot B in this scenario?"]
    assert SHELF_TRUST_RELIANCE_NAMED.item_ids == SHELF_TRUST_RELIANCE.item_ids  # the same columns in exports
    for name in ("model-estimation", "policy-evaluation"):
        config = template(name)
        assert [q.id for q in config.questionnaires] == [SHELF_TRUST_RELIANCE.id, SCHAEFER_14.id]
        assert config.shelf_questionnaire == SHELF_TRUST_RELIANCE.id
    for name in ("demo", "demo-fast"):
        assert template(name).shelf_questionnaire == SHELF_TRUST_RELIANCE_NAMED.id


def test_a_study_can_use_the_new_instruments():
    base = template("policy-evaluation").model_dump(mode="json")
    doc = base | {"questionnaires": base["questionnaires"] + [q.model_dump(mode="json") for q in
                                                              (TPS_HRI_40, JIAN_TRUST_CHECKLIST, MUIR_TRUST_RATING)],
                  "questionnaires_before": ["tps_hri_40", "muir_trust_rating"]}
    config = StudyConfig.model_validate(doc)
    assert config.questionnaire("tps_hri_40") == TPS_HRI_40
    assert config.questionnaire("jian_trust_checklist").citation == JIAN_TRUST_CHECKLIST.citation


def test_a_study_names_a_built_in_by_id_without_copying_it():
    base = template("policy-evaluation").model_dump(mode="json")
    first = base["blocks"][0] | {"questionnaires_after": ["jian_trust_checklist", "schaefer_14"]}
    blocks = [first, *base["blocks"][1:]]
    config = StudyConfig.model_validate(base | {"questionnaires_before": ["tps_hri_40", "muir_trust_rating"],
                                                "blocks": blocks})
    assert [q.id for q in config.questionnaires] == ["shelf_trust_reliance", "schaefer_14", "tps_hri_40",
                                                     "muir_trust_rating", "jian_trust_checklist"]
    assert config.questionnaire("muir_trust_rating") is MUIR_TRUST_RATING
    # the stored document holds the instruments themselves, and reads back as the same study
    assert StudyConfig.model_validate(json.loads(config.model_dump_json())) == config
    with pytest.raises(ValueError, match=r"unknown questionnaire id 'tps_hri_41'; did you mean 'tps_hri_40'\?"):
        StudyConfig.model_validate(base | {"questionnaires_before": ["tps_hri_41"]})


def test_a_studys_own_questionnaire_wins_over_a_built_in_of_the_same_id():
    base = template("policy-evaluation").model_dump(mode="json")
    own = {"id": "muir_trust_rating", "title": "Ours", "instructions": "Rate.",
           "scale": {"min": 1, "max": 10, "step": 1}, "items": [{"id": "trust", "text": "Trust?"}]}
    config = StudyConfig.model_validate(base | {"questionnaires": [*base["questionnaires"], own],
                                                "questionnaires_before": ["muir_trust_rating"]})
    assert config.questionnaire("muir_trust_rating").title == "Ours"
    assert len(config.questionnaires) == 3


# --- every built-in: reverse coding and the score --------------------------------------------

@pytest.mark.parametrize("q", [q for q in BUILTIN_QUESTIONNAIRES.values() if q.scoring == "mean"],
                         ids=[i for i, q in BUILTIN_QUESTIONNAIRES.items() if q.scoring == "mean"])
def test_every_scored_built_in_reverse_codes_and_scores(q):
    points = q.scale.points()
    answers = {item.id: points[(3 * k + 1) % len(points)] for k, item in enumerate(q.items)}  # varied answers
    for item in q.items:
        expected = q.scale.max + q.scale.min - answers[item.id] if item.reverse_coded else answers[item.id]
        assert reverse_code(q, item, answers[item.id]) == expected
        assert answer_columns(q, item, answers[item.id]) == {"value": answers[item.id], "scored_value": expected,
                                                             "text": None}
    by_hand = sum(q.scale.max + q.scale.min - answers[i.id] if i.reverse_coded else answers[i.id]
                  for i in q.items) / len(q.items)
    assert score(q, answers) == pytest.approx(by_hand)
    # the top of the scale on every positive item and the bottom on every reversed one is the best score
    best = {item.id: q.scale.min if item.reverse_coded else q.scale.max for item in q.items}
    assert score(q, best) == q.scale.max


@pytest.mark.parametrize("q", [SHELF_TRUST_RELIANCE, DEMOGRAPHICS, COMMENTS])
def test_unscored_built_ins_have_no_score(q):
    with pytest.raises(ValueError, match="has no score"):
        score(q, {})


# --- item kinds: text and choice --------------------------------------------------------------

def _demographics(**changes):
    return {"age_band": "age_25_34", "gender": "prefer_not_to_say", "robot_experience": "some",
            "video_game_experience": "never"} | changes


def test_demographics_are_choices_with_prefer_not_to_say():
    assert all(item.kind == "choice" and item.required for item in DEMOGRAPHICS.items)
    assert "prefer_not_to_say" in DEMOGRAPHICS.item("gender").option_values
    assert DEMOGRAPHICS.scale is None and DEMOGRAPHICS.scoring == "none"
    assert validate_answers(DEMOGRAPHICS, _demographics()) == _demographics()
    column = answer_columns(DEMOGRAPHICS, DEMOGRAPHICS.item("gender"), "man")
    assert column == {"value": None, "scored_value": None, "text": "man"}


def test_choice_answers_are_checked_with_clear_reasons():
    with pytest.raises(AnswerError) as error:
        validate_answers(DEMOGRAPHICS, _demographics(age_band="age_99", gender=3) | {"shoe_size": "42"})
    assert set(error.value.problems) == {
        "unknown item 'shoe_size'", "item 'gender': 3 is not one of the options (woman, man, non_binary, "
        "self_described, prefer_not_to_say)",
        "item 'age_band': unknown option 'age_99'; the options are age_18_24, age_25_34, age_35_44, age_45_54, "
        "age_55_64, age_65_plus, prefer_not_to_say"}
    with pytest.raises(AnswerError, match="missing item 'gender'"):
        validate_answers(DEMOGRAPHICS, {k: v for k, v in _demographics().items() if k != "gender"})


def test_comments_are_optional_free_text():
    item = COMMENTS.item("comments")
    assert (item.kind, item.required, item.text_limit) == ("text", False, 2000)
    assert validate_answers(COMMENTS, {}) == {}
    assert validate_answers(COMMENTS, {"comments": "   "}) == {}  # blank is no answer
    assert validate_answers(COMMENTS, {"comments": "  Fine.\nThanks "}) == {"comments": "Fine.\nThanks"}
    problems = {"too long": "x" * 2001, "not text": 5, "control characters": "a\x00b"}
    for reason, value in problems.items():
        with pytest.raises(AnswerError) as error:
            validate_answers(COMMENTS, {"comments": value})
        assert len(error.value.problems) == 1, reason
    with pytest.raises(AnswerError, match="2001 characters, more than the 2000 allowed"):
        validate_answers(COMMENTS, {"comments": "x" * 2001})


def _questionnaire(*items, scale=None, scoring="none"):
    doc = {"id": "q", "title": "Q", "instructions": "Answer.", "items": list(items), "scoring": scoring}
    return Questionnaire.model_validate(doc | ({"scale": scale} if scale else {}))


LIKERT = {"min": 1, "max": 5, "step": 1}


@pytest.mark.parametrize("item, reason", [
    ({"id": "a", "text": "A", "kind": "text", "options": [{"value": "x", "label": "X"}] * 2},
     "options does not apply to a text item"),
    ({"id": "a", "text": "A", "kind": "choice"}, "a choice item needs options"),
    ({"id": "a", "text": "A", "kind": "choice", "reverse_coded": True,
      "options": [{"value": "x", "label": "X"}, {"value": "y", "label": "Y"}]}, "reverse_coded does not apply"),
    ({"id": "a", "text": "A", "kind": "choice",
      "options": [{"value": "x", "label": "X"}, {"value": "x", "label": "Y"}]},
     "option values must be unique; repeated: x"),
    ({"id": "a", "text": "A", "kind": "choice", "instructed_response": "z",
      "options": [{"value": "x", "label": "X"}, {"value": "y", "label": "Y"}]},
     "instructed_response 'z' is not an option"),
    ({"id": "a", "text": "A", "kind": "choice", "screen_out_options": ["x", "y"],
      "options": [{"value": "x", "label": "X"}, {"value": "y", "label": "Y"}]}, "cannot be every option"),
    ({"id": "a", "text": "A", "kind": "text", "max_length": 20000}, "less than or equal to 10000"),
    ({"id": "a", "text": "A", "instructed_response": 5, "required": False}, "must be required"),
    ({"id": "a", "text": "A", "instructed_response": 5, "reverse_coded": True}, "cannot be reverse_coded"),
])
def test_item_fields_must_fit_the_kind(item, reason):
    with pytest.raises(ValueError, match=reason):
        _questionnaire(item, scale=LIKERT)


def test_rating_items_need_a_scale_and_on_scale_instructed_responses():
    with pytest.raises(ValueError, match="rating items need the questionnaire's scale"):
        _questionnaire({"id": "a", "text": "A"})
    with pytest.raises(ValueError, match="instructed_response 6 is off the scale"):
        _questionnaire({"id": "a", "text": "A", "instructed_response": 6}, scale=LIKERT)
    with pytest.raises(ValueError, match="scoring 'mean' needs at least one rating item"):
        _questionnaire({"id": "a", "text": "A", "instructed_response": 5}, scale=LIKERT, scoring="mean")


def test_only_rating_items_that_are_no_attention_check_are_scored():
    q = _questionnaire({"id": "a", "text": "A", "reverse_coded": True}, {"id": "b", "text": "B"},
                       {"id": "check", "text": "Select 5 here.", "instructed_response": 5},
                       {"id": "why", "text": "Why?", "kind": "text", "required": False},
                       scale=LIKERT, scoring="mean")
    assert [item.scored for item in q.items] == [True, True, False, False]
    assert score(q, {"a": 2, "b": 3, "check": 1, "why": "because"}) == 3.5  # (6 - 2 + 3) / 2
    assert answer_columns(q, q.item("check"), 1.0) == {"value": 1.0, "scored_value": None, "text": None}


def test_new_item_fields_are_left_out_of_dumps_at_their_defaults():
    """Config hashes: an item or questionnaire written before item kinds existed dumps exactly as before."""
    for q in (SHELF_TRUST_RELIANCE, SCHAEFER_14, TPS_HRI_40, JIAN_TRUST_CHECKLIST, MUIR_TRUST_RATING):
        dumped = q.model_dump(mode="json")
        assert all(set(item) == {"id", "text", "reverse_coded"} for item in dumped["items"])
        assert dumped["scale"] is not None
        assert "about_robot" not in dumped  # true, the default
    assert DEMOGRAPHICS.model_dump()["about_robot"] is COMMENTS.model_dump()["about_robot"] is False
    for name in TEMPLATES:
        dumped = template(name).model_dump(mode="json")
        assert "attention" not in dumped and "questionnaires_end" not in dumped
        assert set(dumped["completion"]) == {"code_completed", "code_declined", "redirect_url"}


def test_the_library_builds_on_the_model_not_the_other_way_round():
    """experiment.questionnaires (the model) stands alone; the instruments live only in experiment.instruments."""
    loaded = subprocess.run([sys.executable, "-c", "import sys, experiment.questionnaires as q; "
                             "print(sorted(m for m in sys.modules if m.startswith('experiment.')), "
                             "hasattr(q, 'BUILTIN_QUESTIONNAIRES'))"],
                            capture_output=True, text=True, check=True, cwd=Path(__file__).parents[2]).stdout.strip()
    assert loaded == ("['experiment.defaults', 'experiment.languages', 'experiment.questionnaire_translations', "
                      "'experiment.questionnaires'] False")
