"""Stored values an export cannot write as they are, found and (on request) repaired: ``trustlab check-data``.

Before requests were read strictly (``server.strict_json``), a client could store strings with lone surrogates,
NaN or Infinity, and objects nested hundreds of levels deep. Exports write such values repaired
(``experiment.writable``); this check finds them in the columns participants fill, and ``repair`` stores that same
repaired form, so the database and its exports agree. Each repair leaves an audit line (``data.repair``) naming
the table, column, row and the kinds of problem, never the value (it is the participant's data).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Text, cast, select, update
from sqlalchemy.orm import Session

from experiment.writable import problems, repair_json, repair_text, text_problems
from server.models import Answer, Event, Participant, Study
from server.services.audit import audit

#: Rows read per query.
PAGE_ROWS = 1000
#: The recursion limit a value too deep for the default one is parsed with (the old server stored values up to
#: about 1,000 levels deep: as deep as its parser went).
DEEP_PARSE_LIMIT = 20_000


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
                    value = _parse(stored)
                    found, repaired = problems(value), None
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
    audit(session, "data.repair", study_id=study_id, participant=problem.participant, table=problem.table,
          column=problem.column, row_id=problem.row_id, problems=list(problem.problems))


def _parse(stored: str) -> Any:
    """A stored JSON text as Python reads it (leniently: NaN, lone surrogates), however deep."""
    try:
        return json.loads(stored)
    except RecursionError:
        limit = sys.getrecursionlimit()
        sys.setrecursionlimit(max(limit, DEEP_PARSE_LIMIT))
        try:
            return json.loads(stored)
        finally:
            sys.setrecursionlimit(limit)
