"""The designer's admin API: the typed config in /openapi.json, live checks, summary, versions and diffs, duplicate."""

import re

import pytest

from experiment.templates import demo
from tests.server.factories import auth, fast_config, join, make_client, make_study

#: The PostgreSQL runs add nothing here (tests/conftest.py): the config document's checks, summary and diffs; its
#: versions are stored as every study's config is, tested on both databases elsewhere.
STORAGE_INCIDENTAL = True


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    return client, admin


def put_config(client, admin, config, **body):
    return client.put("/api/admin/studies/s1/config", json={"config": config, **body}, headers=auth(admin))


def test_openapi_describes_the_study_config(api):
    client, _ = api
    schema = client.get("/openapi.json").json()
    components = schema["components"]["schemas"]
    body = components["StudyCreate"]["properties"]["config"]
    assert "StudyConfig" in str(body) and "StudyConfig" in str(components["StudyConfigUpdate"]["properties"]["config"])
    study = components["StudyConfig"]["properties"]
    assert study["shelf_size"]["minimum"] == 1 and study["shelf_size"]["description"]
    assert study["counterbalance"]["enum"] == ["none", "all", "latin"]
    policy = components["BlockConfig"]["properties"]["policy"]
    assert set(policy["discriminator"]["mapping"]) == {"random_assist", "trust_agnostic", "trust_aware",
                                                        "always_auto", "always_ask"}


def test_a_bad_config_gets_422_listing_every_problem_with_its_place(api):
    client, admin = api
    config = fast_config().model_dump(mode="json")
    config["shelf_size"] = 0
    config["blocks"][1]["schedule"]["n_low"] = -1
    response = put_config(client, admin, config)
    assert response.status_code == 422
    problems = response.json()["problems"]
    assert len(problems) == 2
    assert any(p.startswith("body.config.shelf_size:") for p in problems)
    # placed as the check places them (no union tag such as "counts"), so a refused save and the check agree
    assert any(p.startswith("body.config.blocks.1.schedule.n_low:") for p in problems)
    check = client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin)).json()
    assert sorted(".".join(map(str, ["body", "config", *p["loc"]])) for p in check["problems"]) == sorted(
        p.split(":")[0] for p in problems)
    config = fast_config().model_dump(mode="json")
    config["shelf_size"], config["timing"]["decision_window_s"], config["seed"] = True, "4", 7.0  # as the schema reads
    problems = put_config(client, admin, config).json()["problems"]
    assert sorted(p.split(":")[0] for p in problems) == ["body.config.shelf_size",
                                                         "body.config.timing.decision_window_s"]
    check = client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin)).json()
    assert sorted(p["path"] for p in check["problems"]) == ["shelf_size", "timing.decision_window_s"]


def undescribed_fields(node, path="") -> list[str]:
    """Every property of every object in a (reference-free) JSON Schema that has no description."""
    if isinstance(node, list):
        return [p for item in node for p in undescribed_fields(item, path)]
    if not isinstance(node, dict):
        return []
    found = [f"{path}.{name}" for name, prop in node.get("properties", {}).items() if "description" not in prop]
    for key, value in node.items():
        inner = f"{path}.{key}" if key not in ("properties", "items", "anyOf", "oneOf") else path
        found += undescribed_fields(value, inner)
    return found


def test_the_form_schema_has_no_references_and_titled_options(api):
    client, admin = api
    schema = client.get("/api/admin/study-config-schema", headers=auth(admin)).json()
    assert "$ref" not in str(schema) and "$defs" not in schema
    policy = schema["properties"]["blocks"]["items"]["properties"]["policy"]
    assert [o["title"] for o in policy["oneOf"]] == ["random_assist", "trust_agnostic", "trust_aware", "always_auto",
                                                      "always_ask"]
    questionnaire = schema["properties"]["questionnaires"]["items"]
    assert "citation" not in questionnaire["required"] and "items" in questionnaire["required"]
    assert undescribed_fields(schema) == []  # every field of the study config, at every depth
    assert client.get("/api/admin/study-config-schema").status_code == 401


def test_check_answers_problems_or_the_summary_without_saving(api):
    client, admin = api
    config = fast_config().model_dump(mode="json")
    ok = client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin)).json()
    assert ok["valid"] and ok["problems"] == [] and ok["summary"]["scored_trials"] == 12
    config["blocks"][1]["policy"] = {"kind": "random_assist", "p_ask_low": 1.5}
    config["blocks"][0]["schedule"].pop("n_high")
    response = client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin))
    assert response.status_code == 200
    bad = response.json()
    assert not bad["valid"] and bad["summary"] is None
    places = {p["path"]: p for p in bad["problems"]}
    assert set(places) == {"blocks[1].policy.p_ask_low", "blocks[0].schedule.n_high"}
    assert places["blocks[1].policy.p_ask_low"]["loc"] == ["blocks", 1, "policy", "p_ask_low"]
    assert "less than or equal to 1" in places["blocks[1].policy.p_ask_low"]["message"]
    assert "required" in places["blocks[0].schedule.n_high"]["message"]
    odd = client.post("/api/admin/study-config/check", json={"config": [1]}, headers=auth(admin)).json()
    assert not odd["valid"] and odd["problems"][0]["path"] == ""
    assert client.get("/api/admin/studies/s1/versions", headers=auth(admin)).json()[0]["version"] == 1  # nothing saved


def test_summary_of_a_study(api):
    client, admin = api
    summary = client.get("/api/admin/studies/s1/summary", headers=auth(admin)).json()
    assert summary["orders"] == [["trust_aware", "trust_agnostic"], ["trust_agnostic", "trust_aware"]]
    assert summary["blocks"][0]["policy"].startswith("trust-aware: asks in high complexity when the belief")
    assert summary["payment"] == "nothing (the recruitment site pays)"
    assert client.get("/api/admin/studies/nope/summary", headers=auth(admin)).status_code == 404


def test_every_changed_save_is_a_version_with_its_author_and_a_diff(api):
    client, admin = api
    config = fast_config().model_dump(mode="json")
    assert put_config(client, admin, config, author="Ada").json()["version"] == 1  # the same config: no-op
    config["blocks"][1]["policy"] = {"kind": "always_ask"}
    config["shelf_size"] = 2
    assert put_config(client, admin, config, author="Ada").json()["version"] == 2
    assert put_config(client, admin, config, author="Ada").json()["version"] == 2  # a retried save
    join(client)  # under version 2
    config["title"] = "Wave 1"
    assert put_config(client, admin, config).json()["version"] == 3
    versions = client.get("/api/admin/studies/s1/versions", headers=auth(admin)).json()
    assert [(v["version"], v["author"], v["participants"]) for v in versions] == [
        (1, "admin", 0), (2, "Ada", 1), (3, "admin", 0)]
    join(client, PROLIFIC_PID="later")
    versions = client.get("/api/admin/studies/s1/versions", headers=auth(admin)).json()
    assert [v["participants"] for v in versions] == [0, 1, 1]
    diff = client.get("/api/admin/studies/s1/versions/diff", params={"from": 1, "to": 2}, headers=auth(admin)).json()
    changes = {c["path"]: c for c in diff["changes"]}
    assert changes["blocks[1].policy.kind"] == {"path": "blocks[1].policy.kind", "kind": "changed",
                                                "before": "trust_agnostic", "after": "always_ask"}
    assert changes["blocks[1].policy.intervention_rate_low"]["kind"] == "removed"
    assert changes["shelf_size"]["before"] == 3 and changes["shelf_size"]["after"] == 2
    missing = client.get("/api/admin/studies/s1/versions/diff", params={"from": 1, "to": 9}, headers=auth(admin))
    assert missing.status_code == 404 and "no version 9" in missing.json()["detail"]
    assert client.get("/api/admin/studies/s1/versions/diff", params={"from": 1}, headers=auth(admin)).status_code == 422
    backwards = client.get("/api/admin/studies/s1/versions/diff", params={"from": 3, "to": 1}, headers=auth(admin))
    assert {c["path"]: (c["before"], c["after"]) for c in backwards.json()["changes"]}["shelf_size"] == (2, 3)


@pytest.mark.parametrize("version", ["99999999999999999999", str(2**31), "-1", "0", "two"])
def test_a_version_number_out_of_range_is_a_422_not_a_500(api, version):
    client, admin = api
    response = client.get("/api/admin/studies/s1/versions/diff", params={"from": version, "to": 1},
                          headers=auth(admin))
    assert response.status_code == 422 and "query.from" in response.json()["detail"]


def test_author_is_checked(api):
    client, admin = api
    config = fast_config().model_dump(mode="json")
    assert put_config(client, admin, config, author="").status_code == 422
    assert put_config(client, admin, config, author="x" * 121).status_code == 422


def test_duplicate_makes_a_new_study_with_the_current_config(api):
    client, admin = api
    config = fast_config(title="Wave 1").model_dump(mode="json")
    put_config(client, admin, config)
    saved = client.get("/api/admin/studies/s1", headers=auth(admin)).json()["config"]
    assert saved | {"completion": config["completion"]} == config  # the public default codes became the study's own
    copy = client.post("/api/admin/studies/s1/duplicate", json={"author": "Ada"}, headers=auth(admin))
    assert copy.status_code == 201, copy.text
    body = copy.json()
    assert body["slug"] == "s1-copy" and body["title"] == "Wave 1 (copy)" and body["version"] == 1
    assert body["config"] | {"title": "Wave 1"} == saved
    again = client.post("/api/admin/studies/s1/duplicate", json={"author": "Ada"}, headers=auth(admin))
    assert again.status_code == 409 and "s1-copy" in again.json()["detail"]  # a retry makes no second copy
    named = client.post("/api/admin/studies/s1/duplicate", json={"slug": "wave-2", "title": "Wave 2"},
                        headers=auth(admin)).json()
    assert named["slug"] == "wave-2" and named["config"]["title"] == "Wave 2"
    versions = client.get("/api/admin/studies/wave-2/versions", headers=auth(admin)).json()
    assert versions[0]["author"] == "admin"
    assert client.post("/api/admin/studies/nope/duplicate", json={}, headers=auth(admin)).status_code == 404
    bare = client.post("/api/admin/studies/wave-2/duplicate", headers=auth(admin))  # no body: every default
    assert bare.status_code == 201 and bare.json()["slug"] == "wave-2-copy"
    assert client.post("/api/admin/studies/s1/duplicate", json={"slug": "Bad Slug"},
                       headers=auth(admin)).status_code == 422


def test_create_takes_an_author(api):
    client, admin = api
    body = {"slug": "s2", "config": demo().model_dump(mode="json"), "author": "Grace"}
    assert client.post("/api/admin/studies", json=body, headers=auth(admin)).status_code == 201
    assert client.get("/api/admin/studies/s2/versions", headers=auth(admin)).json()[0]["author"] == "Grace"


def test_check_says_when_a_valid_document_cannot_run(api):
    client, admin = api
    config = fast_config().model_dump(mode="json")
    config["blocks"][0]["policy"] = {"kind": "trust_aware", "model": {
        "format": "trustlab-iohmm", "version": 1, "params": {
            "initial": {"p_high": 0.5},
            "transitions": {c: {a: {e: {"from_low": None, "from_high": None} for e in ("negative", "positive")}
                                for a in ("auto", "ask")} for c in ("low", "high")},
            "emissions": {c: {"auto": {"p_rely_low": 0.5, "p_rely_high": 0.9}} for c in ("low", "high")}}}}
    check = client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin)).json()
    assert not check["valid"] and check["summary"] is None
    assert check["problems"][0]["path"] == "" and "cannot run" in check["problems"][0]["message"]


def form_titles(node, path=""):
    """(path, title) of every property in a (reference-free) JSON Schema."""
    if isinstance(node, list):
        return [t for item in node for t in form_titles(item, path)]
    if not isinstance(node, dict):
        return []
    found = [(f"{path}.{name}", prop.get("title", "")) for name, prop in node.get("properties", {}).items()]
    for key, value in node.items():
        found += form_titles(value, f"{path}.{key}" if key not in ("properties", "items", "anyOf", "oneOf") else path)
    return found


def test_the_form_titles_every_field_in_words_and_lays_out_numbers_and_booleans(api):
    client, admin = api
    schema = client.get("/api/admin/study-config-schema", headers=auth(admin)).json()
    titles = form_titles(schema)
    # no bare name fragments: a lone "P"/"N" word, a unit suffix left as "s"/"m", an underscore
    cryptic = [(path, t) for path, t in titles if not t or "_" in t or re.search(r"(^|\s)[PNpn]\s|\s[sm]$", t)]
    assert cryptic == []
    timing = schema["properties"]["timing"]["properties"]
    assert timing["decision_window_s"]["title"] == "Decision window (s)"
    policy = schema["properties"]["blocks"]["items"]["properties"]["policy"]["oneOf"][0]["properties"]
    assert policy["p_ask_high"]["title"] == "P(ask), high complexity"
    assert policy["p_ask_high"] | {"format": "number", "step": "any", "minimum": 0,
                                   "maximum": 1} == policy["p_ask_high"]
    shelf = schema["properties"]["shelf_size"]
    assert (shelf["format"], shelf["step"], shelf["minimum"], shelf["maximum"]) == ("number", 1, 1, 200)
    assert schema["properties"]["practice"]["properties"]["enabled"]["format"] == "checkbox"
    # a union option switched to starts valid: a required number starts from its model's example
    bernoulli, counts = schema["properties"]["blocks"]["items"]["properties"]["schedule"]["oneOf"]
    assert bernoulli["properties"]["n_trials"]["default"] == 40 and bernoulli["properties"]["p_high"]["default"] == 0.5
    assert "n_trials" in bernoulli["required"]  # the model still requires it: a document must say how many


def test_a_form_example_is_not_a_default():
    from experiment.schedule import BernoulliSchedule
    with pytest.raises(ValueError):
        BernoulliSchedule.model_validate({"kind": "bernoulli"})  # an example is not a default


def test_a_bad_slug_and_a_validator_problem_are_explained_in_words(api):
    client, admin = api
    bad_slug = client.post("/api/admin/studies/s1/duplicate", json={"slug": "Wave 2!"}, headers=auth(admin))
    assert bad_slug.status_code == 422
    assert bad_slug.json()["detail"] == ("body.slug: use 2 to 63 lower-case letters, digits and '-', starting with a "
                                         "letter or digit (it is part of the join link)")
    config = fast_config().model_dump(mode="json")
    config["completion"]["redirect_url"] = "https://example.org/?cc={code}&p={pid}"
    refused = put_config(client, admin, config)
    assert refused.status_code == 422
    assert refused.json()["detail"].startswith("body.config.completion.redirect_url: unknown placeholder {pid}")


def test_an_unknown_questionnaire_id_is_placed_at_its_field_with_every_valid_id_and_a_guess(api):
    """Each field that names a questionnaire nobody defined gets its own problem: the closest ids first, then every
    valid id (the built-ins and the study's own); the check and a refused save say the same."""
    from experiment.instruments import BUILTIN_QUESTIONNAIRES

    client, admin = api
    config = fast_config().model_dump(mode="json")
    own = {"id": "exit_survey", "title": "Ours", "instructions": "Rate.", "scale": {"min": 1, "max": 7, "step": 1},
           "items": [{"id": "trust", "text": "Trust?"}]}
    config["questionnaires"] = [*config["questionnaires"], own]
    config["questionnaires_before"] = ["schaefer_14", "tps_hri_41"]
    config["blocks"][1]["questionnaires_after"] = ["exit_survy"]
    config["shelf_questionnaire"] = "qqq"
    check = client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin)).json()
    assert not check["valid"]
    problems = {p["path"]: p["message"] for p in check["problems"]}
    assert set(problems) == {"questionnaires_before[1]", "blocks[1].questionnaires_after[0]", "shelf_questionnaire"}
    assert [p["loc"] for p in check["problems"] if p["path"] == "blocks[1].questionnaires_after[0]"] == [
        ["blocks", 1, "questionnaires_after", 0]]
    assert problems["questionnaires_before[1]"].startswith("unknown questionnaire id 'tps_hri_41'; did you mean "
                                                           "'tps_hri_40'?")
    assert "did you mean 'exit_survey'?" in problems["blocks[1].questionnaires_after[0]"]
    assert problems["shelf_questionnaire"].startswith("unknown questionnaire id 'qqq'. Valid ids: ")
    for message in problems.values():
        assert all(builtin in message for builtin in BUILTIN_QUESTIONNAIRES)
        assert "exit_survey (this study's own)" in message
    refused = put_config(client, admin, config)
    assert refused.status_code == 422
    assert sorted(p.split(":")[0] for p in refused.json()["problems"]) == [
        "body.config.blocks.1.questionnaires_after.0", "body.config.questionnaires_before.1",
        "body.config.shelf_questionnaire"]
    config["questionnaires_before"], config["shelf_questionnaire"] = ["schaefer_14", "tps_hri_40"], None
    config["blocks"][1]["questionnaires_after"] = ["exit_survey"]
    assert client.post("/api/admin/study-config/check", json={"config": config}, headers=auth(admin)).json()["valid"]
