"""Data-quality flags on plain records: native values (database) and CSV strings (exports)."""

from __future__ import annotations

import csv
import io
from datetime import UTC, datetime, timedelta

import pytest

from experiment.quality import QualityThresholds, flags_by_participant, participant_flags

NOW = datetime(2025, 3, 1, 12, 0, tzinfo=UTC)


def trial(*, complexity="high", robot_action="auto", human_action="rely", teleop_success=None, practice=False):
    return {"practice": practice, "complexity": complexity, "robot_action": robot_action,
            "human_action": human_action, "teleop_success": teleop_success}


def schaefer(values, context="before"):
    return [{"context": context, "questionnaire": "schaefer_14", "item": f"q{i}", "value": v}
            for i, v in enumerate(values)]


def codes(trials=(), answers=(), status="completed", last_seen_at=NOW, now=NOW, **thresholds):
    return [f.code for f in participant_flags(trials, answers, status=status, last_seen_at=last_seen_at, now=now,
                                              thresholds=QualityThresholds(**thresholds))]


def test_a_careful_participant_has_no_flags():
    trials = ([trial(human_action="intervene", teleop_success=True)] + [trial()] * 20
              + [trial(robot_action="ask", human_action="intervene", teleop_success=False)])
    assert codes(trials, schaefer([50, 60, 50] * 5)) == []


def test_straight_lining_needs_every_item_equal_and_enough_items():
    flags = participant_flags([], schaefer([70] * 14, "after:1") + schaefer([20, 30] * 7),
                              status="completed", last_seen_at=NOW)
    assert [(f.code, f.detail) for f in flags] == [
        ("straight_lining", "all 14 items of schaefer_14 (after:1) answered 70")]
    shelf = [{"context": "shelf:1:1", "questionnaire": "shelf_trust_reliance", "item": i, "value": 7}
             for i in ("trust", "reliance")]
    assert codes(answers=shelf) == []
    assert codes(answers=schaefer([40] * 4)) == []
    assert codes(answers=schaefer([40] * 4), min_straight_line_items=4) == ["straight_lining"]


def test_teleop_failed_when_every_teleoperation_failed():
    assert codes([trial(teleop_success=False, practice=True), trial(teleop_success=False)]) == ["teleop_failed"]
    assert codes([trial(teleop_success=False), trial(teleop_success=True)]) == []
    assert codes([trial(teleop_success=False)]) == []  # one is not a pattern


def test_never_and_always_intervened_count_scored_autonomous_attempts_only():
    relied = [trial()] * 15
    assert codes(relied) == ["never_intervened"]
    assert codes(relied[:14] + [trial(practice=True)]) == []
    assert codes(relied[:14] + [trial(complexity="low")]) == []
    assert codes(relied + [trial(human_action="intervene")]) == []
    assert codes(relied[:14] + [trial(human_action=None)]) == []  # undecided trials do not count
    intervened = [trial(complexity="low", human_action="intervene")] * 10
    assert codes(intervened) == ["always_intervened"]
    assert codes(intervened + [trial(robot_action="ask", human_action="intervene")] * 3) == ["always_intervened"]
    assert codes(intervened + [trial()]) == []


def test_idle_only_while_active_and_only_when_now_is_given():
    long_ago = NOW - timedelta(minutes=5)
    assert codes(status="active", last_seen_at=long_ago) == ["idle"]
    assert codes(status="active", last_seen_at=NOW - timedelta(seconds=59)) == []
    assert codes(status="completed", last_seen_at=long_ago) == []
    assert codes(status="active", last_seen_at=long_ago, now=None) == []
    [flag] = participant_flags([], [], status="active", last_seen_at=long_ago, now=NOW)
    assert flag.detail == "active but not seen for 5 min"


def _csv(rows):
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else int(v) if isinstance(v, bool) else v for k, v in row.items()})
    return list(csv.DictReader(io.StringIO(buffer.getvalue())))


def test_export_rows_give_the_same_flags_as_native_records():
    trials = ([{"participant_id": "a", **trial(teleop_success=False)} for _ in range(15)]
              + [{"participant_id": "b", **trial(human_action="intervene", teleop_success=True)}])
    answers = [{"participant_id": "b", **a} for a in schaefer([30] * 14)]
    participants = [{"participant_id": "a", "status": "active", "last_seen_at": "2025-03-01T11:50:00.000000Z"},
                    {"participant_id": "b", "status": "completed", "last_seen_at": "2025-03-01T11:00:00.000000Z"},
                    {"participant_id": "c", "status": "declined", "last_seen_at": ""}]
    native = flags_by_participant(trials, answers, participants, now=NOW)
    exported = flags_by_participant(_csv(trials), _csv(answers), _csv(participants), now=NOW)
    assert exported == native
    assert {k: [f.code for f in v] for k, v in native.items()} == {
        "a": ["teleop_failed", "never_intervened", "idle"], "b": ["straight_lining"], "c": []}


def test_a_malformed_flag_cell_is_an_error_not_a_guess():
    with pytest.raises(ValueError, match="flag must be 0 or 1"):
        participant_flags([trial(teleop_success="yes")], [], status="completed", last_seen_at=None)


def test_text_and_choice_answers_are_not_ratings():
    demographics = [{"context": "before", "questionnaire": "demographics", "item": f"d{i}", "value": None}
                    for i in range(6)]
    csv_cells = [dict(a, value="") for a in demographics]
    assert codes(answers=demographics) == codes(answers=csv_cells) == []


def test_attention_failures_are_flagged_from_records_and_export_rows():
    flags = participant_flags([], [], status="completed", last_seen_at=NOW, attention_failures=2)
    assert [(f.code, f.detail) for f in flags] == [("attention_failed", "failed 2 attention checks")]
    assert participant_flags([], [], status="completed", last_seen_at=NOW, attention_failures=0) == []
    rows = [{"participant_id": "P1", "status": "completed", "attention_failures": "1"},
            {"participant_id": "P2", "status": "completed", "attention_failures": "0"}]
    by_id = flags_by_participant([], [], rows)
    assert [f.code for f in by_id["P1"]] == ["attention_failed"] and by_id["P2"] == []


def test_a_window_opened_at_the_wait_limit_is_flagged_with_how_many_were_scored():
    proven = [trial() | {"window_opened_by": view} for view in ("3d", "2d", "text", None, "")]
    assert "scene_not_proven" not in codes(proven)
    unproven = [trial() | {"window_opened_by": "wait_limit"}, trial(practice=True) | {"window_opened_by": "wait_limit"}]
    [flag] = [f for f in participant_flags(proven + unproven, [], status="completed", last_seen_at=NOW)
              if f.code == "scene_not_proven"]
    assert flag.detail.startswith("2 decision window(s) (1 scored) opened at the wait limit")
