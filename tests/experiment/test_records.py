import csv
import io
from dataclasses import fields

import pytest

from experiment.codebook import columns
from experiment.records import CSV_COLUMNS, MODEL_COLUMNS, DataError, TrialRecord, read_sequences, write_trials_csv
from experiment.task import Complexity as C
from experiment.task import Experience as E
from experiment.task import HumanAction as O
from experiment.task import Outcome
from experiment.task import RobotAction as A

HEADER = ",".join(MODEL_COLUMNS)


def write(tmp_path, text):
    path = tmp_path / "trials.csv"
    path.write_text(text, encoding="utf-8")
    return path


def test_model_columns_lead_the_export():
    assert CSV_COLUMNS[:len(MODEL_COLUMNS)] == list(MODEL_COLUMNS)


def test_records_are_written_with_the_exports_columns_and_cells():
    """The simulator's trials.csv is the export's file: same header, every record field in a column, same cells."""
    assert {f.name for f in fields(TrialRecord)} <= set(CSV_COLUMNS) and CSV_COLUMNS == columns("trials.csv")
    record = TrialRecord("p1", 1, 1, C.LOW, A.AUTO, O.RELY, Outcome.SUCCESS, E.POSITIVE, reward=-4.0, score=0.1 + 0.2,
                         belief_before=1 / 3, seed=7)
    buffer = io.StringIO()
    write_trials_csv([record], buffer)
    header, row = list(csv.reader(io.StringIO(buffer.getvalue())))
    cells = dict(zip(header, row, strict=True))
    assert header == CSV_COLUMNS
    assert (cells["reward"], cells["score"], cells["belief_before"], cells["belief_after"], cells["seed"]) == \
        ("-4", "0.3", "0.3333333333", "", "7")
    assert cells["study"] == cells["decision_time_ms"] == ""


def test_round_trip_skips_practice_and_excluded(tmp_path):
    records = [
        TrialRecord("p1", 1, 1, C.LOW, A.AUTO, O.RELY, Outcome.SUCCESS, E.POSITIVE, practice=True),
        TrialRecord("p1", 1, 2, C.HIGH, A.ASK, O.INTERVENE, Outcome.NONE, E.POSITIVE),
        TrialRecord("p1", 1, 1, C.HIGH, A.AUTO, O.INTERVENE, Outcome.NONE, E.NEGATIVE),
        TrialRecord("p2", 1, 1, C.LOW, A.AUTO, O.RELY, Outcome.FAILURE, E.NEGATIVE, excluded=True),
        TrialRecord("p3", 2, 1, C.LOW, A.AUTO, O.RELY, Outcome.FAILURE, E.NEGATIVE),
        TrialRecord("p3", 1, 1, C.LOW, A.AUTO, O.RELY, Outcome.SUCCESS, E.POSITIVE),
    ]
    buffer = io.StringIO()
    assert write_trials_csv(records, buffer) == len(records)
    ids, sequences = read_sequences(write(tmp_path, buffer.getvalue()))
    assert ids == ["p1", "p3"]
    # ordered by (block, trial), not file order
    assert sequences[0].complexity.tolist() == [1, 1] and sequences[0].robot_action.tolist() == [0, 1]
    assert sequences[1].experience.tolist() == [1, 0]


@pytest.mark.parametrize(("text", "message"), [
    ("", "empty"),
    ("participant_id,block\np,1\n", "missing column"),
    (HEADER + "\np,1,1,medium,auto,rely,success,positive,0,0\n", "complexity must be one of"),
    (HEADER + "\np,1,0,low,auto,rely,success,positive,0,0\n", "trial must be a whole number"),
    (HEADER + "\np,1,1,low,auto,rely,success,positive,1,0\n", "no trials left"),
    (HEADER + "\np,1,1,low,auto,rely,success,positive,0,0\np,1,1,low,auto,rely,success,positive,0,0\n",
     "duplicate trial"),
    (HEADER + "\np,1,1,low,ask,rely,none,negative,0,0\n", "must be 'intervene'"),
])
def test_malformed_input_names_the_problem(tmp_path, text, message):
    with pytest.raises(DataError, match=message):
        read_sequences(write(tmp_path, text))


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_sequences(tmp_path / "nope.csv")
