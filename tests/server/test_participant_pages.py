"""What the participant's pages are told: duration, names, robot labels by position, payment, drafts, stale pages."""

from __future__ import annotations

import pytest
from sqlalchemy import select

from experiment.config import CompensationConfig, PracticeConfig, StudyConfig, TimingConfig
from experiment.flow import PRACTICE_DONE, QuestionnaireStep, ShelfSurveyStep, Step, TrialStep
from experiment.instruments import SCHAEFER_14
from experiment.task import RewardTable, TaskParams
from server.models import Answer, Event, Participant
from tests.server.factories import fast_config, join, make_client, make_study

#: The PostgreSQL runs add nothing here (tests/conftest.py): what the pages are told, computed from the session; its
#: storage is the participant API's, tested on both databases elsewhere.
STORAGE_INCIDENTAL = True

DRAFT = "answers/draft"


@pytest.fixture
def client(database_url):
    client, admin = make_client(database_url=database_url)
    config = fast_config(practice=PracticeConfig(enabled=False), questionnaires_before=[SCHAEFER_14.id])
    make_study(client, admin, config=config)
    client.admin_token = admin
    return client


def post(client, token, what, body=None):
    return client.post(f"/api/p/{token}/{what}", json=body)


def to_questionnaire(client) -> tuple[str, dict]:
    token = join(client)["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    state = post(client, token, "instructions/done").json()
    assert state["phase"] == "questionnaire"
    return token, state["questionnaire"]


def set_step(client, step: Step, order=("trust_agnostic", "trust_aware")) -> None:
    """Move the (only) participant to ``step``, having met the blocks in ``order``."""
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalar(select(Participant))
        participant.step, participant.block_order = step, list(order)


def test_consent_and_instructions_say_how_long_the_study_takes_and_the_title_is_plain(client):
    token = join(client)["token"]
    consent = client.get(f"/api/p/{token}/state").json()
    assert consent["study_title"] == "Robot supervision study"  # not the researchers' "trustlab demo"
    assert consent["duration"]["text"] == (f"about {consent['duration']['low_minutes']}–"
                                           f"{consent['duration']['high_minutes']} minutes")
    assert consent["duration"]["low_minutes"] < consent["duration"]["high_minutes"]
    instructions = post(client, token, "consent", {"agree": True}).json()
    assert instructions["duration"] == consent["duration"]
    assert post(client, token, "instructions/done").json()["duration"] is None  # not on the other pages


def test_questionnaire_heading_is_plain_words_not_the_instruments_name(client):
    _, page = to_questionnaire(client)
    assert page["title"] == SCHAEFER_14.participant_title and "HRI" not in page["title"]
    assert page["about"] is None  # before any robot was met


def test_robot_labels_follow_the_order_the_participant_meets_the_blocks(client):
    token, _ = to_questionnaire(client)
    # Agnostic first: it is "Robot A" on every page that names a robot, the aware block "Robot B".
    set_step(client, ShelfSurveyStep(block=1, shelf=2, trial=6))
    shelf = client.get(f"/api/p/{token}/state").json()["questionnaire"]
    assert shelf["about"] == "You have just finished shelf 2 with Robot A."
    set_step(client, QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id))
    after = client.get(f"/api/p/{token}/state").json()["questionnaire"]
    assert after["about"].startswith("These questions are about Robot B,")
    set_step(client, TrialStep(block=2, trial=1))
    trial = post(client, token, "trials/start", {"practice": False, "block": 2, "trial": 1}).json()["trial"]
    assert trial["block_label"] == "Robot B"


def test_payment_is_shown_only_when_the_study_pays(client):
    make_study(client, client.admin_token, slug="paid",
               config=fast_config(compensation=CompensationConfig(base=5.0, currency="GBP")))
    unpaid = client.get(f"/api/p/{token_at_debrief(client, 's1')}/state").json()
    assert unpaid["phase"] == "debrief" and unpaid["completion"]["compensation"] is None
    paid = client.get(f"/api/p/{token_at_debrief(client, 'paid')}/state").json()
    assert paid["completion"]["compensation"] == 5.0 and paid["completion"]["currency"] == "GBP"


def token_at_debrief(client, slug: str) -> str:
    """A participant of ``slug`` on the last page of its last questionnaire, who then answers it."""
    token = join(client, slug)["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalars(select(Participant).order_by(Participant.id.desc())).first()
        participant.block_order = ["trust_aware", "trust_agnostic"]
        participant.step = QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id)
    answers = {item.id: 50 for item in SCHAEFER_14.items}
    state = post(client, token, "answers", {"questionnaire": SCHAEFER_14.id, "context": "after:2", "answers": answers})
    assert state.status_code == 200, state.text
    return token


def test_a_draft_survives_a_reload_and_goes_when_the_page_is_submitted(client):
    token, page = to_questionnaire(client)
    body = {"questionnaire": page["id"], "context": page["context"], "answers": {"reliable": 70, "have_errors": 20}}
    for _ in range(2):  # idempotent: the same draft twice is one draft
        saved = client.put(f"/api/p/{token}/{DRAFT}", json=body)
        assert saved.status_code == 200 and saved.json()["answers"] == {"reliable": 70.0, "have_errors": 20.0}
    assert client.get(f"/api/p/{token}/state").json()["questionnaire"]["draft"] == {"reliable": 70.0,
                                                                                    "have_errors": 20.0}
    smaller = client.put(f"/api/p/{token}/{DRAFT}", json={**body, "answers": {"reliable": 80}})
    assert smaller.status_code == 200  # a draft replaces the previous one (an answer can be changed)
    assert client.get(f"/api/p/{token}/state").json()["questionnaire"]["draft"] == {"reliable": 80.0}

    wrong = client.put(f"/api/p/{token}/{DRAFT}", json={**body, "answers": {"reliable": 75, "nope": 10}})
    assert wrong.status_code == 422 and {"item 'reliable': 75 is not on a step of 10 from 0",
                                         "unknown item 'nope'"} <= set(wrong.json()["problems"])

    answers = {item["id"]: 60 for item in page["items"]}
    state = post(client, token, "answers",
                 {"questionnaire": page["id"], "context": page["context"], "answers": answers})
    assert state.status_code == 200 and state.json()["phase"] == "trial"
    with client.app.state.services.sessionmaker() as session:
        assert session.scalar(select(Participant.survey_draft)) is None
    late = client.put(f"/api/p/{token}/{DRAFT}", json=body)  # a stale tab's draft
    assert late.status_code == 409 and "the session is at trial" in late.json()["detail"]
    assert late.json()["answered_elsewhere"] is True


def test_a_stale_pages_answers_are_refused_with_what_became_of_the_page(client):
    token, page = to_questionnaire(client)
    answers = {item["id"]: 60 for item in page["items"]}
    body = {"questionnaire": page["id"], "context": page["context"], "answers": answers}
    assert post(client, token, "answers", body).status_code == 200  # one tab answers the page
    stale = post(client, token, "answers", {**body, "answers": {k: 10 for k in answers}})  # the other tab, later
    assert stale.status_code == 409
    assert stale.json()["answered_elsewhere"] is True and "already answered in another tab" in stale.json()["detail"]
    never = post(client, token, "answers", {**body, "context": "after:1"})
    assert never.status_code == 409 and never.json()["answered_elsewhere"] is False


# --- issue 37: what a new participant noticed ---------------------------------------------------------------

def state_of(client, token: str) -> dict:
    return client.get(f"/api/p/{token}/state").json()


def test_the_debrief_shows_the_final_score_when_the_study_plays_for_points(client):
    token = token_at_debrief(client, "s1")
    with client.app.state.services.sessionmaker.begin() as session:
        session.scalar(select(Participant)).score = 23.0
    assert state_of(client, token)["final_score"] == 23.0  # the demo plays for points (config task.rewards)
    no_points = fast_config(task=TaskParams(rewards=RewardTable(auto_rely_success=0, auto_rely_failure=0, ask=0)))
    assert not no_points.plays_for_points
    make_study(client, client.admin_token, slug="unscored", config=no_points)
    unscored = state_of(client, token_at_debrief(client, "unscored"))
    assert unscored["phase"] == "debrief" and unscored["final_score"] is None
    set_step(client, ShelfSurveyStep(block=1, shelf=1, trial=3))
    assert state_of(client, token)["final_score"] is None  # only on the debrief


def test_practice_ends_with_a_page_that_gives_the_decision_window_and_is_recorded(client):
    config = fast_config(timing=TimingConfig(decision_window_s=3.5))
    make_study(client, client.admin_token, slug="practised", config=config)
    token = join(client, "practised")["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    assert post(client, token, "instructions/done").json()["phase"] == "practice"
    early = post(client, token, "practice/done")
    assert early.status_code == 409 and "the session is at practice index=0" in early.json()["detail"]
    with client.app.state.services.sessionmaker.begin() as session:
        session.scalars(select(Participant).order_by(Participant.id.desc())).first().step = PRACTICE_DONE
    page = state_of(client, token)
    assert page["phase"] == "practice_done" and page["progress"] > 0
    assert page["scored_part"] == {"decision_window_s": 3.5, "plays_for_points": True,
                                   "robots": ["Robot A", "Robot B"], "n_trials": 12}
    after = post(client, token, "practice/done")
    assert after.status_code == 200, after.text
    assert after.json()["phase"] == "trial" and after.json()["ready_to_start"] == {
        "practice": False, "block": 1, "trial": 1}
    assert after.json()["scored_part"] is None
    again = post(client, token, "practice/done")  # a second tab's click
    assert again.status_code == 409 and "the session is at trial" in again.json()["detail"]
    with client.app.state.services.sessionmaker() as session:
        steps = [e.payload for e in session.scalars(select(Event).where(Event.kind == "step").order_by(Event.id))]
    assert steps[-1] == {"phase": "trial", "block": 1, "trial": 1}  # recorded like every step


def test_questionnaires_at_the_end_are_asked_after_the_last_block_and_name_no_robot(client):
    config = fast_config(practice=PracticeConfig(enabled=False), questionnaires_end=["demographics", "comments"])
    make_study(client, client.admin_token, slug="ending", config=config)
    token = join(client, "ending")["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalars(select(Participant).order_by(Participant.id.desc())).first()
        participant.block_order = ["trust_agnostic", "trust_aware"]
        participant.step = QuestionnaireStep(context="after:2", block=2, questionnaire=SCHAEFER_14.id)
    after = state_of(client, token)["questionnaire"]
    assert after["about"].startswith("These questions are about Robot B,")  # the paper's after-block Schaefer
    answers = {item.id: 50 for item in SCHAEFER_14.items}
    end = post(client, token, "answers", {"questionnaire": SCHAEFER_14.id, "context": "after:2", "answers": answers})
    assert end.json()["phase"] == "questionnaire"
    page = end.json()["questionnaire"]
    assert (page["id"], page["context"], page["about"]) == ("demographics", "end", None)
    assert "Robot" not in page["title"] + page["instructions"]
    choices = {item["id"]: item["options"][0]["value"] for item in page["items"]}
    comments = post(client, token, "answers", {"questionnaire": "demographics", "context": "end", "answers": choices})
    assert comments.json()["questionnaire"]["about"] is None
    done = post(client, token, "answers", {"questionnaire": "comments", "context": "end", "answers": {}})
    assert done.json()["phase"] == "debrief"
    with client.app.state.services.sessionmaker() as session:
        rows = session.scalars(select(Answer).where(Answer.questionnaire == "demographics")).all()
    assert {(r.context, r.block, r.block_name) for r in rows} == {("end", None, None)}


def test_questions_not_about_the_robot_get_no_robot_heading_after_a_block(client):
    base = fast_config(practice=PracticeConfig(enabled=False))
    blocks = [b.model_copy(update={"questionnaires_after": ["demographics"]}) for b in base.blocks]
    make_study(client, client.admin_token, slug="after",
               config=StudyConfig.model_validate(base.model_dump() | {"blocks": [b.model_dump() for b in blocks]}))
    token = join(client, "after")["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalars(select(Participant).order_by(Participant.id.desc())).first()
        participant.block_order = ["trust_agnostic", "trust_aware"]
        participant.step = QuestionnaireStep(context="after:1", block=1, questionnaire="demographics")
    assert state_of(client, token)["questionnaire"]["about"] is None


@pytest.mark.parametrize("shelf_questionnaire, trust_text", [
    ("shelf_trust_reliance_named", "To what extent do you trust Robot B in this scenario?"),  # the default
    ("shelf_trust_reliance", "To what extent do you trust the automation in this scenario?"),  # the paper's words
])
def test_shelf_questions_name_the_robot_as_the_pages_do_or_keep_the_papers_words(client, shelf_questionnaire,
                                                                                 trust_text):
    config = fast_config(practice=PracticeConfig(enabled=False), shelf_questionnaire=shelf_questionnaire)
    make_study(client, client.admin_token, slug="shelf", config=StudyConfig.model_validate(config.model_dump()))
    token = join(client, "shelf")["token"]
    assert post(client, token, "consent", {"agree": True}).status_code == 200
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalars(select(Participant).order_by(Participant.id.desc())).first()
        participant.block_order = ["trust_agnostic", "trust_aware"]
        participant.step = ShelfSurveyStep(block=2, shelf=1, trial=3)
    page = state_of(client, token)["questionnaire"]
    assert page["about"] == "You have just finished shelf 1 with Robot B."
    assert [item["id"] for item in page["items"]] == ["trust", "reliance"]
    assert page["items"][0]["text"] == trust_text
    assert "{robot}" not in str(page)


@pytest.mark.parametrize("end, reason", [
    (["comments", "comments"], "a questionnaire is asked once per place; repeated: comments"),
    (["demographic"], "unknown questionnaire id 'demographic'; did you mean 'demographics'?"),
    (["shelf_trust_reliance_named"], "names the robot ({robot}), but at the end of a study of several blocks"),
])
def test_a_bad_end_placement_is_refused_with_a_422_and_its_reason(client, end, reason):
    config = fast_config().model_dump(mode="json") | {"questionnaires_end": end}
    response = client.post("/api/admin/studies", json={"slug": "bad-end", "config": config},
                           headers={"Authorization": f"Bearer {client.admin_token}"})
    assert response.status_code == 422 and reason in response.text, response.text
