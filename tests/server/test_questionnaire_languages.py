"""Questionnaires in the participant's language over the API (issue 41): a German participant reads the German texts
(the robot named in them), a questionnaire without German is shown in its own language and says so, the answers and
exports are the same in structure whatever the language, the designer's check warns of the gap, and the instrument
library lists each instrument's languages and whose texts they are."""

from __future__ import annotations

import csv
import io
import re

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from experiment.config import StudyConfig
from experiment.flow import ShelfSurveyStep
from server.models import Participant
from tests.server.factories import auth, fast_config, join, make_client, make_study

OWN = {"id": "own", "title": "Own", "instructions": "One more.", "scoring": "none", "about_robot": False,
       "items": [{"id": "note", "text": "Anything else?", "kind": "text", "required": False}]}
DEMOGRAPHICS = {"age_band": "age_25_34", "gender": "prefer_not_to_say", "robot_experience": "some",
                "video_game_experience": "never"}
JIAN = {item: 5 for item in ("deceptive", "underhanded", "suspicious", "wary", "harmful", "confident", "security",
                             "integrity", "dependable", "reliable", "trust", "familiar")}
#: surveys.csv columns that differ between two participants whatever they answered.
PER_PERSON = {"participant_id", "answered_at", "external_id"}


def study_config() -> StudyConfig:
    base = fast_config().model_dump(mode="json")
    return StudyConfig.model_validate(base | {
        "languages": ["en", "de"], "practice": {"enabled": False},
        "questionnaires": [*base["questionnaires"], OWN],
        "questionnaires_before": ["demographics", "jian_trust_checklist", "own"]})


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=study_config())
    return client, admin


def post(client, token, path, body=None):
    response = client.post(f"/api/p/{token}/{path}", json=body)
    assert response.status_code == 200, response.text
    return response.json()


def first_page(client, pid, **params):
    """Joined, consented and past the instructions: the first questionnaire's page."""
    token = join(client, PROLIFIC_PID=pid, **params)["token"]
    post(client, token, "consent", {"agree": True})
    return token, post(client, token, "instructions/done")["questionnaire"]


def other_browser(client: TestClient) -> TestClient:
    """A second browser on the same app (its own resume key)."""
    return TestClient(client.app)


def answer(client, token, questionnaire, answers):
    return post(client, token, "answers", {"questionnaire": questionnaire, "answers": answers})


def test_a_german_participant_reads_german_with_the_same_ids_and_values(api):
    client, _ = api
    token, page = first_page(client, "p-de", lang="de")
    assert (page["id"], page["language"], page["title"]) == ("demographics", "de", "Einige Fragen zu Ihrer Person")
    gender = next(item for item in page["items"] if item["id"] == "gender")
    assert gender["text"] == "Welchem Geschlecht ordnen Sie sich zu?"
    assert gender["options"][-1] == {"value": "prefer_not_to_say", "label": "Keine Angabe"}
    _, english = first_page(other_browser(client), "p-en", lang="en")
    assert [i["id"] for i in english["items"]] == [i["id"] for i in page["items"]]
    assert [[o["value"] for o in i["options"]] for i in english["items"]] == [
        [o["value"] for o in i["options"]] for i in page["items"]]
    assert english["language"] == "en" and english["title"] == "A few questions about you"

    jian = answer(client, token, "demographics", DEMOGRAPHICS)["questionnaire"]
    assert jian["scale"]["anchors"] == {"1": "Überhaupt nicht", "7": "Äußerst"}
    assert jian["items"][-1] == {"id": "familiar", "text": "Ich bin mit dem System vertraut.", "kind": "rating",
                                 "required": True, "max_length": None, "options": None}
    own = answer(client, token, "jian_trust_checklist", JIAN)["questionnaire"]
    assert (own["id"], own["language"], own["items"][0]["text"]) == ("own", "en", "Anything else?")  # no German


def test_the_shelf_questions_name_the_robot_in_german(api):
    client, _ = api
    token, _ = first_page(client, "p-de", lang="de")
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalar(select(Participant).where(Participant.external_id == "p-de"))
        participant.block_order = ["trust_aware", "trust_agnostic"]
        participant.step = ShelfSurveyStep(block=2, shelf=1, trial=3)
    page = client.get(f"/api/p/{token}/state").json()["questionnaire"]
    assert page["id"] == "shelf_trust_reliance_named" and page["language"] == "de"
    trust, reliance = (item["text"] for item in page["items"])
    robot = re.fullmatch(r"Inwieweit vertrauen Sie (.+) in diesem Szenario\?", trust).group(1)
    assert reliance == f"Inwieweit haben Sie sich in diesem Szenario auf {robot} verlassen?"
    assert "{" not in robot and robot.endswith(" B")  # the second block's robot, by its label
    assert page["scale"]["anchors"] == {"0": "Überhaupt nicht", "10": "Voll und ganz"}


def surveys(client, admin) -> list[dict[str, str]]:
    response = client.get("/api/admin/studies/s1/export/surveys.csv", headers=auth(admin))
    assert response.status_code == 200, response.text
    return list(csv.DictReader(io.StringIO(response.content.decode())))


def test_the_exports_are_the_same_in_structure_in_every_language(api):
    client, admin = api
    for pid, lang, browser in (("p-en", "en", client), ("p-de", "de", other_browser(client))):
        token, _ = first_page(browser, pid, lang=lang)
        answer(browser, token, "demographics", DEMOGRAPHICS)
        answer(browser, token, "jian_trust_checklist", JIAN)
        answer(browser, token, "own", {"note": "ok"})
    rows = surveys(client, admin)
    people = {p["external_id"]: p["participant_id"] for p in csv.DictReader(io.StringIO(client.get(
        "/api/admin/studies/s1/export/participants.csv", headers=auth(admin)).content.decode()))}
    by_person = {pid: [{k: v for k, v in r.items() if k not in PER_PERSON} for r in rows
                       if r["participant_id"] == people[pid]] for pid in ("p-en", "p-de")}
    assert len(by_person["p-en"]) == 4 + 12 + 1
    assert by_person["p-en"] == by_person["p-de"]  # item ids, option values, values, provenance: all the same
    gender = next(r for r in by_person["p-de"] if r["item"] == "gender")
    assert gender["text"] == "prefer_not_to_say"


def test_the_designer_is_warned_of_a_questionnaire_without_a_language_the_study_offers(api):
    client, admin = api
    document = study_config().model_dump(mode="json")
    checked = client.post("/api/admin/study-config/check", json={"config": document}, headers=auth(admin)).json()
    assert checked["valid"] is True and checked["problems"] == []
    [warning] = checked["warnings"]
    own = [q["id"] for q in document["questionnaires"]].index("own")
    assert warning["path"] == f"questionnaires[{own}]"
    assert warning["message"].startswith("questionnaire 'own' has no translation for de")
    document["questionnaires"][own]["translations"] = [
        {"language": "de", "participant_title": "Eigene", "instructions": "Noch eine.",
         "items": [{"id": "note", "text": "Sonst noch etwas?"}]}]
    checked = client.post("/api/admin/study-config/check", json={"config": document}, headers=auth(admin)).json()
    assert (checked["valid"], checked["warnings"]) == (True, [])
    document["questionnaires"][own]["translations"][0]["items"] = [{"id": "note_2", "text": "Sonst?"}]
    refused = client.post("/api/admin/studies", json={"slug": "s2", "config": document}, headers=auth(admin))
    assert refused.status_code == 422 and "items not translated: note" in refused.text


def test_the_instrument_library_lists_languages_and_their_status(api):
    client, admin = api
    response = client.get("/api/admin/instruments", headers=auth(admin))
    assert response.status_code == 200
    library = {i["id"]: i for i in response.json()}
    assert set(library) >= {"schaefer_14", "tps_hri_40", "jian_trust_checklist", "muir_trust_rating",
                            "shelf_trust_reliance", "shelf_trust_reliance_named", "demographics", "comments"}
    schaefer = library["schaefer_14"]
    assert schaefer["languages"] == [{"language": "en", "status": "original", "citation": schaefer["citation"]},
                                     {"language": "de", "status": "lab", "citation": None}]
    assert "Schaefer" in schaefer["citation"] and schaefer["items"] == 14
    assert library["demographics"]["languages"][0] == {"language": "en", "status": "original", "citation": None}
    assert client.get("/api/admin/instruments").status_code == 401
