"""Attention checks, eligibility questions and completion outcomes as pure functions (experiment.attention,
experiment.outcomes), and their place in the study config."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from experiment.attention import (
    AttentionConfig,
    PageCheck,
    ScreenOutReason,
    attention_failed,
    attention_passed,
    check_page,
    count_failures,
    screen_out_reason,
    stored_answer,
)
from experiment.config import StudyConfig, validate_document
from experiment.outcomes import (
    CompletionConfig,
    SessionOutcome,
    outcome_of_status,
    redirect_address_problem,
    redirect_link,
    redirect_template_problem,
)
from experiment.questionnaires import Questionnaire, answer_columns, validate_answers
from experiment.templates import template

CHECKS = Questionnaire.model_validate({
    "id": "checks", "title": "Checks", "instructions": "Answer.", "scale": {"min": 1, "max": 5, "step": 1},
    "scoring": "none", "items": [
        {"id": "liking", "text": "I like robots."},
        {"id": "select_five", "text": "For this item, select 5.", "instructed_response": 5},
        {"id": "pick_blue", "text": "Choose 'Blue' here.", "kind": "choice", "instructed_response": "blue",
         "options": [{"value": "red", "label": "Red"}, {"value": "blue", "label": "Blue"}]},
        {"id": "adult", "text": "Are you 18 or older?", "kind": "choice", "screen_out_options": ["no"],
         "options": [{"value": "yes", "label": "Yes"}, {"value": "no", "label": "No"}]},
    ]})


def test_attention_passed_only_for_the_instructed_answer():
    assert attention_passed(CHECKS.item("select_five"), 5.0) is True
    assert attention_passed(CHECKS.item("select_five"), 4.0) is False
    assert attention_passed(CHECKS.item("pick_blue"), "blue") is True
    assert attention_passed(CHECKS.item("pick_blue"), "red") is False
    assert attention_passed(CHECKS.item("liking"), 5.0) is None  # not a check


def test_check_page_lists_failures_and_ineligible_answers():
    good = {"liking": 2.0, "select_five": 5.0, "pick_blue": "blue", "adult": "yes"}
    assert check_page(CHECKS, good) == PageCheck()
    bad = good | {"select_five": 1.0, "pick_blue": "red", "adult": "no"}
    assert check_page(CHECKS, bad) == PageCheck(("select_five", "pick_blue"), ("adult",))


def test_count_failures_from_stored_answers_and_export_rows():
    def row(item, value=None, text=None):
        return {"questionnaire": "checks", "item": item, "value": value, "text": text}
    stored = [row("liking", 1.0), row("select_five", 4.0), row("pick_blue", text="red"), row("adult", text="no"),
              row("select_five", 5.0), row("pick_blue", text="blue")]  # the second page of the same checks passed
    assert count_failures(stored, {"checks": CHECKS}) == 2
    cells = [{k: "" if v is None else str(v) for k, v in r.items()} for r in stored]  # surveys.csv: strings
    assert count_failures(cells, {"checks": CHECKS}) == 2
    assert count_failures(stored, {}) == 0  # a questionnaire the version does not define counts nothing


#: Pages of answers to CHECKS: any scale point, any option.
pages = st.lists(st.fixed_dictionaries({
    "liking": st.sampled_from(CHECKS.scale.points()), "select_five": st.sampled_from(CHECKS.scale.points()),
    "pick_blue": st.sampled_from(["red", "blue"]), "adult": st.sampled_from(["yes", "no"])}), max_size=4)


@given(pages=pages)
def test_failures_counted_live_and_from_stored_answers_agree(pages):
    """The live check (one attention_failed event per failure check_page finds, counted for participants.csv and
    screening) and the participants table (count_failures over the stored answers, or over surveys.csv's cells)
    follow one definition, so they count the same failures."""
    live, stored = 0, []
    for page in pages:
        values = validate_answers(CHECKS, page)
        live += len(check_page(CHECKS, values).attention_failures)
        stored += [{"questionnaire": CHECKS.id, "item": item.id, **answer_columns(CHECKS, item, values[item.id])}
                   for item in CHECKS.items]
    assert count_failures(stored, {CHECKS.id: CHECKS}) == live
    cells = [{k: "" if v is None else str(v) for k, v in r.items()} for r in stored]
    assert count_failures(cells, {CHECKS.id: CHECKS}) == live
    assert live == sum(page["select_five"] != 5 for page in pages) + sum(page["pick_blue"] != "blue" for page in pages)


def test_an_answer_stored_or_exported_reads_back_as_validated():
    five, blue = CHECKS.item("select_five"), CHECKS.item("pick_blue")
    assert stored_answer(five, {"value": 5.0, "text": None}) == stored_answer(five, {"value": "5.0", "text": ""}) == 5.0
    assert stored_answer(blue, {"value": None, "text": "blue"}) == stored_answer(blue, {"value": "", "text": "blue"})
    assert stored_answer(five, {"value": "", "text": ""}) is None
    assert attention_failed(five, None) is False and attention_failed(five, 4.0) is True  # no answer: no failure
    assert attention_failed(CHECKS.item("liking"), 1.0) is False  # not a check


@pytest.mark.parametrize("rule, before, page, expected", [
    (AttentionConfig(), 5, PageCheck(("a",)), None),  # flag only: never ends the session
    (AttentionConfig(), 0, PageCheck((), ("adult",)), ScreenOutReason.ELIGIBILITY),  # eligibility: whatever the rule
    (AttentionConfig(rule="screen_out", max_failures=2), 0, PageCheck(("a",)), None),
    (AttentionConfig(rule="screen_out", max_failures=2), 1, PageCheck(("a",)), ScreenOutReason.ATTENTION),
    (AttentionConfig(rule="screen_out", max_failures=2), 0, PageCheck(("a", "b")), ScreenOutReason.ATTENTION),
    (AttentionConfig(rule="screen_out", max_failures=1), 3, PageCheck(), None),  # a page without failures
])
def test_screen_out_reason(rule, before, page, expected):
    assert screen_out_reason(rule, before, page) == expected


def test_the_default_rule_is_flag_only_and_left_out_of_dumps():
    assert AttentionConfig() == AttentionConfig(rule="flag", max_failures=2)
    assert "attention" not in template("demo").model_dump(mode="json")
    with pytest.raises(ValueError, match="max_failures"):
        AttentionConfig(max_failures=0)


def test_screen_out_needs_an_attention_check_the_study_asks():
    base = template("demo").model_dump(mode="json")
    with pytest.raises(ValueError, match="needs an attention check"):
        StudyConfig.model_validate(base | {"attention": {"rule": "screen_out"}})
    config = StudyConfig.model_validate(base | {
        "attention": {"rule": "screen_out", "max_failures": 1},
        "questionnaires": [*base["questionnaires"], CHECKS.model_dump(mode="json")],
        "questionnaires_before": ["checks"]})
    assert config.attention.rule == "screen_out"
    assert config.model_dump(mode="json")["attention"] == {"rule": "screen_out", "max_failures": 1}


# --- outcomes ----------------------------------------------------------------------------------

def test_outcome_of_each_status():
    assert [outcome_of_status(s) for s in ("completed", "declined", "screened_out", "abandoned", "withdrawn",
                                           "active", None)] == [
        "completed", "declined", "screened_out", "timed_out", "withdrawn", None, None]


def test_codes_and_redirects_per_outcome():
    shared = CompletionConfig(redirect_url="https://r.example/done?cc={code}&why={outcome}&pid={external_id}")
    assert [shared.code(o) for o in SessionOutcome] == ["TRUSTLAB-DONE", "TRUSTLAB-NOCONSENT", "TRUSTLAB-SCREENED",
                                                        None, None]
    link = redirect_link(shared.redirect_template("screened_out"), outcome="screened_out", code="TRUSTLAB-SCREENED",
                         external_id="a&b c")
    assert link == "https://r.example/done?cc=TRUSTLAB-SCREENED&why=screened_out&pid=a%26b%20c"
    assert shared.redirect_template("timed_out") is None  # no code by default: no redirect carrying an empty one
    assert shared.redirect_template("withdrawn") is None  # the same for a withdrawal (Prolific: returned)
    own = CompletionConfig(code_timed_out="TIMEOUT", redirect_timed_out="https://r.example/t?o={outcome}",
                           code_screened_out=None)
    assert own.code("timed_out") == "TIMEOUT" and own.code("screened_out") is None
    assert redirect_link(own.redirect_template("timed_out"), outcome="timed_out", code="TIMEOUT",
                         external_id=None) == "https://r.example/t?o=timed_out"


@pytest.mark.parametrize("template_, reason", [
    ("https://r.example/?cc={code}", None),
    ("https://r.example/?x={{literal}}", None),
    ("https://r.example/?pid={PROLIFIC_PID}", "unknown placeholder {PROLIFIC_PID}"),
    ("https://r.example/?cc={code", "expected '}'"),
    ("https://r.example/?cc={code!r}", "takes no format or conversion"),
    ("app.prolific.com/submissions/complete?cc={code}", "must be a full web address starting with https://"),
    ("/done?cc={code}", "must be a full web address"),
    ("javascript:alert(1)", "must be a full web address"),
    ("https:///?cc={code}", "must be a full web address"),
    ("HTTP://r.example/?cc={code}", None),
])
def test_redirect_templates_are_checked(template_, reason):
    problem = redirect_template_problem(template_) or redirect_address_problem(template_)
    assert problem is None if reason is None else reason in problem
    received = {"completion": {"redirect_screened_out": template_}}
    if reason:
        with pytest.raises(ValueError, match="redirect"):
            validate_document(template("demo").model_dump(mode="json") | received)
    else:
        validate_document(template("demo").model_dump(mode="json") | received)


def test_a_stored_configuration_loads_whatever_rules_came_after_it():
    """A redirect without a scheme is refused in a configuration received now, but one stored before that rule
    still loads (its study version must run: its sessions go on)."""
    stored = template("demo").model_dump(mode="json") | {"completion": {"redirect_url": "r.example/done?cc={code}"}}
    assert StudyConfig.model_validate(stored).completion.redirect_url == "r.example/done?cc={code}"
    with pytest.raises(ValueError, match="full web address"):
        validate_document(stored)
    with pytest.raises(ValueError, match="unknown placeholder"):  # what was always refused still is
        StudyConfig.model_validate(stored | {"completion": {"redirect_url": "https://r.example/?p={pid}"}})


def test_old_completion_documents_load_and_dump_as_before():
    old = {"code_completed": "C1", "code_declined": "D1", "redirect_url": "https://r.example/?cc={code}"}
    assert CompletionConfig.model_validate(old).model_dump(mode="json") == old
