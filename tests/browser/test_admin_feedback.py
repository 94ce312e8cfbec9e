"""What the dashboard tells the experimenter, in the real browser: a refused admin token in words (the typed token
kept), a withdrawn participant's row saying so once, "Create evaluation study" off with the reason when the model
cannot make one, and an unknown questionnaire id beside its field with the valid ids."""

from __future__ import annotations

import json
import re
import time
import types

from playwright.sync_api import Page, expect

from experiment.config import AlwaysAutoSpec, PracticeConfig
from experiment.iohmm import paper_params
from experiment.templates import model_estimation
from tests.browser.conftest import LiveServer
from tests.server.factories import add_simulated_participants, fast_config


def log_in(page: Page, server: LiveServer) -> None:
    page.goto(f"{server.url}/admin")
    page.get_by_label("Admin token").fill(server.admin_token)
    page.keyboard.press("Enter")
    expect(page.get_by_role("heading", name="Studies")).to_be_visible()


def test_a_refused_token_is_explained_in_words_and_what_was_typed_stays(live_server: LiveServer, browser):
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto(f"{live_server.url}/admin")
    field = page.get_by_label("Admin token")
    error = page.locator("#login-error")
    for typed in ("tla_not-the-token", "tla_wrong token with spaces", "tla_café"):
        field.fill(typed)
        page.get_by_role("button", name="Log in").click()
        expect(error).not_to_be_empty()
        expect(field).to_have_value(typed)  # kept, to correct or paste over (it is selected)
        assert field.evaluate("f => f.selectionEnd - f.selectionStart") == len(typed)
        text = error.inner_text()
        assert not re.search(r"admin API|Error:|HTTP|\d{3}|[{}\[\]]|detail", text), text
        expect(page.get_by_role("heading", name="Studies")).to_be_hidden()
    field.fill("tla_not-the-token")
    page.keyboard.press("Enter")
    expect(error).to_have_text(re.compile(r"^Not logged in: this admin token is not \(or no longer\) valid\."))
    expect(page.locator("#connection")).to_be_hidden()  # the server answered: no connection trouble
    # a token revoked while logged in: logged out, in the same words
    field.fill(live_server.admin_token)
    page.keyboard.press("Enter")
    expect(page.get_by_role("heading", name="Studies")).to_be_visible()
    from server.models import utcnow
    from server.services.admin import rotate_admin_token
    with live_server.app.state.services.sessionmaker.begin() as session:
        rotate_admin_token(session, utcnow())
    page.reload()
    expect(error).to_have_text(re.compile(r"^You were logged out: this admin token is not \(or no longer\) valid\."))
    assert "admin API" not in error.inner_text()
    page.reload()  # logged out already (a poll may have done it before the reload): the reason is still given
    expect(error).to_have_text(re.compile(r"^You were logged out: this admin token is not \(or no longer\) valid\."))
    assert errors == []


def test_a_withdrawn_participant_says_withdrawn_once(live_server: LiveServer, browser):
    live_server.create_study("s1", fast_config())
    for i in range(2):
        joined = live_server.api("POST", "/api/studies/s1/join", params={"PROLIFIC_PID": f"prolific{i}"},
                                 json={"resume_key": f"key-{i:028d}"})
        assert joined.status_code == 200, joined.text
    first, second = (p["public_id"] for p in live_server.admin("GET", "/api/admin/studies/s1/participants").json())
    assert live_server.admin("POST", f"/api/admin/studies/s1/participants/{first}/withdraw",
                             json={"reason": "asked by email"}).status_code == 200
    assert live_server.admin("POST", f"/api/admin/studies/s1/participants/{second}/exclude",
                             json={"reason": "fell asleep"}).status_code == 200
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/s1/participants")
    withdrawn = page.locator(f'#participants-body tr[data-participant="{first}"] td').first
    expect(withdrawn.locator(".badge-withdrawn")).to_have_text("withdrawn")
    expect(withdrawn).to_have_text("withdrawn")  # the badge, and no reason line repeating it
    assert withdrawn.inner_text().lower().count("withdrawn") == 1
    excluded = page.locator(f'#participants-body tr[data-participant="{second}"] td').first
    expect(excluded.locator(".reason")).to_have_text("fell asleep")  # an exclusion's reason is still shown


def test_create_evaluation_study_is_off_with_the_reason_when_the_model_cannot_make_one(live_server: LiveServer,
                                                                                      browser):
    """A robot that never asked: the trust-aware policy needs what follows an ask, which the data never showed."""
    config = fast_config()
    block = config.blocks[0].model_copy(update={"policy": AlwaysAutoSpec()})
    live_server.create_study("never-asks", config.model_copy(update={"blocks": [block]}))
    add_simulated_participants(types.SimpleNamespace(app=live_server.app), "never-asks", n=3, model=paper_params())
    model = live_server.admin("POST", "/api/admin/studies/never-asks/fits", json={"restarts": 1}).json()
    deadline = time.monotonic() + 120
    while (model := live_server.admin("GET", f"/api/admin/models/{model['id']}").json())["status"] == "running":
        assert time.monotonic() < deadline
        time.sleep(0.1)
    assert model["status"] == "done" and model["evaluation_blocked"]
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/never-asks/models")
    page.get_by_role("button", name=re.compile(f"^Model {model['id']}")).click()
    button = page.get_by_role("button", name="Create evaluation study")
    expect(button).to_be_disabled()
    reason = page.locator("#deploy-blocked")
    expect(reason).to_be_visible()
    expect(reason).to_contain_text("An evaluation study cannot be created from this model: the trust-aware policy "
                                   "cannot be solved: the model has no estimate for transitions.")
    assert button.get_attribute("aria-describedby") == "deploy-blocked"
    page.get_by_label("Slug", exact=True).press("Enter")  # no submission by the keyboard either
    expect(page.locator("#deploy-status")).to_be_empty()
    assert live_server.admin("GET", "/api/admin/studies/never-asks-eval").status_code == 404


def test_a_deployable_model_has_the_button_on(live_server: LiveServer, browser):
    """Paper study 1's design (the robot asks at random): every input the policy needs is in the data."""
    live_server.create_study("pilot", fast_config(model_estimation(), practice=PracticeConfig(enabled=False)))
    add_simulated_participants(types.SimpleNamespace(app=live_server.app), "pilot", n=6, model=paper_params(), seed=1)
    model = live_server.admin("POST", "/api/admin/studies/pilot/fits", json={"restarts": 1}).json()
    deadline = time.monotonic() + 120
    while (model := live_server.admin("GET", f"/api/admin/models/{model['id']}").json())["status"] == "running":
        assert time.monotonic() < deadline
        time.sleep(0.1)
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/pilot/models")
    page.get_by_role("button", name=re.compile(f"^Model {model['id']}")).click()
    expect(page.locator("#model-detail")).to_be_visible()
    assert model["status"] == "done" and model["evaluation_blocked"] is None
    expect(page.get_by_role("button", name="Create evaluation study")).to_be_enabled()
    expect(page.locator("#deploy-blocked")).to_be_hidden()


def test_an_unknown_questionnaire_id_is_shown_beside_its_field(live_server: LiveServer, browser):
    live_server.create_study("s1", fast_config())
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/s1/config")
    page.get_by_role("button", name="Advanced: raw JSON").click()
    editor = page.get_by_label("Study configuration (JSON)")
    expect(editor).not_to_be_empty()
    document = json.loads(editor.input_value())
    document["questionnaires_before"] = ["tps_hri_41"]
    editor.fill(json.dumps(document, indent=2))
    page.get_by_role("button", name="Form").click()
    problem = page.locator('[data-schemapath="root.questionnaires_before.0"] .field-problem')
    expect(problem).to_contain_text("unknown questionnaire id 'tps_hri_41'; did you mean 'tps_hri_40'?")
    for builtin in ("comments", "demographics", "jian_trust_checklist", "muir_trust_rating", "schaefer_14",
                    "shelf_trust_reliance", "tps_hri_40"):
        expect(problem).to_contain_text(builtin)
    expect(page.locator("#config-problems li")).to_contain_text("questionnaires_before[0]")
