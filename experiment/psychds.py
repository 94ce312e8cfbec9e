"""A study's data as a Psych-DS 1.5 dataset: its file names and its JSON-LD description (``dataset_description.json``).

Psych-DS (https://psych-ds.github.io/; the rules are the schema model of psych-ds/psych-DS,
``schema_model/versions/jsons/1.5.0/schema.json``) asks for a ``dataset_description.json`` at the root (JSON-LD,
``@context`` schema.org, ``@type`` Dataset, required ``name``, ``description`` and ``variableMeasured``: every
column of every data file) and the data as CSV files under ``data/`` whose names are keyword-value pairs ending in
``_data.csv``. trustlab's four data files become::

    data/study-<slug>_description-trials_data.csv        (trials.csv)
    data/study-<slug>_description-surveys_data.csv       (surveys.csv)
    data/study-<slug>_description-participants_data.csv  (participants.csv)
    data/study-<slug>_description-events_data.csv        (events.csv)

with official keywords only: ``study`` (the slug without its hyphens, which a keyword value may not hold:
``policy-eval`` is ``policyEval``) and ``description`` ("a label describing the data file"): the files are four
tables of one study, not tasks, sessions or subjects. Each file has a sidecar (the same name, ``.json``) whose
``variableMeasured`` lists exactly its own columns; the dataset's ``variableMeasured`` lists every column name of
every file once (a name that files share with different meanings says what it means in each). Both are made from
``experiment.codebook`` (``variable_measured``), the table ``codebook.csv`` is written from, so they never
disagree; only the ``questionnaire`` column gains what the study's configurations say of each instrument (title,
form, citation, DOI, scale, scoring, items), which ``codebook.csv`` leaves to them.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from typing import Annotated, Any, Final

from pydantic import BaseModel, ConfigDict, Field

from experiment.codebook import variable_measured
from experiment.questionnaires import Item, Questionnaire

SCHEMA_VERSION: Final = "Psych-DS 1.5.0"
#: The CSV export's data files and the ``description`` keyword of each in the dataset (codebook.csv is documentation).
DATA_FILES: Final = {"trials.csv": "trials", "surveys.csv": "surveys", "participants.csv": "participants",
                     "events.csv": "events"}
DESCRIPTION_PATH: Final = "dataset_description.json"
CODEBOOK_PATH: Final = "documentation/codebook.csv"
MANIFEST_PATH: Final = "documentation/manifest.json"
ANALYSIS_PATH: Final = "analysis/README.md"
#: Folders that hold no data files: listed in the ignore file (the validator skips them by default too).
NOT_DATA: Final = ("analysis/", "documentation/", "materials/", "results/")
#: The ignore file under both names: the 1.5 schema's core rule recommends ``.psychds-ignore``, the validator reads
#: ``.psychdsignore`` (psychds-validator, src/files/deno.ts).
IGNORE_FILES: Final = (".psychdsignore", ".psychds-ignore")
#: The column whose values name instruments: its PropertyValue lists the study's instruments.
INSTRUMENT_COLUMN: Final = ("surveys.csv", "questionnaire")

_ABOUT = ("Data of a human-robot trust experiment run with trustlab: in each trial a robot announces whether it "
          "will collect an item itself or asks for help; the participant relies on it or intervenes and "
          "teleoperates it. The data files hold the trials, the questionnaire answers, the participants' sessions "
          "and the event log.")


_Text = Annotated[str, Field(min_length=1, max_length=300)]


class DatasetInfo(BaseModel):
    """How the study's Psych-DS export describes the dataset (the recommended fields of dataset_description.json)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    authors: list[_Text] = Field([], max_length=100, description=(
        'Who made the dataset, as names ("Ada Lovelace") or ORCID URLs, in citation order'))
    license: str | None = Field(None, min_length=1, max_length=300, description=(
        "The data's license: a URL (preferred, e.g. https://creativecommons.org/licenses/by/4.0/) or its name; "
        "null: none given"))
    citation: str | None = Field(None, min_length=1, max_length=2000, description=(
        "How to cite the dataset (or the paper that reports it), as a full reference; null: none given"))
    keywords: list[_Text] = Field([], max_length=50, description="Words to find the dataset by")


def keyword_value(text: str) -> str:
    """``text`` as a Psych-DS keyword value (letters and digits only): hyphens dropped, each part after one
    capitalised (``policy-eval`` -> ``policyEval``)."""
    first, *rest = [part for part in text.split("-") if part]
    return first + "".join(part[:1].upper() + part[1:] for part in rest)


def data_file_path(slug: str, name: str) -> str:
    """Where the export file ``name`` (e.g. ``trials.csv``) is in the dataset of study ``slug``."""
    return f"data/study-{keyword_value(slug)}_description-{DATA_FILES[name]}_data.csv"


def sidecar_path(slug: str, name: str) -> str:
    return data_file_path(slug, name).removesuffix(".csv") + ".json"


def file_variables(name: str, instruments: Mapping[tuple[int, str], Questionnaire]) -> list[dict[str, Any]]:
    """Data file ``name``'s ``variableMeasured``: its codebook columns, the instrument column with the study's
    instruments."""
    variables = variable_measured(name)
    if name == INSTRUMENT_COLUMN[0] and instruments:
        for variable in variables:
            if variable["name"] == INSTRUMENT_COLUMN[1]:
                variable["valueReference"] = instrument_values(instruments)
    return variables


def dataset_variables(instruments: Mapping[tuple[int, str], Questionnaire]) -> list[dict[str, Any]]:
    """Every column name of every data file once, in file order. A name several files share keeps what they agree
    on; where their descriptions differ it says what the column means in each file."""
    found: dict[str, list[tuple[str, dict[str, Any]]]] = {}
    for name, kind in DATA_FILES.items():
        for variable in file_variables(name, instruments):
            found.setdefault(variable["name"], []).append((kind, variable))
    return [_merged(column, uses) for column, uses in found.items()]


def _merged(column: str, uses: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    first = uses[0][1]
    if all(variable == first for _, variable in uses):
        return first
    shared = {key: value for key, value in first.items() if all(v.get(key) == value for _, v in uses)}
    descriptions = {variable["description"] for _, variable in uses}
    if len(descriptions) > 1:
        shared["description"] = " ".join(f"In {kind}: {variable['description']}" for kind, variable in uses)
    return {"@type": "PropertyValue", "name": column} | shared


def instrument_values(instruments: Mapping[tuple[int, str], Questionnaire]) -> list[dict[str, Any]]:
    """Each distinct questionnaire document of the study's configuration versions as a PropertyValue
    (``propertyID``: the id the questionnaire column holds), its items as PropertyValues (``propertyID``: the id
    the item column holds)."""
    forms: dict[str, tuple[Questionnaire, list[int]]] = {}
    for (version, _), questionnaire in sorted(instruments.items()):
        key = json.dumps(questionnaire.model_dump(mode="json"), sort_keys=True)
        forms.setdefault(key, (questionnaire, []))[1].append(version)
    return [_instrument(questionnaire, versions) for questionnaire, versions in forms.values()]


def _instrument(q: Questionnaire, versions: list[int]) -> dict[str, Any]:
    reversed_items = [item.id for item in q.items if item.reverse_coded]
    scoring = ("Score: the mean of the scored_value of its rating items that are not attention checks"
               + (f" (reverse-coded: {', '.join(reversed_items)})." if reversed_items else ".")
               if q.scoring == "mean" else "Not scored.")
    parts = [f"Questionnaire {q.id} of study configuration version{'s' if len(versions) > 1 else ''} "
             f"{', '.join(map(str, versions))}.", f"Form: {q.version}." if q.version else "", scoring,
             f"Scoring rule: {q.scoring_rule}" if q.scoring_rule else "",
             f"Citation: {q.citation}" if q.citation else "", f"DOI: {q.doi}" if q.doi else ""]
    value: dict[str, Any] = {"@type": "PropertyValue", "propertyID": q.id, "name": q.title,
                             "description": " ".join(part for part in parts if part)}
    if q.scale is not None:
        value |= {"minValue": q.scale.min, "maxValue": q.scale.max, "unitText": q.scale.unit or "scale points"}
    if q.doi:
        value["url"] = f"https://doi.org/{q.doi}"
    return value | {"valueReference": [_item(item) for item in q.items]}


def _item(item: Item) -> dict[str, Any]:
    if item.kind == "rating":
        what = "A rating on the questionnaire's scale (column value)" + (
            "; reverse-coded: scored_value = scale min + max - value" if item.reverse_coded else "")
    elif item.kind == "text":
        what = "Free text (column text)"
    else:
        what = "One of the options, recorded by its value (column text): " + "; ".join(
            f"{option.value} = {option.label}" for option in item.options or [])
    if item.is_attention_check:
        what += f". Attention check, not scored: the instructed answer is {item.instructed_response}"
    return {"@type": "PropertyValue", "propertyID": item.id, "name": item.text, "description": what + "."}


def dataset_description(*, title: str, study_description: str, info: DatasetInfo | None,
                        instruments: Mapping[tuple[int, str], Questionnaire]) -> dict[str, Any]:
    """``dataset_description.json``: the required fields, the schema version, and the recommended ones the study's
    configuration gives (``dataset``: authors, license, citation, keywords)."""
    document: dict[str, Any] = {
        "@context": "https://schema.org/", "@type": "Dataset", "name": title,
        "description": f"{_ABOUT} {study_description}".strip(), "schemaVersion": SCHEMA_VERSION}
    if info is not None:
        recommended = {"author": info.authors, "license": info.license, "citation": info.citation,
                       "keywords": info.keywords}
        document |= {key: value for key, value in recommended.items() if value}
    return document | {"variableMeasured": dataset_variables(instruments)}


def sidecar(name: str, instruments: Mapping[tuple[int, str], Questionnaire]) -> dict[str, Any]:
    """A data file's sidecar: its own ``variableMeasured``, which replaces the dataset's for that file."""
    return {"variableMeasured": file_variables(name, instruments)}


def psychdsignore() -> str:
    return ("# Not data: how to analyse the data, the codebook and the export's manifest, the study's "
            "configurations, the fitted models.\n" + "".join(f"{folder}\n" for folder in NOT_DATA))


def json_text(document: Any) -> str:
    """How the dataset's JSON files are written: UTF-8 text, indented, one trailing line feed."""
    return json.dumps(document, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def unique_keys() -> Iterable[tuple[str, str, str]]:
    """(export file, what one row is, the columns that identify a row), for the dataset's README."""
    return (("trials.csv", "a completed trial (practice included)", "participant_id, practice, block, trial"),
            ("surveys.csv", "an answer to one questionnaire item", "participant_id, context, questionnaire, item"),
            ("participants.csv", "a participant's session", "participant_id"),
            ("events.csv", "an event, in the order written", "none (the row order)"))


def config_path(version: int) -> str:
    return f"materials/study_config_v{version}.json"


def model_paths(model_id: int) -> tuple[str, str]:
    """Where a fitted model's document and its provenance go."""
    return f"results/fitted_model_{model_id}.json", f"results/fitted_model_{model_id}_provenance.json"


def readme(*, title: str, slug: str, include_preview: bool, models: list[int]) -> str:
    """The dataset's README.md: what is where, what identifies a row, what is left out."""
    rows = "".join(f"| `{data_file_path(slug, name)}` | `{name}` | {row} | {key} |\n"
                   for name, row, key in unique_keys())
    fitted = ("".join(f"- `{model_paths(i)[0]}`: a trust model fitted to this study's data (trustlab's model JSON; "
                      f"its `fitted_on` says on what), and `{model_paths(i)[1]}`: its estimates, standard errors, "
                      "policy thresholds, trust-agnostic baseline and provenance.\n" for i in models)
              or "- No model had been fitted to this study's data when it was exported.\n")
    return (f"# {title}\n\nA Psych-DS 1.5 dataset of the trustlab study `{slug}`. `{DESCRIPTION_PATH}` describes it, "
            "and every column of its data files in `variableMeasured`; each data file's sidecar (the same name "
            "ending in `.json`) lists exactly that file's columns.\n\n"
            "## Data\n\n| File | In trustlab's CSV export | One row is | Columns that identify a row |\n"
            f"|---|---|---|---|\n{rows}\n"
            "The files are the CSV export's, byte for byte: UTF-8, one header row, RFC 4180 quoting; an empty cell "
            f"is a missing value. `{CODEBOOK_PATH}` gives each column's type, allowed values, unit, meaning and "
            "decimal places (its `file` column names the CSV export's files, as above). The experimenter's preview "
            f"sessions are {'included (participants.csv marks them)' if include_preview else 'left out'}.\n\n"
            "Before sharing the data publicly: `external_id` and `recruitment` in the participants file hold the "
            "recruitment platform's ids of the participants.\n\n"
            "## Not data (listed in `.psychdsignore` and `.psychds-ignore`)\n\n"
            f"- `{ANALYSIS_PATH}`: how to fit the trust model to these files with trustlab.\n"
            f"- `{CODEBOOK_PATH}`: the codebook; `{MANIFEST_PATH}`: rows, bytes and SHA-256 of every file.\n"
            "- `materials/study_config_v<N>.json`: the study's configuration version N as stored (the data "
            "files' `version` column); `materials/study_versions.json`: each version's config hash and when it was "
            "frozen (its first participant joined).\n" + fitted)


def changes(versions: list[dict[str, Any]]) -> str:
    """The dataset's CHANGES.md: the study's configuration versions, oldest first."""
    lines = [f"- Version {v['version']}: config hash `{v['config_hash']}`, "
             + (f"frozen at {v['frozen_at']} (participants ran under it)." if v["frozen_at"]
                else "never frozen (no participant joined under it).") for v in versions]
    return ("# Changes\n\nThe study's configuration versions (`materials/`); each participant runs under the version "
            "that was current when they joined.\n\n" + "\n".join(lines) + "\n")


def analysis_readme(slug: str, models: list[int]) -> str:
    """``analysis/README.md``: the trials file is trustlab's ``trials.csv``, so ``trustlab fit`` reads it."""
    trials = data_file_path(slug, "trials.csv")
    again = (f" With the restarts and seed of `{model_paths(models[0])[1]}` (its `provenance`) it gives that model's "
             "estimates again, as long as the participants and exclusions are the same." if models else "")
    return ("# Analysis\n\nThe trials file is trustlab's `trials.csv`, so trustlab's command line reads it as it is:"
            f"\n\n```bash\ntrustlab fit {trials} --restarts 20 --seed 0 --out model.json\n```\n\n"
            "fits the trust model (an input-output hidden Markov model) to the scored trials of the participants who "
            f"are not excluded, with standard errors.{again} `trustlab policy model.json` solves the trust-aware "
            "policy; `trustlab --help` lists the rest.\n")
