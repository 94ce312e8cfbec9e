"""The Psych-DS export, checked against the rules of the Psych-DS 1.5 schema (psych-ds/psych-DS,
schema_model/versions/jsons/1.5.0/schema.json) and its rules-and-conventions page, since the official validator is
not installable here: file names, required fields, JSON-LD type, columns against variableMeasured, CSV shape, row_id.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import re
import zipfile
from contextlib import nullcontext
from pathlib import Path

from sqlalchemy import select
from typer.testing import CliRunner

from experiment.codebook import CODEBOOK, columns, variable_measured
from experiment.config import StudyConfig
from experiment.iohmm import PARAMETER_NAMES, model_document, nest, paper_params
from experiment.psychds import DatasetInfo
from server.cli import app as cli
from server.harness.crowd import run_bots
from server.models import AdminAudit, FitStatus, FittedModel, Study, utcnow
from server.services.studies import config_hash
from tests.server.factories import auth, make_client, make_study, tiny_study

# -- the specification's rules, restated here (not imported from the code under test) ----------------------------

#: rules.files.tabular_data.data.Datafile.fileRegex of schema 1.5.0, matched against the whole name.
DATAFILE_REGEX = re.compile(r"([a-z]+-[a-zA-Z0-9]+)(_[a-z]+-[a-zA-Z0-9]+)*_data\.csv")
#: meta.context.context.properties.keywords (and objects.common_principles.keywords) of schema 1.5.0.
OFFICIAL_KEYWORDS = {"study", "site", "subject", "session", "task", "condition", "trial", "stimulus", "description"}
#: rules.compiled_metadata.CompiledMetadata.fields of schema 1.5.0 marked "required".
REQUIRED_FIELDS = {"name", "description", "variableMeasured"}
#: rules.files.common.core: the root's files and folders (dataset_description and data are required).
CORE = {"dataset_description.json", "data", "README.md", "CHANGES.md", ".psychds-ignore", "analysis", "materials",
        "documentation", "results"}
SCHEMA_ORG = {"https://schema.org/", "https://schema.org", "http://schema.org/", "http://schema.org"}

DATASET_INFO = DatasetInfo(authors=["Ada Lovelace", "https://orcid.org/0000-0002-1825-0097"],
                           license="https://creativecommons.org/licenses/by/4.0/",
                           citation="Lovelace, A. (2025). Trust in a shelf robot. Data set.", keywords=["trust", "HRI"])
#: A finished fit's model document (the paper's parameters standing in for estimates).
FITTED = model_document(paper_params(), loglik=-1.0, stderr=nest(dict.fromkeys(PARAMETER_NAMES, 0.1)),
                        status=nest(dict.fromkeys(PARAMETER_NAMES, "estimated")), fit={"converged": True},
                        fitted_on={"study": "trust-pilot"})
SLUG = "trust-pilot"
KEYWORD = "trustPilot"


def bot_study(client, admin) -> None:
    """One bot through a tiny study (one practice trial, two scored, a shelf survey, the 14-item trust scale), and
    a finished model fit recorded for it: every file of the dataset has rows."""
    config = tiny_study("Psych-DS pilot", hint="rely", n_high=1, animation_speed=8.0)
    block = config.blocks[0].model_copy(update={"questionnaires_after": ["schaefer_14"]})
    config = config.model_copy(update={"blocks": [block], "dataset": DATASET_INFO, "description": "A pilot."})
    make_study(client, admin, config=config, slug=SLUG)
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, SLUG, paper_params(), participants=1,
                       concurrency=1)
    assert summary.errors == [] and summary.completed == 1
    with client.app.state.services.sessionmaker.begin() as session:
        study_id = session.scalar(select(Study.id).where(Study.slug == SLUG))
        session.add(FittedModel(study_id=study_id, fit_key="k", status=FitStatus.DONE, restarts=1, seed=3, p_high=0.5,
                                data_hash="d" * 64, study_versions=[1], participants=["P1"], n_trials=3,
                                code_version="test", document=FITTED, content_hash="c" * 64, loglik=-1.0,
                                evaluation_studies=[], finished_at=utcnow()))


def read_tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_the_dataset_follows_the_psych_ds_rules(database_url, tmp_path):
    client, admin = make_client(database_url=database_url)
    bot_study(client, admin)
    result = CliRunner().invoke(cli, ["export", SLUG, "--format", "psych-ds", "--out", str(tmp_path / "ds"),
                                      "--database-url", database_url])
    assert result.exit_code == 0, (result.output, result.exception)
    files = read_tree(tmp_path / "ds")

    assert {path.split("/")[0] for path in files} == CORE | {".psychdsignore"}
    description = check_json_ld(files)
    data = check_data_files(files)
    check_variables(files, description, data)
    check_codebook_agrees(files, description)
    check_the_rest(files, description)

    # The CSV files are the CSV export's, byte for byte.
    for name, path in data.items():
        exported = client.get(f"/api/admin/studies/{SLUG}/export/{name}", headers=auth(admin))
        assert files[path] == exported.content, name

    # The zip from the API holds the same dataset (only the manifest's time differs), and both are audited.
    response = client.get(f"/api/admin/studies/{SLUG}/export/psych-ds.zip", headers=auth(admin))
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    assert response.headers["content-disposition"] == f'attachment; filename="{SLUG}-psych-ds.zip"'
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert archive.testzip() is None
        zipped = {name: archive.read(name) for name in archive.namelist()}
    manifest = "documentation/manifest.json"
    assert zipped.keys() == files.keys()
    assert {k: v for k, v in zipped.items() if k != manifest} == {k: v for k, v in files.items() if k != manifest}
    with client.app.state.services.sessionmaker() as session:
        lines = session.scalars(select(AdminAudit).where(AdminAudit.action == "study.export")
                                .order_by(AdminAudit.id)).all()
    rows = {path: len(list(csv.reader(io.StringIO(files[path].decode())))) - 1 for path in data.values()}
    lines = [line for line in lines if line.detail["file"].startswith("psych-ds")]
    assert [line.detail["file"] for line in lines] == ["psych-ds directory", "psych-ds.zip", "psych-ds.zip"]
    assert lines[-1].detail["completed"] is True
    assert {k: v for k, v in lines[-1].detail["rows"].items() if k in rows} == rows == {
        k: v for k, v in lines[0].detail["rows"].items() if k in rows}


def check_json_ld(files: dict[str, bytes]) -> dict:
    """dataset_description.json: UTF-8 JSON (JsonInvalid, JsonEncodingError), schema.org context and Dataset type
    (IncorrectDatasetType, MissingDatasetType), the required fields (JsonKeyRequired), typed objects inside
    (ObjectTypeMissing)."""
    text = files["dataset_description.json"].decode("utf-8")  # raises unless UTF-8
    description = json.loads(text)
    assert description["@context"] in SCHEMA_ORG and description["@type"] in {"Dataset", "https://schema.org/Dataset"}
    assert REQUIRED_FIELDS <= description.keys()
    assert isinstance(description["name"], str) and description["name"] == "Psych-DS pilot"
    assert isinstance(description["description"], str) and description["description"].endswith("A pilot.")
    assert description["schemaVersion"] == "Psych-DS 1.5.0"
    # The recommended fields the study's configuration gives.
    assert description["author"] == DATASET_INFO.authors and description["keywords"] == DATASET_INFO.keywords
    assert (description["license"], description["citation"]) == (DATASET_INFO.license, DATASET_INFO.citation)
    assert untyped_objects(description) == []
    return description


def untyped_objects(node, path="") -> list[str]:
    """Objects (below the root) without an @type: the validator's ObjectTypeMissing warning."""
    if isinstance(node, list):
        return [p for i, item in enumerate(node) for p in untyped_objects(item, f"{path}[{i}]")]
    if not isinstance(node, dict):
        return []
    found = [path] if path and "@type" not in node else []
    return found + [p for key, value in node.items() for p in untyped_objects(value, f"{path}.{key}")]


def check_data_files(files: dict[str, bytes]) -> dict[str, str]:
    """Every data file is under data/, named by the spec's regex with official keywords only (FilenameKeyword-
    FormattingError, FilenameUnofficialKeywordWarning) and a valid CSV: UTF-8 without BOM, a header of unique names,
    every row as long as the header, no empty line, a row_id column unique if there is one. Returns the
    export file name -> dataset path."""
    data = {path: content for path, content in files.items() if path.startswith("data/") and path.endswith(".csv")}
    found = {}
    for path, content in data.items():
        name = path.removeprefix("data/")
        assert DATAFILE_REGEX.fullmatch(name), name
        pairs = [pair.split("-", 1) for pair in name.removesuffix("_data.csv").split("_")]
        assert {key for key, _ in pairs} <= OFFICIAL_KEYWORDS, name
        assert dict(pairs)["study"] == KEYWORD
        found[dict(pairs)["description"] + ".csv"] = path
        text = content.decode("utf-8")
        assert not text.startswith("\ufeff") and "\n\n" not in text and text.endswith("\n")
        header, *rows = list(csv.reader(io.StringIO(text)))
        assert header and len(set(header)) == len(header), name
        assert rows and all(len(row) == len(header) for row in rows), name
        if "row_id" in header:
            ids = [row[header.index("row_id")] for row in rows]
            assert len(set(ids)) == len(ids), name
    assert sorted(found) == sorted(["trials.csv", "surveys.csv", "participants.csv", "events.csv"])
    return found


def check_variables(files: dict[str, bytes], description: dict, data: dict[str, str]) -> None:
    """Columns against variableMeasured (CsvColumnMissingFromMetadata, VariableMissingFromCsvColumns): each file's
    compiled metadata (the dataset's, its sidecar's keys replacing the dataset's: the inheritance principle) lists
    exactly that file's columns, in file order, as its codebook does; the dataset's lists every column name of
    every data file, each once."""
    headers = {name: next(csv.reader(io.StringIO(files[path].decode()))) for name, path in data.items()}
    for name, path in data.items():
        sidecar = json.loads(files[path.removesuffix(".csv") + ".json"].decode("utf-8"))
        compiled = description | sidecar
        assert [v["name"] for v in compiled["variableMeasured"]] == headers[name] == columns(name)
        assert all(v["@type"] == "PropertyValue" for v in compiled["variableMeasured"])
        codebook = variable_measured(name)
        for variable, expected in zip(compiled["variableMeasured"], codebook, strict=True):
            if (name, variable["name"]) != ("surveys.csv", "questionnaire"):
                assert variable == expected
    names = [v["name"] for v in description["variableMeasured"]]
    assert len(names) == len(set(names)) and set(names) == {c for header in headers.values() for c in header}
    # A name shared with different meanings says what it means in each file; the instruments are on questionnaire.
    outcome = next(v for v in description["variableMeasured"] if v["name"] == "outcome")
    assert outcome["description"].startswith("In trials: Outcome of the autonomous attempt")
    assert "In participants: How the session ended" in outcome["description"]
    instrument = next(v for v in description["variableMeasured"] if v["name"] == "questionnaire")
    schaefer = next(i for i in instrument["valueReference"] if i["propertyID"] == "schaefer_14")
    assert schaefer["url"].startswith("https://doi.org/10.") and len(schaefer["valueReference"]) == 14
    assert (schaefer["minValue"], schaefer["maxValue"], schaefer["unitText"]) == (0, 100, "%")
    assert "Score: the mean" in schaefer["description"] and "Citation: Schaefer" in schaefer["description"]


def check_codebook_agrees(files: dict[str, bytes], description: dict) -> None:
    """documentation/codebook.csv and the JSON-LD come from one table: the same columns, meanings and units."""
    codebook = list(csv.DictReader(io.StringIO(files["documentation/codebook.csv"].decode("utf-8"))))
    assert len(codebook) == sum(map(len, CODEBOOK.values()))
    for name in ("trials.csv", "surveys.csv", "participants.csv", "events.csv"):
        rows = [r for r in codebook if r["file"] == name]
        for row, variable in zip(rows, variable_measured(name), strict=True):
            assert variable["name"] == row["column"] and variable["description"].startswith(row["meaning"])
            assert variable.get("unitText", "") == row["unit"]
            assert (f"Allowed values: {row['allowed_values']}" in variable["description"]) == bool(
                row["allowed_values"])


def check_the_rest(files: dict[str, bytes], description: dict) -> None:
    """.psychdsignore lists the folders that hold no data; the configuration versions and the fitted model are
    there with their provenance; the manifest's hashes are the files'."""
    # The schema's core rule names .psychds-ignore; the validator reads .psychdsignore: both, the same.
    assert files[".psychdsignore"] == files[".psychds-ignore"]
    ignored = [line for line in files[".psychdsignore"].decode().splitlines() if line and not line.startswith("#")]
    assert sorted(ignored) == ["analysis/", "documentation/", "materials/", "results/"]
    assert not [p for p in files if "/" not in p and p.endswith(".csv")]  # no data file outside data/
    config = json.loads(files["materials/study_config_v1.json"])
    versions = json.loads(files["materials/study_versions.json"])
    assert [v["version"] for v in versions] == [1] and versions[0]["file"] == "materials/study_config_v1.json"
    assert versions[0]["config_hash"] == config_hash(StudyConfig.model_validate(config)) and versions[0]["frozen_at"]
    assert "Version 1: config hash" in files["CHANGES.md"].decode()
    model_files = sorted(p for p in files if p.startswith("results/"))
    assert len(model_files) == 2
    document = json.loads(files[model_files[0]])
    provenance = json.loads(files[model_files[1]])
    assert document == FITTED and provenance["status"] == "done"
    assert provenance["provenance"]["study"] == SLUG and provenance["provenance"]["seed"] == 3
    readme = files["README.md"].decode()
    assert f"data/study-{KEYWORD}_description-trials_data.csv" in readme and model_files[0] in readme
    assert f"trustlab fit data/study-{KEYWORD}_description-trials_data.csv " in files["analysis/README.md"].decode()
    manifest = json.loads(files["documentation/manifest.json"])
    assert manifest["files"].keys() == files.keys() - {"documentation/manifest.json"}
    for path, entry in manifest["files"].items():
        assert entry["sha256"] == hashlib.sha256(files[path]).hexdigest() and entry["bytes"] == len(files[path])


def test_the_zip_needs_the_admin_token_and_a_known_study(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    path = "/api/admin/studies/s1/export/psych-ds.zip"
    assert client.get(path).status_code == 401
    missing = client.get(path.replace("/s1/", "/nope/"), headers=auth(admin))
    assert missing.status_code == 404 and missing.json() == {"detail": "no study 'nope'", "code": "not_found"}
    # A study without data is still a dataset: headers only, every column described.
    with zipfile.ZipFile(io.BytesIO(client.get(path, headers=auth(admin)).content)) as archive:
        description = json.loads(archive.read("dataset_description.json"))
        assert "author" not in description and description["name"]
        trials = archive.read("data/study-s1_description-trials_data.csv").decode()
    assert trials == ",".join(columns("trials.csv")) + "\n"
