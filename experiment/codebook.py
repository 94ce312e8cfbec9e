"""The codebook of every exported CSV file (SPEC §7, §10) and the one writer of those files.

Each file's columns are declared once here, in file order, with a type, a
meaning, allowed values, a unit and — for numbers — the decimal places they
are rounded to. ``codebook.csv`` is this table; the server's exports
(``server.export``) and the simulator's ``trials.csv``
(``experiment.records.write_trials_csv``) both write through
:class:`TableWriter`, so a file has one format whoever writes it.

Cells are formatted by their column's declaration, never by sniffing the
value: numbers (``integer``, ``number``, ``flag``) are written as numbers
(a reward of -4 stays ``-4``), ``number`` cells rounded to the column's
``decimals`` in fixed notation with trailing zeros dropped (``1214.7``, not
``1214.6999999999534``; ``0.25``; never ``1e-05``), missing values and NaN
as empty cells; datetimes as ``YYYY-MM-DDTHH:MM:SS.ffffffZ`` (UTC); text,
category and JSON cells are neutralised against spreadsheet formula
injection: a cell starting with ``=``, ``+``, ``-``, ``@``, tab or CR gets a
leading ``'`` (so a free-text ``-4`` becomes ``'-4``, while the number -4
stays ``-4``). Files are UTF-8 without BOM, one header row, ``\\n`` line
ends, RFC 4180 quoting.

Precision: measured times keep 0.1 ms (the browser's clocks are coarser);
probabilities (beliefs) keep 10 decimal places, far below any difference
the model's parameters can make, so beliefs recomputed from the exported
rows agree to ~1e-10; points and scale answers keep 6 places (their inputs
are whole or short decimals in the study configuration).
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import partial
from typing import Any, TextIO

from experiment.events import CLIENT_KIND_PREFIX, EventKind
from experiment.policies import PolicyKind
from experiment.task import Complexity, Experience, HumanAction, Outcome, RobotAction
from experiment.writable import repair_json

#: Decimal places of each kind of measured quantity (see the module docstring).
PROBABILITY_DECIMALS = 10
MS_DECIMALS = 1
SECONDS_DECIMALS = 4  # 0.1 ms, as MS_DECIMALS
POINTS_DECIMALS = 6
METRE_DECIMALS = 6  # a micrometre
MONEY_DECIMALS = 2
#: Numbers inside JSON cells (event payloads: times in ms, velocities, rewards).
JSON_DECIMALS = 6

#: Columns ``fit`` and ``agnostic`` read, with their allowed values (they lead ``trials.csv``).
MODEL_COLUMNS: dict[str, tuple[str, ...] | None] = {
    "participant_id": None,
    "block": None,
    "trial": None,
    "complexity": tuple(Complexity),
    "robot_action": tuple(RobotAction),
    "human_action": tuple(HumanAction),
    "outcome": tuple(Outcome),
    "experience": tuple(Experience),
    "practice": ("0", "1"),
    "excluded": ("0", "1"),
}

FORMULA_TRIGGERS = ("=", "+", "-", "@", "\t", "\r")
#: Codebook types written as numbers (never neutralised).
NUMERIC_TYPES = frozenset({"integer", "number", "flag"})
TYPES = NUMERIC_TYPES | {"category", "text", "datetime", "json"}


@dataclass(frozen=True)
class Column:
    """One codebook row."""

    name: str
    type: str  # integer | number | flag (0/1) | category | text | datetime (ISO 8601, UTC) | json
    meaning: str
    allowed: str = ""  # allowed values ("a|b") or range
    unit: str = ""
    #: Decimal places of a ``number`` column (and of the numbers inside a ``json`` one); None otherwise.
    decimals: int | None = None


def allowed_values(name: str) -> str:
    allowed = MODEL_COLUMNS[name]
    assert allowed is not None
    return "|".join(allowed)


_UTC = "ISO 8601, UTC"
_P_HIGH = "probability P(trust = high)"
#: What a belief column holds under a model of more than two trust states (issue 40: experiment.trust_belief).
_K_STATES = (". Under a model of K = 3 or 4 trust states (model format trustlab-iohmm-k): the belief that trust is "
             "in the highest of its states, P(T = state_{K-1}); the whole belief vector is the model's filter "
             "(experiment.trust_belief) over the participant's trials.")
_POLICIES = "|".join(PolicyKind)

#: The codebook: every column of every exported file, in file order. Written by hand; a test checks
#: that it matches the files exactly.
CODEBOOK: dict[str, tuple[Column, ...]] = {
    "trials.csv": (
        Column("participant_id", "text", "Participant's public id (not a credential); joins all files."),
        Column("block", "integer", "Position of the block in the participant's block order, from 1; 0 for practice.",
               "0, 1, 2, ..."),
        Column("trial", "integer", "Index of the trial within its block (or within practice), from 1.", "1, 2, ..."),
        Column("complexity", "category", "Complexity of the item to collect.", allowed_values("complexity")),
        Column("robot_action", "category", "What the robot did: auto = attempt autonomously (a+), ask = ask the "
               "human for help (a-).", allowed_values("robot_action")),
        Column("human_action", "category", "What the human did: rely = let the robot attempt (o+), intervene = "
               "teleoperate (o-; always the case after ask).", allowed_values("human_action")),
        Column("outcome", "category", "Outcome of the autonomous attempt; none when the robot did not attempt "
               "(it asked, or the human intervened).", allowed_values("outcome")),
        Column("experience", "category", "Experience E_{t+1} the trial gave the human (model input).",
               allowed_values("experience")),
        Column("practice", "flag", "1 for a practice trial (not used for model fitting).", allowed_values("practice")),
        Column("excluded", "flag", "1 if the participant is excluded from analysis (participant's flag at "
               "export time; reason in participants.csv).", allowed_values("excluded")),
        Column("study", "text", "Study slug."),
        Column("version", "integer", "Study configuration version the participant ran under.", "1, 2, ..."),
        Column("block_name", "category", "Name of the block in the study configuration; practice for practice "
               "trials."),
        Column("policy", "category", "Robot policy of the block.", _POLICIES),
        Column("trial_overall", "integer", "Index of the trial over all scored blocks, from 1 (practice: index "
               "within practice).", "1, 2, ..."),
        Column("shelf", "integer", "Shelf number within the block, from 1 (a shelf survey follows its last "
               "trial); 1 for practice.", "1, 2, ..."),
        Column("reward", "number", "Reward of the trial R^a_{o,E} (eq. 1 of the paper; study's reward table).",
               unit="points", decimals=POINTS_DECIMALS),
        Column("score", "number", "Running score after the trial (practice trials do not change it).",
               unit="points", decimals=POINTS_DECIMALS),
        Column("belief_before", "number", "Belief that trust is high before the trial, under the study's model "
               f"and belief update{_K_STATES}", "[0, 1]", _P_HIGH, PROBABILITY_DECIMALS),
        Column("belief_after", "number", "Belief that trust is high after the trial (belief_before updated with "
               f"this trial); equals belief_before for practice{_K_STATES}", "[0, 1]", _P_HIGH, PROBABILITY_DECIMALS),
        Column("policy_belief", "number", "Belief the block's policy acted on (differs from belief_before when "
               f"the block's policy uses its own model); empty for practice{_K_STATES}", "[0, 1]", _P_HIGH,
               PROBABILITY_DECIMALS),
        Column("decision_time_ms", "number", "Time from the decision window opening to the Intervene press "
               "(browser clock); empty when the human relied, the robot asked or the client sent no times.",
               unit="ms", decimals=MS_DECIMALS),
        Column("teleop_time_ms", "number", "Duration of the teleoperation (the time limit when it timed out); "
               "empty without teleoperation.", unit="ms", decimals=MS_DECIMALS),
        Column("teleop_view_wait_ms", "number", "How long the teleoperation's time limit stood still because the "
               "page had no usable view (a reload while its 3D view loaded; at most 30 s per teleoperation), "
               "included in teleop_time_ms; empty when it never did.", unit="ms", decimals=MS_DECIMALS),
        Column("teleop_success", "flag", "1 if teleoperation deposited the item; empty without teleoperation.",
               "0|1"),
        Column("failure_mode", "category", "How an autonomous attempt failed; empty unless outcome is failure.",
               "collision|drop"),
        Column("started_at", "datetime", "When the trial started (server clock).", unit=_UTC),
        Column("decided_at", "datetime", "When the decision was made (Intervene pressed, or the decision window "
               "closed for rely); empty when the robot asked.", unit=_UTC),
        Column("completed_at", "datetime", "When the trial was resolved (server clock).", unit=_UTC),
        Column("model_hash", "text", "SHA-256 of the canonical JSON of the model document the trial ran under: "
               "the trust-aware block's own model, otherwise the study's belief model (the word paper stands for "
               "the paper's parameters as a model document); equals the content_hash of a fitted model deployed "
               "by trustlab. Empty for trials recorded before provenance was kept.", "64 hex digits"),
        Column("policy_hash", "text", "SHA-256 of the canonical JSON of the block's resolved policy: its spec with "
               "the schedule's p_high filled in and the model replaced by its hash, plus the study's task (rewards); "
               "practice trials hash the practice list. Empty for trials recorded before provenance was kept.",
               "64 hex digits"),
        Column("seed", "integer", "Study seed. With participant_id, block_name and trial it determines every random "
               "draw of the trial (complexity schedule, the policy's randomness, the autonomous outcome). Empty for "
               "trials recorded before provenance was kept.", "0 ... 2^63 - 1"),
        Column("tutorial", "flag", "1 if the trial's teleoperation was the guided practice (study config "
               "practice.tutorial: every practice teleoperation until the participant's first deposit; a try that "
               "runs out of time starts over from the ready pose).", "0|1"),
        Column("teleop_tries", "integer", "Tries of the teleoperation (more than 1 only for the guided practice); "
               "empty without teleoperation.", "1 ... practice.tutorial.max_tries"),
        Column("grasp_radius_m", "number", "Teleoperation rule the trial ran under (study config "
               "teleop.grasp_radius_m): closing grasps when the gripper centre is this close to the item's grasp "
               "point; empty without teleoperation.", "(0, 0.2]", unit="m",
               decimals=METRE_DECIMALS),
        Column("align_radius_m", "number", "Teleoperation assistance the trial ran under (study config "
               "teleop.align_radius_m): closing within this distance first moves the gripper onto the grasp point; "
               "0 = no assistance; empty without teleoperation.", "[0, 0.3]", unit="m",
               decimals=METRE_DECIMALS),
        Column("window_opened_at", "datetime", "When the decision window opened (server clock): when the page "
               "reported the trial's scene on screen, or at the wait limit (window_opened_by); empty when the robot "
               "asked, and for trials recorded before the window waited for the scene.", unit=_UTC),
        Column("window_opened_by", "category", "What opened the decision window: the page's proof that its 3D "
               "view (3d) or its 2-D helper view (2d) had drawn a frame from this trial's scene (the scene's stamp, "
               "read back from the view that drew it; a frame of the previous trial's scene never counts), a "
               "client without a view (text, e.g. a bot), or no proof within the study's timing.scene_wait_s "
               "(wait_limit: the window opened without evidence that the scene was on screen; a data-quality "
               "flag). Empty as for window_opened_at.", "3d|2d|text|wait_limit"),
        Column("scene_shown_at", "datetime", "When the server received the page's first proof that the trial's "
               "scene was on screen (server clock); later than window_opened_at when it came after the wait "
               "limit, empty without one.", unit=_UTC),
        Column("scene_shown_view", "category", "Which view the first proof came from: 3d, 2d, or text (a client "
               "without a view). Empty without a proof.", "3d|2d|text"),
        Column("scene_shown_client_ms", "number", "The page's clock (performance.now(), ms since the page "
               "loaded) when it drew the first frame proven to show the trial's scene; compare with the same "
               "trial's decision times, which use the same clock. Empty without a proof, or from a client that did "
               "not say.", unit="ms", decimals=MS_DECIMALS),
    ),
    "surveys.csv": (
        Column("participant_id", "text", "Participant's public id."),
        Column("study", "text", "Study slug."),
        Column("version", "integer", "Study configuration version.", "1, 2, ..."),
        Column("context", "category", "When the questionnaire was asked: before (before the first block), "
               "shelf:B:S (after shelf S of block position B), after:B (after block position B), end (at the end "
               "of the study, after every block, whatever the block order).",
               "before|shelf:B:S|after:B|end"),
        Column("block", "integer", "Block position the answer follows, from 1; empty for before and end.",
               "1, 2, ..."),
        Column("block_name", "category", "Name of that block in the study configuration; empty for before and "
               "end."),
        Column("shelf", "integer", "Shelf within the block for shelf surveys, from 1; empty otherwise.", "1, 2, ..."),
        Column("questionnaire", "category", "Questionnaire id in the study configuration.",
               "e.g. shelf_trust_reliance|schaefer_14"),
        Column("item", "category", "Item id within the questionnaire. The item's text (and its options' labels) "
               "was shown in the participant's language when the questionnaire has a translation for it, else in "
               "the questionnaire's own; ids, values and option values are the same in every language."),
        Column("value", "number", "The answer as given on the questionnaire's scale (rating items); empty for text "
               "and choice items (see text).",
               unit="scale points (see the questionnaire's scale, e.g. % for schaefer_14)", decimals=POINTS_DECIMALS),
        Column("scored_value", "number", "The answer with reverse-coded items reversed (scale min + max - value); "
               "equals value otherwise. Empty for text and choice items and for attention checks (not scored).",
               unit="scale points", decimals=POINTS_DECIMALS),
        Column("belief", "number", f"Model belief that trust is high when the answer was given{_K_STATES}", "[0, 1]",
               _P_HIGH, PROBABILITY_DECIMALS),
        Column("answered_at", "datetime", "When the answer was recorded (server clock).", unit=_UTC),
        Column("excluded", "flag", "1 if the participant is excluded from analysis.", "0|1"),
        Column("text", "text", "The answer to a text item as written (surrounding white space removed), or the "
               "chosen option's value for a choice item (its stable identifier, not the label shown); empty for "
               "rating items. An optional item left blank has no row."),
        Column("item_kind", "category", "The item's kind in the study configuration version: rating (value), text or "
               "choice (text).", "rating|text|choice"),
        Column("attention_passed", "flag", "For an attention check (an instructed-response item): 1 if the answer "
               "was the instructed one, 0 if not (each 0 is an attention_failed event); empty for other items.",
               "0|1"),
        Column("instrument_title", "text", "The questionnaire's title in the study configuration version the answer "
               "was given under (provenance: e.g. Trust Perception Scale–HRI (14-item subscale))."),
        Column("instrument_version", "text", "Which form of the instrument (the questionnaire's version, e.g. "
               "14-item subscale); empty when the configuration gives none."),
        Column("scoring", "category", "The questionnaire's score: mean (of the scored_value of its rating items "
               "that are not attention checks) or none.", "mean|none"),
        Column("scoring_rule", "text", "How the score is computed, in words (which items are reverse-coded); empty "
               "when the configuration gives none."),
        Column("instrument_doi", "text", "DOI of the instrument's publication; empty for the lab's own "
               "questionnaires."),
        Column("instrument_citation", "text", "Full reference of the instrument's publication; empty for the lab's "
               "own questionnaires (e.g. demographics, comments)."),
    ),
    "participants.csv": (
        Column("participant_id", "text", "Participant's public id."),
        Column("external_id", "text", "Recruitment platform id (e.g. PROLIFIC_PID); empty if none, or once erased "
               "(withdrawn, or the study's retention rule: personal_data_erased_at). In a pseudonymised export "
               "(manifest pseudonymised: true; trustlab export --pseudonymise) a salted hash instead: HMAC-SHA256 of "
               "the id under the study's own random key, its first 24 hex digits; the same id gives the same value in "
               "every export of the study and another in another study's."),
        Column("study", "text", "Study slug."),
        Column("version", "integer", "Study configuration version the participant ran under.", "1, 2, ..."),
        Column("status", "category", "Session status (screened_out: ended by an eligibility question or by failed "
               "attention checks under the study's attention rule screen_out).",
               "active|completed|declined|abandoned|withdrawn|screened_out"),
        Column("block_order", "text", "Block names in the order the participant did them, separated by |; "
               "empty until the first scored trial.", "e.g. trust_aware|trust_agnostic"),
        Column("joined_at", "datetime", "When the participant opened the study link.", unit=_UTC),
        Column("consented_at", "datetime", "When consent was given; empty if not (yet).", unit=_UTC),
        Column("started_at", "datetime", "Start of the first scored trial.", unit=_UTC),
        Column("finished_at", "datetime",
               "When the session ended: completed (debrief reached), declined (consent refused), "
               "abandoned (when the server judged it idle: the first sweep after last_seen_at plus the study's "
               "idle timeout, so at most a sweep interval later) or withdrawn (the earlier end, else the "
               "withdrawal). Empty only while active.", unit=_UTC),
        Column("last_seen_at", "datetime",
               "Last request from the participant while the session was active (written at most every 5 s; "
               "requests after the session ended do not move it).", unit=_UTC),
        Column("score", "number", "Total score.", unit="points", decimals=POINTS_DECIMALS),
        Column("compensation", "number", "Payment: base plus score bonus (capped); empty until completed.",
               unit="study currency (config compensation.currency)", decimals=MONEY_DECIMALS),
        Column("completion_code", "text", "The code of the session's outcome (see outcome): shown at the end; for "
               "timed_out the code the page shows if the participant comes back. Empty when the outcome has no code "
               "(timed_out by default) or the session has not ended."),
        Column("excluded", "flag", "1 if excluded from analysis.", "0|1"),
        Column("exclusion_reason", "text", "Why the participant was excluded (withdrawn for withdrawals)."),
        Column("recruitment", "json", "Recruitment parameters of the join link (e.g. PROLIFIC_PID, STUDY_ID, "
               "SESSION_ID), as a JSON object; {} once erased. In a pseudonymised export every value but STUDY_ID "
               "is a salted hash, as external_id."),
        Column("preview", "flag", "1 for an experimenter's preview session (not data: in an export only when "
               "previews are asked for, include_preview=true; their trials, answers and events are in the other "
               "files under the same participant_id).", "0|1"),
        Column("duplicate_of", "text", "For a session joined with an external id that had joined before, without "
               "proof of being that session's person (its browser's resume key, or the same Prolific SESSION_ID / "
               "MTurk assignmentId): the participant_id of the first session of the id (quality flag duplicate_id on "
               "both). Empty otherwise."),
        Column("language", "category", "The language the participant saw every page and message in (a BCP 47 tag of "
               "the study's config languages), chosen once at the join: the join link's lang parameter, else the "
               "browser's preferred language the study offers, else the study's first. The study's texts and "
               "questionnaire items were shown in this language where the config gives them in it "
               "(experiment.languages).", "BCP 47 tag, e.g. en|de|ar"),
        Column("outcome", "category", "How the session ended for the recruitment platform, from status: completed, "
               "declined (consent), screened_out, timed_out (abandoned), withdrawn; empty while active. "
               "Each outcome has its own code and redirect (study config completion).",
               "completed|declined|screened_out|timed_out|withdrawn"),
        Column("attention_failures", "integer", "Attention checks (instructed-response items) answered otherwise "
               "than instructed (events attention_failed).", "0, 1, 2, ..."),
        Column("personal_data_erased_at", "datetime", "When the session's personal fields (external_id, "
               "recruitment, resume key, address hash) were erased: on withdrawal (data kept) or by the study's "
               "retention rule (config privacy); empty while they are kept. The research data stay.", unit=_UTC),
    ),
    "events.csv": (
        Column("participant_id", "text", "Participant's public id; empty for study-level events."),
        Column("kind", "category", "Event kind (client events are prefixed client.).",
               "|".join([*EventKind, CLIENT_KIND_PREFIX + "*"]) + ". attention_failed: an attention check answered "
               "otherwise than instructed (payload: questionnaire, context, item, answer, instructed, failures = the "
               "count so far); screened_out: the session ended at a questionnaire page (reason: eligibility | "
               "attention). join_refused is a study-level event (no participant): a new join refused because the "
               "study was full (payload: active, cap = recruitment.max_active_participants). decision_window_opened "
               "says by what (by: 3d|2d|text|wait_limit, as trials.csv window_opened_by); a press of Intervene outside "
               "the window is client.intervene_too_early or client.intervene_too_late (known_by: page = the page's own "
               "countdown had ended, server = the server refused it). teleop_log's payload holds entries, each with "
               "server_ms (since the teleoperation began) and either an input the participant started to hold "
               "(client_ms, seq, input: ee_velocity m/s | joint_velocity rad/s | gripper) or a world event "
               "(grasped, aligned, dropped, item_reset, deposited, blocked, deadman_stop, resumed, disconnect_stop, "
               "server_lag with lost_ms: real time in which the arm did not move because the server was late): the "
               "arm moves on the server's clock from the held input, so the inputs and their times, less the lost "
               "time logged between them, reconstruct the teleoperation."),
        Column("client_time_ms", "number", "Browser performance.now() when the client reported the event; empty "
               "for server events.", unit="ms", decimals=MS_DECIMALS),
        Column("server_monotonic_s", "number", "Server monotonic clock when written (comparable only within one "
               "server process run).", unit="s", decimals=SECONDS_DECIMALS),
        Column("created_at", "datetime", "When the event was written (server clock).", unit=_UTC),
        Column("payload", "json", "Event details as a JSON object (numbers in it rounded like the file's other "
               "measurements, see decimals).", decimals=JSON_DECIMALS),
    ),
    "codebook.csv": (
        Column("file", "category", "Exported file the column belongs to.",
               "trials.csv|surveys.csv|participants.csv|events.csv|codebook.csv"),
        Column("column", "text", "Column name (header cell) in that file."),
        Column("type", "category", "How cells are written: integer, number (decimal), flag (0/1), category "
               "(one of a set), text, datetime (ISO 8601 UTC, to the microsecond) or json. Empty cells mean missing.",
               "|".join(sorted(TYPES))),
        Column("allowed_values", "text", "Allowed values (a|b) or range, when restricted."),
        Column("unit", "text", "Unit of measurement or format."),
        Column("meaning", "text", "What the column holds."),
        Column("decimals", "integer", "Decimal places numbers in the column are rounded to (trailing zeros are "
               "dropped: 0.25 at 10 places is written 0.25); for json, the numbers inside it. Empty for columns "
               "without fractional numbers.", "0, 1, 2, ..."),
    ),
}

EXPORT_FILES: tuple[str, ...] = tuple(CODEBOOK)


def columns(name: str) -> list[str]:
    return [c.name for c in CODEBOOK[name]]


def codebook_rows() -> list[tuple[Any, ...]]:
    """``codebook.csv``'s rows (values in its column order)."""
    return [(file, c.name, c.type, c.allowed, c.unit, c.meaning, c.decimals)
            for file, cols in CODEBOOK.items() for c in cols]


# -- the same rows as schema.org PropertyValues (Psych-DS variableMeasured) ------------------------

_ENUMERATION = re.compile(r"[A-Za-z0-9_]+(?:\|[A-Za-z0-9_]+)+")
_INTERVAL = re.compile(r"([\[(])(-?\d+(?:\.\d+)?), (-?\d+(?:\.\d+)?)([\])])")
_COUNTING_FROM = re.compile(r"(\d+)(?:, \d+)*, \.\.\.|(\d+) \.\.\. .+")


def variable_measured(name: str) -> list[dict[str, Any]]:
    """File ``name``'s columns as the Psych-DS ``variableMeasured`` of its data file, in file order: one
    ``property_value`` per codebook row, so ``codebook.csv`` and the JSON-LD description never disagree."""
    return [property_value(c) for c in CODEBOOK[name]]


def property_value(column: Column) -> dict[str, Any]:
    """One codebook row as a schema.org ``PropertyValue``: ``name`` the column, ``description`` its meaning followed
    by the allowed values in the codebook's words, ``unitText`` its unit; allowed values that are a list of names
    (``a|b``) also as ``valueReference`` terms, a numeric range as ``minValue``/``maxValue`` (a closed end only)."""
    value: dict[str, Any] = {"@type": "PropertyValue", "name": column.name, "description": column.meaning}
    if column.allowed:
        value["description"] += f" Allowed values: {column.allowed}" + ("" if column.allowed.endswith(".") else ".")
    if column.unit:
        value["unitText"] = column.unit
    return value | _allowed_fields(column.allowed)


def _allowed_fields(allowed: str) -> dict[str, Any]:
    if _ENUMERATION.fullmatch(allowed):
        return {"valueReference": [{"@type": "DefinedTerm", "termCode": v, "name": v} for v in allowed.split("|")]}
    if interval := _INTERVAL.fullmatch(allowed):
        opening, low, high, closing = interval.groups()
        return ({"minValue": _number(low)} if opening == "[" else {}) | (
            {"maxValue": _number(high)} if closing == "]" else {})
    if counting := _COUNTING_FROM.fullmatch(allowed):
        return {"minValue": int(counting[1] or counting[2])}
    return {}


def _number(text: str) -> int | float:
    return float(text) if "." in text else int(text)


# -- cells ---------------------------------------------------------------------------------------

_TRIGGER_CHARS = frozenset(FORMULA_TRIGGERS)


def neutralise(text: str) -> str:
    """Prefix ``'`` to a text cell a spreadsheet would read as a formula (SPEC §10)."""
    return "'" + text if text and text[0] in _TRIGGER_CHARS else text


def format_number(value: Any, decimals: int | None = None) -> str:
    """A number cell: rounded to ``decimals`` places in fixed notation without trailing zeros (integral values
    without ``.0``); with ``decimals`` None, the shortest round-trip repr. None and NaN are empty."""
    if type(value) is not float:  # floats first: they are most cells
        if value is None:
            return ""
        if isinstance(value, bool):
            return "1" if value else "0"
        if isinstance(value, int):
            return str(value)
        value = float(value)
    if value != value:  # NaN
        return ""
    if decimals is None or math.isinf(value):
        return str(int(value)) if value.is_integer() and -1e15 < value < 1e15 else repr(value)
    text = f"{value:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def _format_integer(value: Any) -> str:
    return str(value) if type(value) is int else format_number(value)


def _format_flag(value: Any) -> str:
    return "" if value is None else ("1" if value else "0")


def _format_text(value: Any) -> str:
    if value is None:
        return ""
    text = value if type(value) is str else str(value)
    return "'" + text if text and text[0] in _TRIGGER_CHARS else text


def _format_datetime(value: datetime | str | None) -> str:
    """``YYYY-MM-DDTHH:MM:SS.ffffffZ`` (UTC); ``value`` is a datetime or SQLite's stored UTC text."""
    if value is None:
        return ""
    if isinstance(value, str):
        if len(value) == 26 and value[10] == " ":  # SQLAlchemy's SQLite storage format, in UTC (TZDateTime)
            return value[:10] + "T" + value[11:] + "Z"
        value = datetime.fromisoformat(value)
    if value.tzinfo is None:  # naive values are UTC in trustlab
        value = value.replace(tzinfo=UTC)
    return value.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _format_json(value: Any, decimals: int | None = None) -> str:
    """Standard JSON, floats rounded to ``decimals``; a stored value that is not standard JSON (a lone surrogate,
    NaN, nesting past ``experiment.writable.MAX_DEPTH``) is written in its repaired form (see there), never refused:
    an export writes every row."""
    if value is None:
        return ""
    value = repair_json(value, decimals)
    return _format_text(json.dumps(value, sort_keys=True, ensure_ascii=False, separators=(",", ":"), allow_nan=False))


_FORMATTERS: dict[str, Callable[..., str]] = {
    "integer": _format_integer, "number": format_number, "flag": _format_flag, "category": _format_text,
    "text": _format_text, "datetime": _format_datetime, "json": _format_json,
}


def format_cell(column_type: str, value: Any, decimals: int | None = None) -> str:
    """A cell as written for a column of ``column_type`` (a codebook type), never sniffed from the value."""
    return _formatter(column_type, decimals)(value)


def _formatter(column_type: str, decimals: int | None) -> Callable[[Any], str]:
    f = _FORMATTERS[column_type]
    return partial(f, decimals=decimals) if column_type in ("number", "json") else f


def formatters(name: str) -> list[Callable[[Any], str]]:
    """The cell formatter of each column of file ``name``, in file order."""
    return [_formatter(c.type, c.decimals) for c in CODEBOOK[name]]


# -- the writer ----------------------------------------------------------------------------------

class TableWriter:
    """Writes one codebook file to ``out``: the header on creation, then rows of raw values in the file's column
    order, each cell formatted by its column (the only code that writes an exported CSV file)."""

    def __init__(self, name: str, out: TextIO) -> None:
        if name not in CODEBOOK:
            raise KeyError(f"unknown export file {name!r}; files: {', '.join(EXPORT_FILES)}")
        self.name, self.out = name, out
        self._cells = formatters(name)
        self._csv = csv.writer(out, lineterminator="\n")
        self._csv.writerow(neutralise(c) for c in columns(name))
        self.rows = 0

    def format(self, rows: Sequence[Sequence[Any]]) -> list[tuple[str, ...]]:
        """Rows of raw values as cells. Column by column: one ``map`` per column is much faster than a call per
        cell from Python."""
        if not rows:
            return []
        raw = list(zip(*rows, strict=True))
        if len(raw) != len(self._cells):
            raise ValueError(f"{self.name}: rows have {len(raw)} values, the file has {len(self._cells)} columns")
        return list(zip(*(map(f, column) for f, column in zip(self._cells, raw, strict=True)), strict=True))

    def write(self, rows: Sequence[Sequence[Any]]) -> int:
        """Format and write ``rows``; returns how many."""
        cells = self.format(rows)
        _write_cells(self._csv, self.out, cells)
        self.rows += len(cells)
        return len(cells)

    def write_all(self, rows: Iterable[Sequence[Any]], batch: int = 200) -> int:
        """``write`` over any iterable of rows, ``batch`` at a time; returns how many rows this call wrote."""
        n, pending = 0, []
        for row in rows:
            pending.append(row)
            if len(pending) == batch:
                n += self.write(pending)
                pending = []
        return n + self.write(pending)


def _write_cells(writer: Any, out: TextIO, rows: list[tuple[str, ...]]) -> None:
    """RFC 4180 rows. ``csv`` quotes a cell holding a line feed but not one holding a lone CR (our line end is
    ``\n``), which readers take as a line break: rows with a CR in a cell are written here instead (they are rare)."""
    if "\r" not in "".join(map("".join, rows)):
        writer.writerows(rows)
        return
    for row in rows:
        out.write(",".join(_rfc4180_cell(cell) for cell in row) + "\n")


def _rfc4180_cell(cell: str) -> str:
    return '"' + cell.replace('"', '""') + '"' if any(c in cell for c in ',"\r\n') else cell
