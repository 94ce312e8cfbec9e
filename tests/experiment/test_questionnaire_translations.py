"""Questionnaires in several languages (issue 41): a translation is checked whole and each gap is named at its place;
documents without translations keep their config hash; a participant reads the questionnaire in their language with
ids and values unchanged; the library says per instrument and language whose texts they are; a study is warned of a
questionnaire it asks without a translation for a language it offers."""

from __future__ import annotations

import copy
import hashlib
import json
import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from experiment.codebook import CODEBOOK
from experiment.config import StudyConfig, validate_document
from experiment.config_problems import check_document, language_gaps
from experiment.instruments import BUILTIN_QUESTIONNAIRES, DEMOGRAPHICS, SCHAEFER_14, SHELF_TRUST_RELIANCE_NAMED
from experiment.questionnaire_translations import language_statuses, serves
from experiment.questionnaires import Questionnaire, validate_answers
from experiment.templates import demo

#: A study configuration document stored before questionnaires had translations (every built-in asked), and the
#: config hash it was stored under (server.services.studies.config_hash, computed by the code of that time).
BEFORE = Path(__file__).parent / "data" / "config_before_translations.json"
BEFORE_HASH = "c2f8d022351b463315c574a8bb5234676089853507e0c594674ab42e51a8ce27"

PICK = {"id": "pick", "title": "Pick", "instructions": "Answer about {robot}.", "scoring": "none",
        "scale": {"min": 1, "max": 5, "step": 1, "anchors": {"1": "Never", "5": "Always"}},
        "items": [{"id": "often", "text": "How often did {robot} help?"},
                  {"id": "colour", "text": "Which colour?", "kind": "choice",
                   "options": [{"value": "red", "label": "Red"}, {"value": "blue", "label": "Blue"}]}]}
PICK_DE = {"language": "de", "participant_title": "Auswahl", "instructions": "Antworten Sie zu {robot}.",
           "anchors": {"1": "Nie", "5": "Immer"},
           "items": [{"id": "often", "text": "Wie oft hat {robot} geholfen?"},
                     {"id": "colour", "text": "Welche Farbe?",
                      "options": [{"value": "red", "label": "Rot"}, {"value": "blue", "label": "Blau"}]}]}


def pick(translation: dict | None = None, **changes) -> dict:
    return PICK | {"translations": [translation or copy.deepcopy(PICK_DE)]} | changes


def refusal(document: dict) -> str:
    with pytest.raises(ValidationError) as caught:
        Questionnaire.model_validate(document)
    [error] = caught.value.errors()
    assert error["loc"] == ("translations", 0)
    return error["msg"]


def test_a_complete_translation_is_accepted_and_read_in_its_language():
    q = Questionnaire.model_validate(pick())
    german = q.in_language("de")
    assert (german.heading, german.instructions, german.language) == ("Auswahl", "Antworten Sie zu {robot}.", "de")
    assert [i.text for i in german.items] == ["Wie oft hat {robot} geholfen?", "Welche Farbe?"]
    assert [(o.value, o.label) for o in german.items[1].options] == [("red", "Rot"), ("blue", "Blau")]
    assert german.scale.anchors == {1: "Nie", 5: "Immer"} and german.scale.points() == q.scale.points()
    assert german.item_ids == q.item_ids and german.translations is None
    assert german.naming("Roboter B").items[0].text == "Wie oft hat Roboter B geholfen?"
    assert q.in_language("de-AT").heading == "Auswahl"  # a regional tag reads its language's translation
    for other in ("en", "en-GB", "fr"):  # its own texts: its language, or none for that language
        assert q.in_language(other).items[0].text == "How often did {robot} help?"
    assert validate_answers(german, {"often": 3, "colour": "blue"}) == validate_answers(q, {"often": 3,
                                                                                             "colour": "blue"})


def test_an_item_left_untranslated_is_named():
    translation = copy.deepcopy(PICK_DE)
    del translation["items"][1]
    assert refusal(pick(translation)) == "translation 'de': items not translated: colour"


def test_an_option_an_anchor_or_an_unknown_item_is_named():
    translation = copy.deepcopy(PICK_DE)
    translation["items"][1]["options"] = [{"value": "red", "label": "Rot"}, {"value": "green", "label": "Grün"}]
    translation["anchors"] = {"1": "Nie"}
    translation["items"].append({"id": "extra", "text": "Noch eine?"})
    translation |= {"instructions": "", "unit": "Punkte"}
    message = refusal(pick(translation))
    assert "instructions not translated" in message
    assert "unit: the scale's unit is None, so the translation's must be left out" in message
    assert "items the questionnaire does not have: extra" in message
    assert "item 'colour': options not translated: blue" in message
    assert "item 'colour': options the item does not have: green" in message
    assert "anchors must be translated at the scale's anchor points (1, 5), not at 1" in message


def test_the_robot_placeholder_must_survive_translation():
    translation = copy.deepcopy(PICK_DE)
    translation["items"][0]["text"] = "Wie oft hat der Roboter geholfen?"
    translation["items"][1]["text"] = "Welche Farbe hatte {robot}?"
    message = refusal(pick(translation))
    assert "item 'often': the original names the robot with {robot}, the translation must too" in message
    assert "item 'colour': the original does not name the robot, so the translation cannot hold {robot}" in message


def test_a_language_is_translated_once_and_never_into_the_questionnaires_own():
    assert refusal(pick(PICK_DE | {"language": "en"})).startswith(
        "translation 'en': 'en' is given twice (or is the questionnaire's own language)")
    with pytest.raises(ValidationError, match="'de' is given twice"):
        Questionnaire.model_validate(PICK | {"translations": [PICK_DE, PICK_DE | {"language": "DE"}]})


def test_a_gap_in_a_study_document_is_placed_at_the_translation():
    document = demo().model_dump(mode="json")
    translation = document["questionnaires"][1]["translations"][0]  # schaefer_14's German
    translation["items"] = [i for i in translation["items"] if i["id"] != "have_errors"]
    config, problems = check_document(document)
    assert config is None
    assert [(p.path, p.message) for p in problems] == [
        ("questionnaires[1].translations[0]", "translation 'de': items not translated: have_errors")]


def test_a_document_stored_before_translations_keeps_its_config_hash():
    document = json.loads(BEFORE.read_text(encoding="utf-8"))
    config = validate_document(document)
    dumped = config.model_dump(mode="json")
    assert dumped == document  # nothing added: no "translations", no "language"
    canonical = json.dumps(dumped, sort_keys=True, separators=(",", ":"))  # as server.services.studies hashes
    assert hashlib.sha256(canonical.encode()).hexdigest() == BEFORE_HASH
    assert all(q.translations is None and q.language == "en" for q in config.questionnaires)


def test_every_builtin_instrument_has_german_marked_as_the_labs_own():
    for q in BUILTIN_QUESTIONNAIRES.values():
        assert q.languages == ["en", "de"], q.id
        assert language_statuses(q) == [("en", "original", q.citation), ("de", "lab", None)], q.id
        german = q.in_language("de")
        assert german.item_ids == q.item_ids and [i.option_values for i in german.items] == [
            i.option_values for i in q.items]
        assert (german.scale.points() if german.scale else None) == (q.scale.points() if q.scale else None)
        assert german.heading != q.heading and german.instructions != q.instructions
    assert SCHAEFER_14.in_language("de").scale.unit == "%"


def _german_texts() -> list[str]:
    return [text for q in BUILTIN_QUESTIONNAIRES.values() for text in q.in_language("de").participant_texts()]


def test_the_german_texts_address_the_participant_formally():
    informal = re.compile(r"\b(du|dich|dir|dein\w*|euch|euer\w*|ihr)\b")  # "Ihr" (formal) is capitalised
    assert [t for t in _german_texts() if informal.search(t)] == []
    assert sum(bool(re.search(r"\b(Sie|Ihre?[mnrs]?)\b", t)) for t in _german_texts()) >= 10


def test_the_named_shelf_questions_name_the_robot_in_german_too():
    german = SHELF_TRUST_RELIANCE_NAMED.in_language("de").naming("Roboter A")
    assert [i.text for i in german.items] == ["Inwieweit vertrauen Sie Roboter A in diesem Szenario?",
                                              "Inwieweit haben Sie sich in diesem Szenario auf Roboter A verlassen?"]
    assert german.scale.anchors == {0: "Überhaupt nicht", 10: "Voll und ganz"}


def test_german_demographics_keep_the_option_values():
    german = DEMOGRAPHICS.in_language("de")
    assert [i.option_values for i in german.items] == [i.option_values for i in DEMOGRAPHICS.items]
    gender = german.item("gender")
    assert [o.label for o in gender.options][-1] == "Keine Angabe"


def test_a_study_is_warned_of_a_questionnaire_asked_without_its_language():
    base = demo().model_dump(mode="json")
    own = {"id": "own", "title": "Own", "instructions": "", "scoring": "none", "about_robot": False,
           "items": [{"id": "note", "text": "Anything?", "kind": "text", "required": False}]}
    unused = own | {"id": "unused"}
    config = StudyConfig.model_validate(base | {"languages": ["de", "en"], "questionnaires_end": ["own"],
                                                "questionnaires": [*base["questionnaires"], own, unused]})
    [warning] = language_gaps(config)
    assert warning.path == "questionnaires[2]" and warning.message.startswith(
        "questionnaire 'own' has no translation for de, which the study offers: participants of that language read "
        "it in 'en'")
    assert language_gaps(StudyConfig.model_validate(base | {"languages": ["en", "de-CH"]})) == []  # "de" serves it
    french = language_gaps(StudyConfig.model_validate(base | {"languages": ["en", "fr"]}))
    assert [w.path for w in french] == ["questionnaires[0]", "questionnaires[1]"]
    assert not serves(SCHAEFER_14, "fr") and serves(SCHAEFER_14, "de-AT") and serves(SCHAEFER_14, "en-US")


def test_the_codebook_says_the_item_text_followed_the_participants_language():
    surveys = {column.name: column for column in CODEBOOK["surveys.csv"]}
    assert "in the participant's language" in surveys["item"].meaning
    assert "the same in every language" in surveys["item"].meaning
