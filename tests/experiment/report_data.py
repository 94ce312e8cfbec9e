"""Export directories made from simulated studies, for the report's tests (and sample reports).

``trials.csv`` holds the simulator's records as they are. The simulator has no surveys, so
``surveys.csv`` is synthesised in the export's format: after each shelf a trust answer that
rises with the model belief stored with it and a reliance answer that rises with trust; Schaefer
answers (where the design asks them) around a level that rises with the belief at that point.
``participants.csv`` lists every simulated participant as completed, plus optional extras.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from experiment.config import StudyConfig
from experiment.flow import BEFORE_BLOCKS, after_block_context, shelf_context
from experiment.instruments import SCHAEFER_14
from experiment.iohmm import IOHMMParams, paper_params
from experiment.questionnaires import reverse_code
from experiment.records import TrialRecord, write_trials_csv
from experiment.simulate import StudySimulation, simulate_study
from experiment.templates import template

SURVEY_HEADER = ["participant_id", "study", "version", "context", "block", "block_name", "shelf", "questionnaire",
                 "item", "value", "scored_value", "belief", "answered_at", "excluded"]
PARTICIPANT_HEADER = ["participant_id", "external_id", "study", "version", "status", "block_order", "joined_at",
                      "consented_at", "started_at", "finished_at", "last_seen_at", "score", "compensation",
                      "completion_code", "excluded", "exclusion_reason", "recruitment"]
WHEN = "2025-01-01T00:00:00.000000Z"


def write_simulated_export(directory: Path, design: str | StudyConfig, n_participants: int, *, seed: int = 0,
                           model: IOHMMParams | None = None, declined: int = 0,
                           excluded: tuple[str, ...] = ()) -> StudySimulation:
    """Simulate ``n_participants`` of ``design`` and write an export directory; returns the simulation."""
    config = template(design) if isinstance(design, str) else design
    sim = simulate_study(config, model or paper_params(), n_participants, seed=seed)
    directory.mkdir(parents=True, exist_ok=True)
    records = [r if r.participant_id not in excluded else _excluded(r) for r in sim.records()]
    with (directory / "trials.csv").open("w", encoding="utf-8", newline="") as handle:
        write_trials_csv(records, handle)
    rng = np.random.default_rng(seed)
    surveys = [row for p in sim.participants for row in _surveys(config, p.records, rng, p.participant_id in excluded)]
    _write(directory / "surveys.csv", SURVEY_HEADER, surveys)
    people = [_participant(p.participant_id, "|".join(p.block_order), p.participant_id in excluded)
              for p in sim.participants]
    people += [_participant(f"declined-{i}", "", False, status="declined") for i in range(declined)]
    _write(directory / "participants.csv", PARTICIPANT_HEADER, people)
    return sim


def _excluded(record: TrialRecord) -> TrialRecord:
    return TrialRecord(**{**record.__dict__, "excluded": True})


def _write(path: Path, header: list[str], rows: list[dict[str, object]]) -> None:
    with path.open("w", encoding="utf-8", newline="") as handle:
        writer = csv.DictWriter(handle, header, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)


def _participant(pid: str, order: str, excluded: bool, status: str = "completed") -> dict[str, object]:
    done = status == "completed"
    return {"participant_id": pid, "external_id": "", "study": "sim", "version": 1, "status": status,
            "block_order": order, "joined_at": WHEN, "consented_at": WHEN if done else "",
            "started_at": WHEN if done else "", "finished_at": WHEN, "last_seen_at": WHEN, "score": "",
            "compensation": "", "completion_code": "", "excluded": int(excluded),
            "exclusion_reason": "inattentive (test)" if excluded else "", "recruitment": "{}"}


def _answer(pid: str, context: str, block: int | str, block_name: str, shelf: int | str, questionnaire: str,
            item: str, value: float, scored: float, belief: float, excluded: bool) -> dict[str, object]:
    return {"participant_id": pid, "study": "sim", "version": 1, "context": context, "block": block,
            "block_name": block_name, "shelf": shelf, "questionnaire": questionnaire, "item": item, "value": value,
            "scored_value": scored, "belief": belief, "answered_at": WHEN, "excluded": int(excluded)}


def _surveys(config: StudyConfig, records: list[TrialRecord], rng: np.random.Generator,
             excluded: bool) -> list[dict[str, object]]:
    pid = records[0].participant_id
    rows = []
    if SCHAEFER_14.id in config.questionnaires_before:
        rows += _schaefer(pid, BEFORE_BLOCKS, "", "", records[0].belief_before, rng, excluded)
    for i, r in enumerate(records):
        last_of_shelf = i + 1 == len(records) or (records[i + 1].block, records[i + 1].shelf) != (r.block, r.shelf)
        if last_of_shelf:
            trust = float(np.clip(np.rint(rng.normal(2.5 + 6.5 * r.belief_after, 1.2)), 0, 10))
            reliance = float(np.clip(np.rint(rng.normal(0.6 * trust + 3.3, 1.0)), 0, 10))
            context = shelf_context(r.block, r.shelf)
            for item, value in (("trust", trust), ("reliance", reliance)):
                rows.append(_answer(pid, context, r.block, r.block_name, r.shelf, "shelf_trust_reliance", item,
                                    value, value, r.belief_after, excluded))
        block_ends = i + 1 == len(records) or records[i + 1].block != r.block
        if block_ends and SCHAEFER_14.id in config.block(r.block_name).questionnaires_after:
            rows += _schaefer(pid, after_block_context(r.block), r.block, r.block_name, r.belief_after, rng, excluded)
    return rows


def _schaefer(pid: str, context: str, block: int | str, block_name: str, belief: float, rng: np.random.Generator,
              excluded: bool) -> list[dict[str, object]]:
    level = 40 + 40 * belief
    rows = []
    for item in SCHAEFER_14.items:
        agree = float(np.clip(np.rint(rng.normal(level, 12) / 10) * 10, 0, 100))
        value = 100 - agree if item.reverse_coded else agree
        rows.append(_answer(pid, context, block, block_name, "", SCHAEFER_14.id, item.id, value,
                            reverse_code(SCHAEFER_14, item, value), belief, excluded))
    return rows
