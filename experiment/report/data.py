"""Reading an export directory (the files ``trustlab export`` writes) for the report.

Only ``trials.csv`` is required; ``surveys.csv``, ``participants.csv`` and
``manifest.json`` are optional, and a section that needs a missing file says
so. The model data (non-practice trials of non-excluded participants) are
read and checked by ``experiment.records``, which raises ``DataError`` when
no such trial is left. Column names are those of the export codebook
(``experiment.codebook.CODEBOOK``); cells are strings as in the CSV.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiment.records import DataError, read_model_trials, rows_to_sequence
from experiment.sequences import Sequence

Row = dict[str, str]

#: surveys.csv columns the report reads (a subset of the codebook's).
SURVEY_COLUMNS = ("participant_id", "context", "block", "block_name", "questionnaire", "item", "value",
                  "scored_value", "belief", "excluded")
#: participants.csv columns the report reads.
PARTICIPANT_COLUMNS = ("participant_id", "status", "block_order", "consented_at", "started_at", "excluded",
                       "exclusion_reason")


@dataclass(frozen=True)
class ExportData:
    source: Path
    #: Model data: non-practice rows of non-excluded participants, by participant, in trial order.
    trials: dict[str, list[Row]]
    all_trials: list[Row]  # every row of trials.csv (practice and excluded too)
    trial_columns: tuple[str, ...]
    surveys: list[Row] | None  # None: no surveys.csv
    participants: list[Row] | None  # None: no participants.csv
    manifest: dict[str, Any] | None

    def sequences(self) -> list[Sequence]:
        return [rows_to_sequence(rows, f"{self.source / 'trials.csv'}: ") for rows in self.trials.values()]

    @property
    def n_trials(self) -> int:
        return sum(len(rows) for rows in self.trials.values())

    def included_surveys(self) -> list[Row]:
        """Answers of participants not excluded from analysis."""
        return [r for r in self.surveys or [] if r.get("excluded") != "1"]


def load_export(directory: str | Path) -> ExportData:
    """The export in ``directory``; DataError if trials.csv is missing, malformed or has no model data."""
    source = Path(directory)
    if not source.is_dir():
        raise DataError(f"{source} is not a directory (expected an export with trials.csv)")
    trials = read_model_trials(source / "trials.csv")
    header, all_trials = _read_csv(source / "trials.csv", ())
    surveys = _optional_csv(source / "surveys.csv", SURVEY_COLUMNS)
    participants = _optional_csv(source / "participants.csv", PARTICIPANT_COLUMNS)
    return ExportData(source=source, trials=trials, all_trials=all_trials or [], trial_columns=tuple(header),
                      surveys=surveys, participants=participants, manifest=_manifest(source / "manifest.json"))


def _read_csv(path: Path, required: tuple[str, ...]) -> tuple[list[str], list[Row]]:
    try:
        with path.open(encoding="utf-8-sig", newline="") as handle:
            reader = csv.DictReader(handle)
            rows = list(reader)
            header = list(reader.fieldnames or [])
    except UnicodeDecodeError as exc:
        raise DataError(f"cannot read {path} as UTF-8 text: {exc}") from None
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}")
    return header, rows


def _optional_csv(path: Path, required: tuple[str, ...]) -> list[Row] | None:
    return _read_csv(path, required)[1] if path.exists() else None


def _manifest(path: Path) -> dict[str, Any] | None:
    if not path.exists():
        return None
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{path} is not valid JSON: {exc}") from None
    return document if isinstance(document, dict) else None


def number(row: Row, column: str) -> float | None:
    """A numeric cell as float; None when empty or absent (DataError when not a number)."""
    cell = row.get(column, "")
    if cell in ("", None):
        return None
    try:
        return float(cell)
    except ValueError:
        raise DataError(f"column {column!r} must hold numbers, got {cell!r}") from None
