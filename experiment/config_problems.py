"""The one way a study configuration document is checked and its problems reported.

``check_document`` validates a document as strictly as its JSON Schema reads
(``experiment.config.validate_document``) and returns every problem at its place in the document: pydantic's error
location without the union tags it adds (a policy's ``trust_aware``, a schedule's ``counts``, ``literal['paper']``),
as keys and indices (``loc``) and as a path a person reads (``blocks[1].policy.kind``, as ``experiment.config_diff``
writes a change's place). The designer's live check, a refused save (422) and the command line's design files all
report problems this way. ``language_gaps`` reports, the same way, what a valid study may still want to fix: a
questionnaire asked without a translation for a language the study offers (a warning: the study runs).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from experiment.config import StudyConfig, validate_document
from experiment.config_diff import readable
from experiment.questionnaire_translations import serves


@dataclass(frozen=True)
class ConfigProblem:
    path: str  # "blocks[1].schedule.n_low"; "" for the document itself
    loc: list[str | int]  # ["blocks", 1, "schedule", "n_low"]
    message: str

    def __str__(self) -> str:
        return f"{self.path or '(document)'}: {self.message}"


def check_document(document: Any) -> tuple[StudyConfig | None, list[ConfigProblem]]:
    """The validated configuration and no problem, or None and every problem of the document."""
    try:
        return validate_document(document), []
    except ValidationError as exc:
        return None, [place(document, e["loc"], plain_message(e)) for e in exc.errors()]


#: What a field's pattern asks for, in words (pydantic's message quotes the regular expression).
PATTERNS_IN_WORDS = {
    r"^[A-Za-z][A-Za-z0-9_]*$": "use only letters, digits and '_', starting with a letter (it names a column in "
                                "exports)",
    r"^[A-Za-z0-9_\-]+$": "use only letters, digits, '_' and '-'",
    r"^10\.\d{4,9}/\S+$": "write the DOI without its https://doi.org/ prefix, e.g. 10.1145/3610977.3634945",
}
#: What pydantic puts before the message of a validator's ValueError or assertion, which a person need not read.
_VALIDATOR_PREFIXES = ("Value error, ", "Assertion failed, ")


def plain_message(error: Mapping[str, Any], patterns: Mapping[str, str] = PATTERNS_IN_WORDS) -> str:
    """A pydantic error's message as a person reads it: a validator's own words without pydantic's "Value error, "
    prefix, a pattern in words rather than as a regular expression."""
    message = str(error["msg"])
    if error.get("type") == "string_pattern_mismatch":
        pattern = (error.get("ctx") or {}).get("pattern")
        if isinstance(pattern, str) and pattern in patterns:
            return patterns[pattern]
    for prefix in _VALIDATOR_PREFIXES:
        if message.startswith(prefix):
            return message[len(prefix):]
    return message


def place(document: Any, loc: Sequence[Any], message: str) -> ConfigProblem:
    """A validation error's place in the document: ``loc`` without the union tags, as keys and indices and as a
    readable path."""
    path: list[str | int] = []
    node = document
    for segment in loc:
        if isinstance(node, list) and isinstance(segment, int):
            path.append(segment)
            node = node[segment] if segment < len(node) else None
        elif isinstance(node, dict) and segment in node:
            path.append(segment)
            node = node[segment]
        elif isinstance(segment, str) and _is_union_tag(node, segment):
            continue
        else:  # a missing field: its name is the place
            path.append(segment)
            node = None
    return ConfigProblem(path=readable(path), loc=path, message=message)


def _is_union_tag(node: Any, segment: str) -> bool:
    return (isinstance(node, dict) and node.get("kind") == segment) or "[" in segment


def language_gaps(config: StudyConfig) -> list[ConfigProblem]:
    """Warnings, not problems (the study runs): each questionnaire the study asks that has no translation for a
    language the study offers, at its place in ``questionnaires``. A participant of that language reads it in its
    own language (English for the built-ins) in the middle of pages in theirs."""
    asked = [*config.questionnaires_before, *([config.shelf_questionnaire] if config.shelf_questionnaire else []),
             *(q for block in config.blocks for q in block.questionnaires_after), *config.questionnaires_end]
    warnings = []
    for index, q in enumerate(config.questionnaires):
        missing = [tag for tag in config.languages if not serves(q, tag)]
        if q.id in asked and missing:
            warnings.append(ConfigProblem(
                path=readable(["questionnaires", index]), loc=["questionnaires", index], message=(
                    f"questionnaire {q.id!r} has no translation for {', '.join(missing)}, which the study offers: "
                    f"participants of {'that language' if len(missing) == 1 else 'those languages'} read it in "
                    f"{q.language!r}. Add a translation (translations) or accept the mixed page")))
    return warnings + text_gaps(config)


def text_gaps(config: StudyConfig) -> list[ConfigProblem]:
    """Warnings: each of the study's own texts written once (one string) in a study of several languages. Every
    participant reads it as written; a text left at trustlab's default is said in each language and is no gap."""
    if len(config.languages) < 2:
        return []
    texts = config.texts
    return [ConfigProblem(path=readable(["texts", name]), loc=["texts", name], message=(
        f"texts.{name} is one text for every language the study offers ({', '.join(config.languages)}): every "
        f"participant reads it as written. Give a text per language ({{\"{config.languages[0]}\": \"…\", …}}) or "
        "accept it"))
        for name in ("title", "block_label", "consent", "instructions", "debrief")
        if isinstance(value := getattr(texts, name), str) and value != type(texts).model_fields[name].default]
