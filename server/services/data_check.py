"""Stored values an export cannot write as they are, found and (on request) repaired: ``trustlab check-data``.

Before requests were read strictly (``server.strict_json``), a client could store strings with lone surrogates,
NaN or Infinity, and objects nested hundreds of levels deep. Exports write such values repaired
(``experiment.writable``); this check finds them in the columns participants fill, and ``repair`` stores that same
repaired form, so the database and its exports agree. Each repair leaves an audit line (``data.repair``) naming
the table, column, row and the kinds of problem, never the value (it is the participant's data).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Text, cast, select, update
from sqlalchemy.orm import Session

from experiment.writable import (
    MAX_DEPTH,
    TOO_DEEP,
    cut_deep_json_text,
    problems,
    repair_json,
    repair_text,
    text_problems,
)
from server.models import Answer, AuditAction, Event, Participant, Study
from server.services.audit import audit

#: Rows read per query.
PAGE_ROWS = 1000
#: Problems of a stored text that could not be parsed as it is (``_read``).
NOT_JSON_PROBLEM = "not JSON at all (written as a JSON string of the stored text)"
TOO_DEEP_PROBLEM = f"nested deeper than {MAX_DEPTH} levels (written as {TOO_DEEP!r})"


@dataclass(frozen=True)
class Checked:
    """One column participants fill: ``kind`` is ``json`` or ``text``."""

    table: str
    column: str
    kind: str
    attribute: Any
    study: Any
    participant: Any


#: The columns checked (every JSON or text column a participant's request fills).
CHECKED = (
    Checked("event", "payload", "json", Event.payload, Event.study_id, Event.participant_id),
    Checked("answer", "text", "text", Answer.text, Participant.study_id, Answer.participant_id),
    Checked("participant", "recruitment", "json", Participant.recruitment, Participant.study_id, Participant.id),
    Checked("participant", "survey_draft", "json", Participant.survey_draft, Participant.study_id, Participant.id),
    Checked("participant", "external_id", "text", Participant.external_id, Participant.study_id, Participant.id),
)


@dataclass(frozen=True)
class Problem:
    study: str
    participant: str | None  # public id
    table: str
    column: str
    row_id: int
    problems: tuple[str, ...]
    repaired_value: Any

    def line(self) -> str:
        return (f"{self.study}\t{self.participant or '-'}\t{self.table}.{self.column}\trow {self.row_id}\t"
                f"{'; '.join(self.problems)}")


def find_problems(session: Session) -> Iterator[Problem]:
    """Every stored value of ``CHECKED`` that an export would have to repair, page by page."""
    slugs = dict(session.execute(select(Study.id, Study.slug)).all())
    public_ids = dict(session.execute(select(Participant.id, Participant.public_id)).all())
    for checked in CHECKED:
        table = checked.attribute.class_
        row_id = table.id
        query = select(row_id, cast(checked.attribute, Text), checked.study, checked.participant)
        if table is Answer:
            query = query.join(Participant, Participant.id == Answer.participant_id)
        last = 0
        while True:
            rows = session.execute(query.where(row_id > last).order_by(row_id).limit(PAGE_ROWS)).all()
            for rid, stored, study_id, participant_id in rows:
                if stored is None:
                    continue
                if checked.kind == "text":
                    found, repaired = text_problems(stored), repair_text(stored)
                else:
                    value, unreadable = _read(stored)
                    found, repaired = problems(value), None
                    if unreadable:  # cut before parsing, or kept as a string: the problem was in the stored text
                        found = [unreadable, *found]
                    if found:
                        repaired = repair_json(value)
                if found:
                    yield Problem(slugs.get(study_id, f"study {study_id}"), public_ids.get(participant_id),
                                  checked.table, checked.column, rid, tuple(found), repaired)
            if len(rows) < PAGE_ROWS:
                break
            last = rows[-1][0]


def repair(session: Session, problem: Problem) -> None:
    """Store ``problem``'s repaired value and an audit line (no value in it)."""
    checked = next(c for c in CHECKED if (c.table, c.column) == (problem.table, problem.column))
    table = checked.attribute.class_
    session.execute(update(table).where(table.id == problem.row_id)
                    .values({checked.column: problem.repaired_value}))
    study_id = session.scalar(select(Study.id).where(Study.slug == problem.study))
    audit(session, AuditAction.DATA_REPAIR, study_id=study_id, participant=problem.participant, table=problem.table,
          column=problem.column, row_id=problem.row_id, problems=list(problem.problems))



def _read(stored: str) -> tuple[Any, str | None]:
    """A stored JSON text parsed leniently (NaN, lone surrogates pass) and, if it could not be parsed as it is,
    the problem: too deep for the parser (cut first, as ``experiment.writable.read_json_text`` does) or not JSON at
    all (kept as a string)."""
    try:
        return json.loads(stored), None
    except RecursionError:
        pass
    except ValueError:
        return stored, NOT_JSON_PROBLEM
    try:
        return json.loads(cut_deep_json_text(stored)), TOO_DEEP_PROBLEM
    except ValueError:
        return stored, NOT_JSON_PROBLEM
