"""The readable diff between config documents: paths a person reads, added/removed items and keys."""

from hypothesis import given
from hypothesis import strategies as st

from experiment.config_diff import Change, diff
from experiment.templates import demo, policy_evaluation

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.floats(-5, 5, allow_nan=False) | st.text(max_size=3),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=12)


@given(json_values)
def test_a_document_has_no_diff_with_itself(value):
    assert diff(value, value) == []


@given(json_values, json_values)
def test_documents_differ_exactly_when_there_are_changes(a, b):
    changes = diff(a, b)
    assert (changes == []) == (_canonical(a) == _canonical(b))
    assert len({c.path for c in changes}) == len(changes)  # one change per place


def _canonical(value):
    """JSON equality: numbers by value (1 == 1.0), booleans apart from numbers, key order ignored."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return (type(value).__name__, value)
    if isinstance(value, int | float):
        return ("number", float(value))
    if isinstance(value, list):
        return ("list", tuple(_canonical(v) for v in value))
    return ("object", frozenset((k, _canonical(v)) for k, v in value.items()))


def test_paths_name_list_items_and_keys():
    before = demo().model_dump(mode="json")
    after = demo().model_dump(mode="json")
    after["blocks"][1]["policy"] = {"kind": "always_ask"}
    after["blocks"][0]["schedule"]["n_low"] = 5
    after["questionnaires_before"] = ["schaefer_14"]
    after["compensation"]["note"] = "x"
    changes = diff(before, after)
    assert Change("blocks[1].policy.kind", "changed", "trust_agnostic", "always_ask") in changes
    assert Change("blocks[1].policy.intervention_rate_low", "removed", before=0.006) in changes
    assert Change("blocks[0].schedule.n_low", "changed", 3, 5) in changes
    assert Change("questionnaires_before[0]", "added", after="schaefer_14") in changes
    assert Change("compensation.note", "added", after="x") in changes
    assert len(changes) == 7  # kind, 3 removed agnostic fields, n_low, questionnaire, note


def test_a_removed_block_and_odd_keys():
    two = policy_evaluation().model_dump(mode="json")
    one = {**two, "blocks": two["blocks"][:1]}
    assert diff(two, one) == [Change("blocks[1]", "removed", before=two["blocks"][1])]
    assert diff({"a b": 1}, {"a b": 2}) == [Change("['a b']", "changed", 1, 2)]
    assert diff({"x": 1}, {"x": 1.0}) == [] and diff({"x": 1}, {"x": True}) != []
    assert diff(1, {"a": 1}) == [Change("", "changed", 1, {"a": 1})]
