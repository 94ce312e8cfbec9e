"""A config document's problems: every one, placed in the document as a person and a form read it, the same way the
diff names places."""

from experiment.config_diff import diff, readable
from experiment.config_problems import check_document
from experiment.templates import demo


def test_a_valid_document_has_no_problem():
    config, problems = check_document(demo().model_dump(mode="json"))
    assert config == demo() and problems == []


def test_every_problem_is_placed_without_union_tags():
    document = demo().model_dump(mode="json")
    document["blocks"][1]["policy"] = {"kind": "random_assist", "p_ask_low": 1.5}
    document["blocks"][0]["schedule"].pop("n_high")
    document["shelf_size"] = "3"  # as strictly as the schema reads
    config, problems = check_document(document)
    assert config is None
    places = {p.path: p for p in problems}
    assert set(places) == {"blocks[1].policy.p_ask_low", "blocks[0].schedule.n_high", "shelf_size"}
    assert places["blocks[1].policy.p_ask_low"].loc == ["blocks", 1, "policy", "p_ask_low"]
    assert str(places["shelf_size"]).startswith("shelf_size: ")
    _, problems = check_document([1])
    assert [p.path for p in problems] == [""] and str(problems[0]).startswith("(document): ")


def test_a_problem_and_a_change_at_one_place_have_one_path():
    document = demo().model_dump(mode="json")
    changed = demo().model_dump(mode="json")
    changed["questionnaires"][0]["scale"]["anchors"]["10"] = "Fully"  # a key that is not an identifier
    [change] = diff(document, changed)
    assert change.path == readable(["questionnaires", 0, "scale", "anchors", "10"]) == \
        "questionnaires[0].scale.anchors['10']"
    assert readable(["blocks", 1, "policy", "kind"]) == "blocks[1].policy.kind" and readable([]) == ""


def test_problems_read_as_sentences_not_as_pydantic_internals():
    document = demo().model_dump(mode="json")
    document["completion"]["redirect_url"] = "https://example.org/?cc={code}&p={pid}"
    document["questionnaires"][0]["items"][0]["id"] = "trust level"
    _, problems = check_document(document)
    messages = {p.path: p.message for p in problems}
    assert messages["completion.redirect_url"].startswith("unknown placeholder {pid}")  # no "Value error, "
    assert messages["questionnaires[0].items[0].id"] == ("use only letters, digits and '_', starting with a letter "
                                                         "(it names a column in exports)")
    assert not any("Value error" in m or "pattern" in m for m in messages.values())


def test_a_block_too_long_for_any_session_is_refused_with_its_size():
    """An extra zero or six in a trial count is a problem at the block, not a schedule that exhausts memory."""
    document = demo().model_dump(mode="json")
    document["blocks"][1]["schedule"] = {"kind": "counts", "n_low": 10**12, "n_high": 3}
    config, problems = check_document(document)
    assert config is None
    assert [(p.path, p.message) for p in problems] == [
        ("blocks[1]", "a block may have at most 10,000 trials; block 'trust_agnostic' has 1,000,000,000,003")]
    document["blocks"][1]["schedule"] = {"kind": "bernoulli", "n_trials": 10_000, "p_high": 0.5}
    assert check_document(document)[1] == []
