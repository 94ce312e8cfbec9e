"""The built-in instruments: items, reverse coding, scores of answer sets worked out by hand, scale checks and
provenance (experiment.questionnaires)."""

import json

import pytest

from experiment import defaults
from experiment.config import StudyConfig
from experiment.questionnaires import (BUILTIN_QUESTIONNAIRES, JIAN_TRUST_CHECKLIST, MUIR_TRUST_RATING, SCHAEFER_14,
                                       SHELF_TRUST_RELIANCE, TPS_HRI_40, TPS_HRI_ITEMS, AnswerError, Questionnaire,
                                       score, validate_answers)
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
    assert q.citation and q.version and q.scoring_rule
    assert q.doi or q is SHELF_TRUST_RELIANCE
    assert Questionnaire.model_validate(json.loads(q.model_dump_json())) == q


def test_versions_and_dois():
    assert (TPS_HRI_40.version, SCHAEFER_14.version) == ("40-item", "14-item subscale")
    assert TPS_HRI_40.doi == SCHAEFER_14.doi == "10.1007/978-1-4899-7668-0_10"
    assert JIAN_TRUST_CHECKLIST.doi == "10.1207/S15327566IJCE0401_04"
    assert MUIR_TRUST_RATING.doi == "10.1080/00140139608964474"
    assert set(BUILTIN_QUESTIONNAIRES) == {"shelf_trust_reliance", "schaefer_14", "tps_hri_40",
                                           "jian_trust_checklist", "muir_trust_rating"}


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


def test_the_default_study_questionnaires_are_unchanged():
    assert StudyConfig.model_fields["questionnaires"].default == [SHELF_TRUST_RELIANCE, SCHAEFER_14]
    for name in TEMPLATES:
        assert [q.id for q in template(name).questionnaires] == [SHELF_TRUST_RELIANCE.id, SCHAEFER_14.id]


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
    with pytest.raises(ValueError, match=r"unknown questionnaire ids \['tps_hri_41'\]"):
        StudyConfig.model_validate(base | {"questionnaires_before": ["tps_hri_41"]})


def test_a_studys_own_questionnaire_wins_over_a_built_in_of_the_same_id():
    base = template("policy-evaluation").model_dump(mode="json")
    own = {"id": "muir_trust_rating", "title": "Ours", "instructions": "Rate.",
           "scale": {"min": 1, "max": 10, "step": 1}, "items": [{"id": "trust", "text": "Trust?"}]}
    config = StudyConfig.model_validate(base | {"questionnaires": [*base["questionnaires"], own],
                                                "questionnaires_before": ["muir_trust_rating"]})
    assert config.questionnaire("muir_trust_rating").title == "Ours"
    assert len(config.questionnaires) == 3
