"""The Psych-DS names and the JSON-LD description, without a server: keyword values, the codebook as PropertyValues,
shared columns, instruments."""

from __future__ import annotations

import re

from hypothesis import given
from hypothesis import strategies as st

from experiment.codebook import CODEBOOK, property_value
from experiment.config import StudyConfig
from experiment.instruments import SCHAEFER_14, SHELF_TRUST_RELIANCE_NAMED
from experiment.psychds import (
    DATA_FILES,
    DatasetInfo,
    data_file_path,
    dataset_description,
    dataset_variables,
    instrument_values,
    keyword_value,
)
from experiment.templates import demo

#: rules.files.tabular_data.data.Datafile.fileRegex of the Psych-DS 1.5.0 schema.
DATAFILE_REGEX = re.compile(r"([a-z]+-[a-zA-Z0-9]+)(_[a-z]+-[a-zA-Z0-9]+)*_data\.csv")


@given(st.from_regex(r"[a-z0-9][a-z0-9\-]{1,62}", fullmatch=True))
def test_every_slug_makes_data_file_names_the_spec_accepts(slug):
    assert re.fullmatch(r"[a-zA-Z0-9]+", keyword_value(slug))
    for name in DATA_FILES:
        assert DATAFILE_REGEX.fullmatch(data_file_path(slug, name).removeprefix("data/"))


def test_keyword_values_read_like_the_slug():
    assert [keyword_value(s) for s in ("s1", "policy-eval", "pilot-2-b")] == ["s1", "policyEval", "pilot2B"]


def test_allowed_values_become_terms_or_bounds_and_stay_in_the_description():
    columns = {c.name: c for c in CODEBOOK["trials.csv"]}
    outcome = property_value(columns["outcome"])
    assert [t["termCode"] for t in outcome["valueReference"]] == ["success", "failure", "none"]
    assert outcome["description"].endswith("Allowed values: success|failure|none.")
    belief = property_value(columns["belief_before"])
    assert (belief["minValue"], belief["maxValue"], belief["unitText"]) == (0, 1, "probability P(trust = high)")
    assert "maxValue" not in property_value(columns["block"]) and property_value(columns["block"])["minValue"] == 0
    assert property_value(columns["grasp_radius_m"]).keys() & {"minValue", "maxValue"} == {"maxValue"}  # (0, 0.2]
    assert property_value(columns["participant_id"]).keys() == {"@type", "name", "description"}
    for columns_of_file in CODEBOOK.values():
        for column in columns_of_file:
            value = property_value(column)
            assert value["name"] == column.name and value["description"].startswith(column.meaning)
            assert (column.allowed in value["description"]) and value.get("unitText", "") == column.unit


def test_shared_columns_are_listed_once_saying_what_they_mean_in_each_file():
    variables = {v["name"]: v for v in dataset_variables({})}
    assert len(variables) == len({c.name for name in DATA_FILES for c in CODEBOOK[name]})
    assert variables["study"] == {"@type": "PropertyValue", "name": "study", "description": "Study slug."}
    score = variables["score"]["description"]
    assert score.startswith("In trials: Running score") and "In participants: Total score." in score
    assert variables["score"]["unitText"] == "points"  # what the files agree on stays


def test_an_instrument_is_listed_once_per_form_with_its_items_and_scoring():
    changed = SCHAEFER_14.model_copy(update={"version": "another form"})
    forms = instrument_values({(1, "schaefer_14"): SCHAEFER_14, (2, "schaefer_14"): SCHAEFER_14,
                               (3, "schaefer_14"): changed, (1, SHELF_TRUST_RELIANCE_NAMED.id):
                               SHELF_TRUST_RELIANCE_NAMED})
    schaefer = [f for f in forms if f["propertyID"] == "schaefer_14"]
    assert [f["description"].split(".")[0] for f in schaefer] == [
        "Questionnaire schaefer_14 of study configuration versions 1, 2",
        "Questionnaire schaefer_14 of study configuration version 3"]
    assert [item["propertyID"] for item in schaefer[0]["valueReference"]] == SCHAEFER_14.item_ids
    assert schaefer[0]["url"] == f"https://doi.org/{SCHAEFER_14.doi}"


def test_recommended_fields_only_when_the_config_gives_them():
    bare = dataset_description(title="t", study_description="", info=None, instruments={})
    assert bare.keys() == {"@context", "@type", "name", "description", "schemaVersion", "variableMeasured"}
    some = dataset_description(title="t", study_description="", info=DatasetInfo(license="CC0-1.0"), instruments={})
    assert some["license"] == "CC0-1.0" and "author" not in some and "keywords" not in some
    # A configuration without them is dumped as before (its hash is unchanged); with them, it round-trips.
    assert "dataset" not in demo().model_dump(mode="json")
    given_info = demo().model_copy(update={"dataset": DatasetInfo(authors=["A. B."], keywords=["trust"])})
    assert StudyConfig.model_validate(given_info.model_dump(mode="json")) == given_info
