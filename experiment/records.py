"""Trial records, and reading and writing ``trials.csv`` (SPEC §9).

The model-fitting columns (``MODEL_COLUMNS``) have fixed names and values:
``participant_id``, ``block`` (position of the block in the participant's
order, from 1), ``trial`` (index within block, from 1), ``complexity``,
``robot_action``, ``human_action``, ``outcome``, ``experience``,
``practice`` and ``excluded`` (``0``/``1``). Other columns may follow;
readers ignore them. The file's columns and cell format are
``experiment.codebook``'s, the same as the server's export.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Collection, Iterable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TextIO

import numpy as np

from experiment.codebook import MODEL_COLUMNS, TableWriter, columns
from experiment.sequences import Sequence
from experiment.task import Complexity, Experience, HumanAction, Outcome, RobotAction


class DataError(ValueError):
    """Input data that cannot be used, with a one-line reason naming the problem."""


@dataclass(frozen=True)
class TrialRecord:
    """One trial as stored and exported (the leading fields are the model columns)."""

    participant_id: str
    block: int
    trial: int
    complexity: Complexity
    robot_action: RobotAction
    human_action: HumanAction
    outcome: Outcome
    experience: Experience
    practice: bool = False
    excluded: bool = False
    block_name: str = ""
    policy: str = ""
    trial_overall: int = 0
    shelf: int = 0
    reward: float = 0.0
    score: float = 0.0
    belief_before: float = math.nan
    belief_after: float = math.nan
    policy_belief: float = math.nan
    #: Provenance (``experiment.provenance.TrialProvenance``): the content hash of the model the block's
    #: policy and beliefs used, the hash of the block's resolved policy, and the study seed.
    model_hash: str = ""
    policy_hash: str = ""
    seed: int | None = None

    def values(self) -> tuple[object, ...]:
        """The record as a ``trials.csv`` row of raw values: what the simulator does not know (the study's slug
        and version, times, teleoperation details) is None, an empty cell."""
        known = {f.name: getattr(self, f.name) for f in fields(self)}
        return tuple(known.get(name) for name in CSV_COLUMNS)


#: The columns of ``trials.csv`` (the export's; ``TrialRecord`` fills those it has).
CSV_COLUMNS = columns("trials.csv")


def write_trials_csv(records: Iterable[TrialRecord], out: TextIO) -> int:
    """Write records as ``trials.csv`` (the export's columns and format); returns the number of rows."""
    return TableWriter("trials.csv", out).write_all(record.values() for record in records)


def write_survey_rows(rows: Iterable[dict[str, object]], out: TextIO) -> int:
    """Write rows (cells by column name; missing ones empty) as ``surveys.csv``; returns the number of rows."""
    names = columns("surveys.csv")
    return TableWriter("surveys.csv", out).write_all(tuple(row.get(name) for name in names) for row in rows)


def read_model_trials(path: str | Path) -> dict[str, list[dict[str, str]]]:
    """Validated non-practice, non-excluded rows of a ``trials.csv``, grouped by participant and ordered.

    Raises DataError with a one-line reason for a missing file, a missing
    column, an unknown value, a duplicate trial or an empty data set.
    """
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"file not found: {path}") from None
    except (UnicodeDecodeError, IsADirectoryError) as exc:
        raise DataError(f"cannot read {path} as UTF-8 text: {exc}") from None
    return parse_model_trials(io.StringIO(text), path)


def parse_model_trials(lines: Iterable[str], path: str | Path,
                       keep: Collection[str] | None = None) -> dict[str, list[dict[str, str]]]:
    """``read_model_trials`` on the lines of a ``trials.csv`` (e.g. streamed from an export).

    ``path`` names the source in error messages. ``keep``: the columns kept in
    each row besides the model columns (all columns when None).
    """
    reader = csv.DictReader(lines)
    kept = None if keep is None else [*MODEL_COLUMNS, *keep]
    missing = [c for c in kept or MODEL_COLUMNS if c not in (reader.fieldnames or [])]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}" if reader.fieldnames
                        else f"{path}: the file is empty")
    by_participant: dict[str, dict[tuple[int, int], dict[str, str]]] = {}
    for line, row in enumerate(reader, start=2):
        _check_row(path, line, row)
        if row["practice"] == "1" or row["excluded"] == "1":
            continue
        key = (_positive_int(path, line, row, "block"), _positive_int(path, line, row, "trial"))
        trials = by_participant.setdefault(row["participant_id"], {})
        if key in trials:
            raise DataError(f"{path}:{line}: duplicate trial {key[1]} of block {key[0]} for participant "
                            f"{row['participant_id']!r}")
        trials[key] = row if kept is None else {c: row[c] for c in kept}
    if not by_participant:
        raise DataError(f"{path}: no trials left after removing practice and excluded rows")
    return {pid: [trials[k] for k in sorted(trials)] for pid, trials in by_participant.items()}


def _check_row(path: str | Path, line: int, row: dict[str, str]) -> None:
    for column, allowed in MODEL_COLUMNS.items():
        value = row.get(column)
        if value is None or value == "" and column == "participant_id":
            raise DataError(f"{path}:{line}: empty {column}")
        if allowed is not None and value not in allowed:
            raise DataError(f"{path}:{line}: {column} must be one of {', '.join(allowed)}, got {value!r}")


def _positive_int(path: str | Path, line: int, row: dict[str, str], column: str) -> int:
    try:
        value = int(row[column])
    except ValueError:
        value = 0
    if value < 1:
        raise DataError(f"{path}:{line}: {column} must be a whole number from 1, got {row[column]!r}")
    return value


def rows_to_sequence(rows: list[dict[str, str]], where: str = "") -> Sequence:
    """A participant's ordered rows as a model ``Sequence`` (checks the trial is consistent)."""
    codes = []
    for row in rows:
        c, a, o = Complexity(row["complexity"]), RobotAction(row["robot_action"]), HumanAction(row["human_action"])
        if a == RobotAction.ASK and o == HumanAction.RELY:
            raise DataError(f"{where}participant {row['participant_id']!r}, block {row['block']}, trial "
                            f"{row['trial']}: "
                            "the robot asked, so the human action must be 'intervene'")
        codes.append((c.code, a.code, o.code, Experience(row["experience"]).code))
    columns = np.array(codes, dtype=np.int8).reshape(len(codes), 4).T.copy()  # (4, T)
    return Sequence(columns[0], columns[1], columns[2], columns[3])


def read_sequences(path: str | Path) -> tuple[list[str], list[Sequence]]:
    """Participant ids and their model sequences (blocks concatenated in order) from a ``trials.csv``."""
    return grouped_sequences(read_model_trials(path), path)


def grouped_sequences(grouped: dict[str, list[dict[str, str]]], path: str | Path) -> tuple[list[str], list[Sequence]]:
    """Participant ids and model sequences of rows grouped by ``read_model_trials``/``parse_model_trials``."""
    return list(grouped), [rows_to_sequence(rows, f"{path}: ") for rows in grouped.values()]
