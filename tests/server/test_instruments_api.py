"""Questionnaire item kinds, attention checks, eligibility and completion outcomes over the API: what is stored,
what the page gets, and what the exports say (issue 17)."""

from __future__ import annotations

import csv
import io
import json
import zipfile
from datetime import timedelta

import pytest
from sqlalchemy import select

from experiment.config import StudyConfig
from experiment.flow import QuestionnaireStep
from server.models import Answer, Participant, utcnow
from server.sweeper import sweep
from tests.server.factories import auth, fast_config, join, make_client, make_study

REDIRECT = "https://recruit.example/done?cc={code}&o={outcome}&pid={external_id}"
CHECKS = {"id": "checks", "title": "Checks", "instructions": "Answer each.", "scoring": "none",
          "scale": {"min": 1, "max": 5, "step": 1}, "items": [
              {"id": "liking", "text": "I like robots."},
              {"id": "select_five", "text": "For this item, select 5.", "instructed_response": 5},
              {"id": "pick_blue", "text": "Choose 'Blue' here.", "kind": "choice", "instructed_response": "blue",
               "options": [{"value": "red", "label": "Red"}, {"value": "blue", "label": "Blue"}]}]}
CHECKS_2 = {"id": "checks_2", "title": "More checks", "instructions": "Answer.", "scoring": "none",
            "scale": {"min": 1, "max": 5, "step": 1},
            "items": [{"id": "select_one", "text": "For this item, select 1.", "instructed_response": 1}]}
ELIGIBILITY = {"id": "eligibility", "title": "Eligibility", "instructions": "Answer.", "scoring": "none", "items": [
    {"id": "adult", "text": "Are you 18 or older?", "kind": "choice", "screen_out_options": ["no"],
     "options": [{"value": "yes", "label": "Yes"}, {"value": "no", "label": "No"}]}]}
DEMOGRAPHICS = {"age_band": "age_25_34", "gender": "prefer_not_to_say", "robot_experience": "some",
                "video_game_experience": "never"}
GOOD_CHECKS = {"liking": 2, "select_five": 5, "pick_blue": "blue"}


def study_config(**changes) -> StudyConfig:
    """No practice; before the blocks: eligibility, demographics, two pages of attention checks, comments."""
    base = fast_config().model_dump(mode="json")
    return StudyConfig.model_validate(base | {
        "practice": {"enabled": False}, "questionnaires": [*base["questionnaires"], CHECKS, CHECKS_2, ELIGIBILITY],
        "questionnaires_before": ["eligibility", "demographics", "checks", "checks_2", "comments"],
        "completion": {"code_completed": "DONE-1", "code_declined": "NO-1", "redirect_url": REDIRECT}} | changes)


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    return client, admin


def study_code(client, admin, name, slug="s1"):
    """A completion code of the study (random in place of a public default: server.services.completion_codes)."""
    return client.get(f"/api/admin/studies/{slug}", headers=auth(admin)).json()["config"]["completion"][name]


def start(client, admin, config=None, pid="pp1"):
    make_study(client, admin, config=config or study_config())
    token = join(client, PROLIFIC_PID=pid)["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    state = post(client, token, "instructions/done").json()
    assert state["questionnaire"]["id"] == "eligibility"
    return token


def post(client, token, path, body=None):
    return client.post(f"/api/p/{token}/{path}", json=body)


def answer(client, token, questionnaire, answers):
    return post(client, token, "answers", {"questionnaire": questionnaire, "answers": answers})


def export(client, admin, name):
    response = client.get(f"/api/admin/studies/s1/export/{name}", headers=auth(admin))
    assert response.status_code == 200, response.text
    return list(csv.DictReader(io.StringIO(response.content.decode())))


def answer_through(client, token, *, checks=GOOD_CHECKS, checks_2=None):
    assert answer(client, token, "eligibility", {"adult": "yes"}).status_code == 200
    assert answer(client, token, "demographics", DEMOGRAPHICS).status_code == 200
    assert answer(client, token, "checks", checks).status_code == 200
    return answer(client, token, "checks_2", checks_2 or {"select_one": 1})


def test_every_item_kind_is_shown_stored_and_exported(api):
    client, admin = api
    token = start(client, admin)
    page = answer(client, token, "eligibility", {"adult": "yes"}).json()["questionnaire"]
    assert page["id"] == "demographics" and page["scale"] is None
    gender = next(i for i in page["items"] if i["id"] == "gender")
    assert gender["kind"] == "choice" and gender["required"] is True
    assert {"value": "prefer_not_to_say", "label": "Prefer not to say"} in gender["options"]
    page = answer(client, token, "demographics", DEMOGRAPHICS).json()["questionnaire"]
    assert page["id"] == "checks" and [i["kind"] for i in page["items"]] == ["rating", "rating", "choice"]
    assert "instructed" not in str(page)  # the page never learns the instructed answer
    page = answer(client, token, "checks", GOOD_CHECKS).json()["questionnaire"]
    page = answer(client, token, "checks_2", {"select_one": 1}).json()["questionnaire"]
    assert page["items"] == [{"id": "comments", "text": "Your comments", "kind": "text", "required": False,
                              "max_length": 2000, "options": None}]
    state = answer(client, token, "comments", {"comments": "  =1+1 was fun\nthanks "}).json()
    assert state["phase"] == "trial"

    surveys = {(r["questionnaire"], r["item"]): r for r in export(client, admin, "surveys.csv")}
    assert len(surveys) == 1 + 4 + 3 + 1 + 1
    gender = surveys[("demographics", "gender")]
    assert (gender["text"], gender["value"], gender["scored_value"], gender["item_kind"]) == (
        "prefer_not_to_say", "", "", "choice")
    assert (gender["instrument_title"], gender["scoring"], gender["instrument_citation"]) == (
        "Demographics (trustlab)", "none", "")
    assert surveys[("comments", "comments")]["text"] == "'=1+1 was fun\nthanks"  # neutralised, trimmed
    five = surveys[("checks", "select_five")]
    assert (five["value"], five["scored_value"], five["attention_passed"], five["item_kind"]) == ("5", "", "1",
                                                                                                  "rating")
    assert surveys[("checks", "pick_blue")]["attention_passed"] == "1"
    assert surveys[("checks", "liking")]["attention_passed"] == ""
    people = export(client, admin, "participants.csv")
    assert [(p["status"], p["outcome"], p["attention_failures"]) for p in people] == [("active", "", "0")]


def test_instrument_provenance_of_scored_answers(api):
    client, admin = api
    token = start(client, admin)
    answer_through(client, token)
    answer(client, token, "comments", {})
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalar(select(Participant))
        participant.block_order = ["trust_aware", "trust_agnostic"]
        participant.step = QuestionnaireStep(context="after:2", block=2, questionnaire="schaefer_14")
    answers = {i: 80 for i in ("function_successfully", "act_consistently", "reliable", "predictable", "dependable",
                               "follow_directions", "meet_the_needs_of_the_mission", "perform_exactly_as_instructed",
                               "have_errors", "provide_appropriate_information", "unresponsive", "malfunction",
                               "communicate_with_people", "provide_feedback")}
    state = answer(client, token, "schaefer_14", answers).json()
    assert state["phase"] == "debrief"
    assert state["completion"] == {"outcome": "completed", "code": "DONE-1", "compensation": None, "currency": "USD",
                                   "redirect_url": "https://recruit.example/done?cc=DONE-1&o=completed&pid=pp1"}
    rows = [r for r in export(client, admin, "surveys.csv") if r["questionnaire"] == "schaefer_14"]
    assert len(rows) == 14
    assert {r["scored_value"] for r in rows if r["item"] in ("have_errors", "unresponsive", "malfunction")} == {"20"}
    assert {(r["instrument_version"], r["scoring"], r["instrument_doi"]) for r in rows} == {
        ("14-item subscale", "mean", "10.1007/978-1-4899-7668-0_10")}
    assert all(r["scoring_rule"].startswith('Reverse-code "have errors"') and "Schaefer" in r["instrument_citation"]
               for r in rows)
    [person] = export(client, admin, "participants.csv")
    assert (person["outcome"], person["completion_code"]) == ("completed", "DONE-1")


@pytest.mark.parametrize("answers, problem", [
    ({"age_band": "age_99"}, "item 'age_band': unknown option 'age_99'"),
    ({"age_band": 3}, "item 'age_band': 3 is not one of the options"),
    ({}, "missing item 'gender'"),
])
def test_invalid_choice_answers_are_refused_with_the_reason(api, answers, problem):
    client, admin = api
    token = start(client, admin)
    answer(client, token, "eligibility", {"adult": "yes"})
    response = answer(client, token, "demographics", DEMOGRAPHICS | answers if answers else {"age_band": "age_18_24"})
    assert response.status_code == 422 and any(problem in p for p in response.json()["problems"])
    with client.app.state.services.sessionmaker() as session:
        assert session.scalars(select(Answer.questionnaire)).all() == ["eligibility"]  # nothing of the page written


def test_text_answers_are_checked_and_drafts_keep_every_kind(api):
    client, admin = api
    token = start(client, admin)
    answer(client, token, "eligibility", {"adult": "yes"})
    draft = {"questionnaire": "demographics", "context": "before", "answers": {"gender": "woman"}}
    assert client.put(f"/api/p/{token}/answers/draft", json=draft).status_code == 200
    assert client.get(f"/api/p/{token}/state").json()["questionnaire"]["draft"] == {"gender": "woman"}
    bad_draft = draft | {"answers": {"gender": "womn"}}
    assert client.put(f"/api/p/{token}/answers/draft", json=bad_draft).status_code == 422
    assert answer(client, token, "demographics", DEMOGRAPHICS).status_code == 200
    assert answer(client, token, "checks", GOOD_CHECKS).status_code == 200
    assert answer(client, token, "checks_2", {"select_one": 1}).status_code == 200
    too_long = answer(client, token, "comments", {"comments": "x" * 2001})
    assert too_long.status_code == 422 and "more than the 2000 allowed" in too_long.json()["detail"]
    assert answer(client, token, "comments", {"comments": "a\u0000b"}).status_code == 422
    text_draft = {"questionnaire": "comments", "context": "before", "answers": {"comments": "half a thought"}}
    assert client.put(f"/api/p/{token}/answers/draft", json=text_draft).status_code == 200
    assert client.get(f"/api/p/{token}/state").json()["questionnaire"]["draft"] == {"comments": "half a thought"}
    assert answer(client, token, "comments", {}).json()["phase"] == "trial"  # optional: no row
    assert "comments" not in {r["questionnaire"] for r in export(client, admin, "surveys.csv")}


def test_flag_only_records_and_counts_failures_but_goes_on(api):
    client, admin = api
    token = start(client, admin)
    state = answer_through(client, token, checks={"liking": 2, "select_five": 4, "pick_blue": "red"},
                           checks_2={"select_one": 2}).json()
    assert state["phase"] == "questionnaire" and state["questionnaire"]["id"] == "comments"
    events = [e for e in export(client, admin, "events.csv") if e["kind"] == "attention_failed"]
    assert len(events) == 3 and '"failures":3' in events[-1]["payload"]
    [person] = export(client, admin, "participants.csv")
    assert (person["status"], person["attention_failures"], person["outcome"]) == ("active", "3", "")
    [row] = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()
    assert row["attention_failures"] == 3
    assert {"code": "attention_failed", "detail": "failed 3 attention checks"} in row["flags"]
    passed = {r["item"]: r["attention_passed"] for r in export(client, admin, "surveys.csv")}
    assert (passed["select_five"], passed["pick_blue"], passed["select_one"]) == ("0", "0", "0")


def test_screen_out_after_n_failures(api):
    client, admin = api
    token = start(client, admin, study_config(attention={"rule": "screen_out", "max_failures": 2}))
    state = answer_through(client, token, checks={"liking": 2, "select_five": 4, "pick_blue": "blue"})
    assert state.json()["phase"] == "questionnaire"  # one failure of two: goes on
    token_2 = join(client, PROLIFIC_PID="pp2")["token"]
    post(client, token_2, "consent", {"agree": True})
    post(client, token_2, "instructions/done")
    state = answer_through(client, token_2, checks={"liking": 2, "select_five": 4, "pick_blue": "blue"},
                           checks_2={"select_one": 5}).json()
    assert (state["status"], state["phase"]) == ("screened_out", "screened_out")
    code = study_code(client, admin, "code_screened_out")  # the study's own: the default is public
    assert state["completion"] == {"outcome": "screened_out", "code": code, "compensation": None,
                                   "currency": "USD", "redirect_url": f"https://recruit.example/done?cc={code}"
                                                                      "&o=screened_out&pid=pp2"}
    assert answer(client, token_2, "comments", {}).status_code == 409  # the session records nothing more
    people = {p["external_id"]: p for p in export(client, admin, "participants.csv")}
    assert (people["pp2"]["outcome"], people["pp2"]["completion_code"], people["pp2"]["attention_failures"]) == (
        "screened_out", code, "2")
    assert people["pp2"]["finished_at"]
    assert (people["pp1"]["outcome"], people["pp1"]["attention_failures"]) == ("", "1")
    [ended] = [e for e in export(client, admin, "events.csv") if e["kind"] == "screened_out"]
    assert '"reason":"attention"' in ended["payload"]


def test_an_eligibility_question_screens_out_at_once_whatever_the_rule(api):
    client, admin = api
    token = start(client, admin)  # the default rule: flag only
    state = answer(client, token, "eligibility", {"adult": "no"}).json()
    assert state["phase"] == "screened_out" and state["completion"]["code"] == study_code(client, admin,
                                                                                          "code_screened_out")
    assert client.get(f"/api/p/{token}/state").json()["phase"] == "screened_out"
    [ended] = [e for e in export(client, admin, "events.csv") if e["kind"] == "screened_out"]
    assert '"reason":"eligibility"' in ended["payload"]
    [row] = export(client, admin, "surveys.csv")
    assert (row["item"], row["text"]) == ("adult", "no")


def test_declined_gets_its_own_code_and_redirect(api):
    client, admin = api
    make_study(client, admin, config=study_config(completion={"redirect_url": REDIRECT, "code_declined": "NO-1",
                                                              "redirect_declined": "https://recruit.example/no?o={outcome}"}))
    token = join(client, PROLIFIC_PID="pp1")["token"]
    state = post(client, token, "consent", {"agree": False}).json()
    assert state["completion"] == {"outcome": "declined", "code": "NO-1", "compensation": None, "currency": "USD",
                                   "redirect_url": "https://recruit.example/no?o=declined"}
    [person] = export(client, admin, "participants.csv")
    assert (person["outcome"], person["completion_code"]) == ("declined", "NO-1")


@pytest.mark.parametrize("completion, expected", [
    ({"redirect_url": REDIRECT}, None),  # by default a timed-out session has no code and no redirect
    ({"redirect_url": REDIRECT, "code_timed_out": "LATE-1"},
     {"outcome": "timed_out", "code": "LATE-1", "compensation": None, "currency": "USD",
      "redirect_url": "https://recruit.example/done?cc=LATE-1&o=timed_out&pid=pp1"}),
])
def test_a_timed_out_session_shows_its_outcome_when_the_participant_comes_back(api, completion, expected):
    client, admin = api
    make_study(client, admin, config=study_config(completion=completion))
    join(client, PROLIFIC_PID="pp1")
    app = client.app
    assert sweep(app.state.services.sessionmaker, app.state.services.runtimes, app.state.services.hub,
                 now=utcnow() + timedelta(hours=2)) == 1
    again = join(client, PROLIFIC_PID="pp1")  # back with the same link: the same session
    assert again["created"] is False and again["state"]["phase"] == "abandoned"
    assert again["state"]["completion"] == expected
    [person] = export(client, admin, "participants.csv")
    assert (person["outcome"], person["completion_code"]) == ("timed_out", expected["code"] if expected else "")


def test_a_redirect_template_with_an_unknown_placeholder_is_refused(api):
    client, admin = api
    config = fast_config().model_dump(mode="json") | {"completion": {"redirect_url": "https://r.example/?p={PID}"}}
    response = client.post("/api/admin/studies", json={"slug": "s1", "config": config}, headers=auth(admin))
    assert response.status_code == 422
    assert "unknown placeholder {PID}" in response.text


def test_the_manifest_holds_every_instrument_whole(api):
    client, admin = api
    make_study(client, admin, config=study_config())
    response = client.get("/api/admin/studies/s1/export.zip", headers=auth(admin))
    assert response.status_code == 200
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        manifest = json.loads(archive.read("manifest.json"))
    instruments = {(q["config_version"], q["id"]): q for q in manifest["instruments"]}
    assert set(instruments) == {(1, q) for q in ("shelf_trust_reliance_named", "schaefer_14", "checks", "checks_2",
                                                 "eligibility", "demographics", "comments")}
    schaefer = instruments[(1, "schaefer_14")]
    assert schaefer["doi"] == "10.1007/978-1-4899-7668-0_10" and schaefer["scale"]["max"] == 100
    assert {i["id"] for i in schaefer["items"] if i["reverse_coded"]} == {"have_errors", "unresponsive", "malfunction"}
    assert instruments[(1, "checks")]["items"][1]["instructed_response"] == 5
