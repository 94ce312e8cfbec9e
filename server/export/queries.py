"""What each export file selects: for every codebook column, where its values come from.

A file's columns, their order and their types are declared once, in
``experiment.codebook.CODEBOOK``. Here each file maps every one of those
column names to its source: an SQL expression, an SQL expression whose values
Python converts before they are formatted (:class:`Converted`, e.g. the block
order joined by ``|``), or a value Python fills in on every row
(:class:`Filled`: the study slug, the same for the whole export, so it is not
selected). The select list is generated in codebook order, each expression
labelled with its column's name, and rows are put back together in that
order: no position is written by hand. A codebook column without a source, or
a source without a codebook column, stops the import (``FileQuery`` checks).

Rows are ordered by participant (database id, i.e. join order), then by record
id (trials and answers in the order they happened); events by id. Those keys
are what keyset pagination pages by (``server.export.pages``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import DateTime, Select, Text, TypeDecorator, cast, func, or_, select, type_coerce
from sqlalchemy.orm import Session

from experiment.attention import attention_passed, stored_answer
from experiment.codebook import EXPORT_FILES, columns
from experiment.events import EventKind
from experiment.outcomes import outcome_of_status
from experiment.privacy import pseudonym, pseudonymised_parameters
from experiment.questionnaires import Item, Questionnaire
from experiment.writable import read_json_text
from server.models import Answer, Event, Participant, StudyVersion, Trial
from server.services.joining import app_secret
from server.services.studies import get_study


@dataclass(frozen=True)
class ExportTarget:
    """The study an export is for (resolved once, before streaming).

    ``include_preview``: the experimenter's preview sessions too (left out by default: they are not data).
    ``instruments``: the questionnaires of each configuration version, by (version number, questionnaire id), for
    the provenance columns of surveys.csv.
    ``pseudonym_key``: the study's own key (``experiment.privacy.pseudonym``) when the export pseudonymises the
    recruitment ids (participants.csv ``external_id`` and the values of ``recruitment``); None: written as stored.
    """

    study_id: int
    slug: str
    title: str
    include_preview: bool = False
    instruments: Mapping[tuple[int, str], Questionnaire] = field(default_factory=dict, compare=False, hash=False)
    pseudonym_key: bytes | None = field(default=None, compare=False, hash=False, repr=False)

    @property
    def pseudonymised(self) -> bool:
        return self.pseudonym_key is not None

    def instrument(self, version: int | None, questionnaire: str | None) -> Questionnaire | None:
        return self.instruments.get((version, questionnaire)) if version is not None and questionnaire else None

    def item(self, version: int | None, questionnaire: str | None, item_id: str | None) -> Item | None:
        q = self.instrument(version, questionnaire)
        return next((item for item in q.items if item.id == item_id), None) if q is not None else None


def export_target(session: Session, slug: str, *, include_preview: bool = False,
                  pseudonymise: bool = False) -> ExportTarget:
    """The study with ``slug``; raises ``NotFound`` (404) naming it otherwise. With ``pseudonymise``, the study's
    pseudonym key (made on first use and kept in the database, like the server's other secrets)."""
    study = get_study(session, slug)
    key = app_secret(session, pseudonym_key_name(study.id)) if pseudonymise else None
    return ExportTarget(study.id, study.slug, study.title, include_preview=include_preview,
                        instruments=_instruments(session, study.id), pseudonym_key=key)


def pseudonym_key_name(study_id: int) -> str:
    """The name of a study's pseudonym key among the server's secrets (``app_secret``)."""
    return f"pseudonym_key:{study_id}"


def participant_condition(target: ExportTarget) -> Any:
    """The condition on ``Participant`` rows an export reads: the study's, previews only if asked for."""
    if target.include_preview:
        return Participant.study_id == target.study_id
    return (Participant.study_id == target.study_id) & Participant.preview.is_(False)


def _instruments(session: Session, study_id: int) -> dict[tuple[int, str], Questionnaire]:
    """Every version's questionnaires as its stored document holds them (a version whose document does not read
    leaves its rows' provenance cells empty rather than stopping the export)."""
    found: dict[tuple[int, str], Questionnaire] = {}
    for version, config in session.execute(select(StudyVersion.version, StudyVersion.config)
                                           .where(StudyVersion.study_id == study_id)):
        for document in (config or {}).get("questionnaires", []):
            try:
                q = Questionnaire.model_validate(document)
            except ValueError:
                continue
            found[(version, q.id)] = q
    return found


# -- sources ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Converted:
    """A column selected by SQL whose values ``convert`` turns into what is formatted."""

    expression: Any
    convert: Callable[[Any], Any]


@dataclass(frozen=True)
class Filled:
    """A column with one value for the whole export, filled in by Python rather than selected."""

    value: Callable[[ExportTarget], Any]


@dataclass(frozen=True)
class Keyed:
    """A column selected by SQL whose values ``convert(target, value)`` turns into what is formatted (the export's
    choices, e.g. pseudonymised ids)."""

    expression: Any
    convert: Callable[[ExportTarget, Any], Any]


@dataclass(frozen=True)
class Derived:
    """A column computed by Python from other columns of the same row (``inputs``, by name) and the target:
    ``derive(target, *values)``."""

    inputs: tuple[str, ...]
    derive: Callable[..., Any]


#: The study slug (every row of an export belongs to the one study).
STUDY_SLUG = Filled(lambda target: target.slug)

#: Where a column's values come from: an SQL expression, a ``Converted`` one, or ``Filled``.
Source = Any


class _StoredDateTime(TypeDecorator[Any]):
    """A ``TZDateTime`` column read as SQLite stores it (UTC text), skipping the parse to ``datetime``
    that ``experiment.codebook``'s ``_format_datetime`` would undo; other backends return datetimes as usual."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def result_processor(self, dialect: Any, coltype: Any) -> Any:
        if dialect.name == "sqlite":
            return None
        return super().result_processor(dialect, coltype)


def _dt(column: Any) -> Any:
    return type_coerce(column, _StoredDateTime())


def _stored_json(column: Any) -> Converted:
    """A JSON column participants fill, read as its stored text and parsed here: a value nested too deep for the
    driver's parser (stored before requests were read strictly) is read too, cut at ``experiment.writable``'s
    depth, instead of stopping the export."""
    return Converted(cast(column, Text), read_json_text)


class FileQuery:
    """How one export file is read: each codebook column's source, the rows, and their keyset key.

    ``sources`` maps every column of ``file`` in the codebook to its source (in any order); anything else
    raises ``ValueError``. ``rows`` adds the joins and the study's condition to a select of the file's
    columns. ``keys`` are ordered, indexed and unique; pagination appends them to the select.
    ``per_participant``: read participant by participant (``keys[0]`` is the participant id, see
    ``server.export.pages``).
    """

    def __init__(self, file: str, sources: Mapping[str, Source],
                 rows: Callable[[Select[Any], ExportTarget], Select[Any]], keys: tuple[Any, ...], *,
                 per_participant: bool = False) -> None:
        names = columns(file)
        missing, unknown = [n for n in names if n not in sources], [n for n in sources if n not in names]
        if missing or unknown:
            raise ValueError(f"{file}: codebook columns without a source: {missing or 'none'}; "
                             f"sources without a codebook column: {unknown or 'none'}")
        self.file, self.keys, self.per_participant, self._rows = file, keys, per_participant, rows
        #: Every column in file order, with its source.
        self.sources: tuple[tuple[str, Source], ...] = tuple((n, sources[n]) for n in names)
        self._selected = [_expression(source).label(n) for n, source in self.sources
                          if not isinstance(source, Filled | Derived)]
        self._filled = [(at, source) for at, (_, source) in enumerate(self.sources) if isinstance(source, Filled)]
        self._derived = [(at, source.derive, [names.index(i) for i in source.inputs])
                         for at, (_, source) in enumerate(self.sources) if isinstance(source, Derived)]
        self._python = sorted([at for at, _ in self._filled] + [at for at, _, _ in self._derived])
        if any(isinstance(sources[i], Derived) for _, _, inputs in self._derived
               for i in map(names.__getitem__, inputs)):
            raise ValueError(f"{file}: a derived column's inputs must be other columns")
        self._converted = [(at, source.convert) for at, (_, source) in enumerate(self.sources)
                           if isinstance(source, Converted)]
        self._keyed = [(at, source.convert) for at, (_, source) in enumerate(self.sources)
                       if isinstance(source, Keyed)]

    def select(self, target: ExportTarget) -> Select[Any]:
        """The file's rows for ``target``, selecting its SQL-sourced columns in file order (no keys, no order)."""
        return self._rows(select(*self._selected), target)

    def file_rows(self, page: Sequence[Sequence[Any]], target: ExportTarget) -> list[tuple[Any, ...]]:
        """Rows as selected (keys appended or not) as raw values in the file's column order (built column by
        column, as ``TableWriter.format`` formats them)."""
        raw: list[Sequence[Any]] = list(zip(*page, strict=True))
        del raw[len(self._selected):]  # without the keyset keys
        if not raw:
            return []
        for at in self._python:  # ascending positions: each insert lands where the file has it
            raw.insert(at, ())
        for at, filled in self._filled:
            raw[at] = (filled.value(target),) * len(page)
        for at, derive, inputs in self._derived:  # from the values as selected, before conversion
            raw[at] = [derive(target, *values) for values in zip(*(raw[i] for i in inputs), strict=True)]
        for at, convert in self._converted:
            raw[at] = list(map(convert, raw[at]))
        for at, keyed in self._keyed:
            raw[at] = [keyed(target, value) for value in raw[at]]
        return list(zip(*raw, strict=True))


def _expression(source: Source) -> Any:
    return source.expression if isinstance(source, Converted | Keyed) else source


def _external_id(target: ExportTarget, value: str | None) -> str | None:
    return pseudonym(target.pseudonym_key, value) if target.pseudonym_key is not None and value else value


def _recruitment(target: ExportTarget, text: str | None) -> Any:
    parameters = read_json_text(text)
    if target.pseudonym_key is None or not isinstance(parameters, dict):
        return parameters
    return pseudonymised_parameters(target.pseudonym_key, parameters)


def _block_order(order: list[str] | None) -> str | None:
    return "|".join(order) if order else None


def _trial_rows(query: Select[Any], target: ExportTarget) -> Select[Any]:
    # ``stage`` through an expression, so that no planner prefers ix_trial_stage (every finished trial
    # of the database) to the participant index.
    return (query.join(Participant, Participant.id == Trial.participant_id)
            .join(StudyVersion, StudyVersion.id == Trial.study_version_id)
            .where(participant_condition(target), (Trial.stage + "") == "done"))


def _answer_rows(query: Select[Any], target: ExportTarget) -> Select[Any]:
    return (query.join(Participant, Participant.id == Answer.participant_id)
            .join(StudyVersion, StudyVersion.id == Answer.study_version_id)
            .where(participant_condition(target)))


def _participant_rows(query: Select[Any], target: ExportTarget) -> Select[Any]:
    return (query.join(StudyVersion, StudyVersion.id == Participant.study_version_id)
            .where(participant_condition(target)))


def _event_rows(query: Select[Any], target: ExportTarget) -> Select[Any]:
    query = (query.outerjoin(Participant, Participant.id == Event.participant_id)
             .where(Event.study_id == target.study_id))
    # Study-level events (no participant, e.g. refused joins) are always in; a preview's only if asked for.
    if target.include_preview:
        return query
    return query.where(or_(Participant.id.is_(None), Participant.preview.is_(False)))


_TRIALS = FileQuery("trials.csv", {
    "participant_id": Participant.public_id, "block": Trial.block, "trial": Trial.trial,
    "complexity": Trial.complexity, "robot_action": Trial.robot_action, "human_action": Trial.human_action,
    "outcome": Trial.outcome, "experience": Trial.experience, "practice": Trial.practice,
    "excluded": Participant.excluded, "study": STUDY_SLUG, "version": StudyVersion.version,
    "block_name": Trial.block_name, "policy": Trial.policy, "trial_overall": Trial.trial_overall,
    "shelf": Trial.shelf, "reward": Trial.reward, "score": Trial.score, "belief_before": Trial.belief_before,
    "belief_after": Trial.belief_after, "policy_belief": Trial.policy_belief,
    "decision_time_ms": Trial.decision_time_ms, "teleop_time_ms": Trial.teleop_time_ms,
    "teleop_view_wait_ms": Trial.teleop_view_wait_ms,
    "teleop_success": Trial.teleop_success, "failure_mode": Trial.failure_mode, "started_at": _dt(Trial.started_at),
    "decided_at": _dt(Trial.decided_at), "completed_at": _dt(Trial.completed_at), "model_hash": Trial.model_hash,
    "policy_hash": Trial.policy_hash, "seed": Trial.seed, "tutorial": Trial.tutorial,
    "teleop_tries": Trial.teleop_tries, "grasp_radius_m": Trial.grasp_radius_m, "align_radius_m": Trial.align_radius_m,
    "window_opened_at": _dt(Trial.window_opened_at), "window_opened_by": Trial.window_opened_by,
    "scene_shown_at": _dt(Trial.scene_shown_at), "scene_shown_view": Trial.scene_shown_view,
    "scene_shown_client_ms": Trial.scene_shown_client_ms,
}, _trial_rows, (Trial.participant_id, Trial.id), per_participant=True)

_INSTRUMENT = ("version", "questionnaire")
_ITEM = ("version", "questionnaire", "item")


def _of(q: Questionnaire | None, name: str) -> Any:
    return getattr(q, name) if q is not None else None


def _kind(item: Item | None) -> str | None:
    return item.kind if item is not None else None


def _attention_passed(target: ExportTarget, version: int, questionnaire: str, item_id: str, value: float | None,
                      text: str | None) -> bool | None:
    item = target.item(version, questionnaire, item_id)
    return attention_passed(item, stored_answer(item, {"value": value, "text": text})) if item is not None else None


_SURVEYS = FileQuery("surveys.csv", {
    "participant_id": Participant.public_id, "study": STUDY_SLUG, "version": StudyVersion.version,
    "context": Answer.context, "block": Answer.block, "block_name": Answer.block_name, "shelf": Answer.shelf,
    "questionnaire": Answer.questionnaire, "item": Answer.item, "value": Answer.value,
    "scored_value": Answer.scored_value, "belief": Answer.belief, "answered_at": _dt(Answer.answered_at),
    "excluded": Participant.excluded, "text": Answer.text,
    "item_kind": Derived(_ITEM, lambda t, v, q, i: _kind(t.item(v, q, i))),
    "attention_passed": Derived(_ITEM + ("value", "text"), _attention_passed),
    "instrument_title": Derived(_INSTRUMENT, lambda t, v, q: _of(t.instrument(v, q), "title")),
    "instrument_version": Derived(_INSTRUMENT, lambda t, v, q: _of(t.instrument(v, q), "version")),
    "scoring": Derived(_INSTRUMENT, lambda t, v, q: _of(t.instrument(v, q), "scoring")),
    "scoring_rule": Derived(_INSTRUMENT, lambda t, v, q: _of(t.instrument(v, q), "scoring_rule")),
    "instrument_doi": Derived(_INSTRUMENT, lambda t, v, q: _of(t.instrument(v, q), "doi")),
    "instrument_citation": Derived(_INSTRUMENT, lambda t, v, q: _of(t.instrument(v, q), "citation")),
}, _answer_rows, (Answer.participant_id, Answer.id), per_participant=True)

_PARTICIPANTS = FileQuery("participants.csv", {
    "participant_id": Participant.public_id, "external_id": Keyed(Participant.external_id, _external_id),
    "study": STUDY_SLUG,
    "version": StudyVersion.version, "status": Participant.status,
    "block_order": Converted(Participant.block_order, _block_order), "joined_at": _dt(Participant.created_at),
    "consented_at": _dt(Participant.consented_at), "started_at": _dt(Participant.started_at),
    "finished_at": _dt(Participant.finished_at), "last_seen_at": _dt(Participant.last_seen_at),
    "score": Participant.score, "compensation": Participant.compensation,
    "completion_code": Participant.completion_code, "excluded": Participant.excluded,
    "exclusion_reason": Participant.exclusion_reason,
    "recruitment": Keyed(cast(Participant.recruitment, Text), _recruitment),
    "preview": Participant.preview, "duplicate_of": Participant.duplicate_of, "language": Participant.language,
    "outcome": Converted(Participant.status, outcome_of_status),
    "attention_failures": (select(func.count()).where(Event.participant_id == Participant.id,
                                                      Event.kind == EventKind.ATTENTION_FAILED)
                           .correlate(Participant).scalar_subquery()),
    "personal_data_erased_at": _dt(Participant.personal_data_erased_at),
}, _participant_rows, (Participant.id,))

_EVENTS = FileQuery("events.csv", {
    "participant_id": Participant.public_id, "kind": Event.kind, "client_time_ms": Event.client_time_ms,
    "server_monotonic_s": Event.server_monotonic_s, "created_at": _dt(Event.created_at),
    "payload": _stored_json(Event.payload),
}, _event_rows, (Event.id,))  # ix_event_study_id is (study_id, id)

#: How every export file but ``codebook.csv`` (the codebook itself, not a query) is read.
FILE_QUERIES: dict[str, FileQuery] = {q.file: q for q in (_TRIALS, _SURVEYS, _PARTICIPANTS, _EVENTS)}

if set(FILE_QUERIES) | {"codebook.csv"} != set(EXPORT_FILES):
    raise ValueError(f"export files without a query: {set(EXPORT_FILES) - set(FILE_QUERIES) - {'codebook.csv'}}")
