"""The study config's JSON Schema as the designer's form library reads it.

Pydantic writes ``$defs`` and ``$ref``, discriminated unions as ``oneOf`` with a ``discriminator`` and optional
values as ``anyOf [X, null]``. The form (json-editor, ``static/vendor/``) draws ``oneOf``/``anyOf`` as a choice
between titled options, so here every ``$ref`` is inlined, each union option gets a title a researcher reads (the
policy's or schedule's ``kind``; "none" for null), and every object property is marked required so that the form
shows every field — except the ones a document may leave out (``exclude_if``: left out of dumps when missing),
which the form offers as opt-in fields so that a document round-trips through the form unchanged. A few hints
for json-editor (``options``, ``format``) lay it out, by rule and never per field: every field is titled by the
model's ``title=`` or else by its name in words (units and acronyms spelt out), numbers are number inputs with
their bounds and step, booleans check boxes, a required number without a default starts from its model's first
example (or its minimum) so that a union option switched to starts valid, constants are hidden, long texts get a
text area, a free-form document (a model JSON) is edited as JSON text, and the sections a researcher rarely
changes start collapsed.
"""

from __future__ import annotations

import copy
import re
import typing
from typing import Any

from pydantic import BaseModel

from experiment.config import StudyConfig

#: Top-level sections shown collapsed at first (the blocks, timing, pay and texts stay open).
COLLAPSED = ("task", "model", "practice", "questionnaires", "teleop", "recruitment", "completion")
#: Strings longer than this (or unbounded) are edited in a text area.
SHORT_TEXT = 200
#: Words of a field name written differently in its title: units (a trailing ``_s``), acronyms, abbreviations.
WORDS = {"s": "(s)", "m": "(m)", "id": "ID", "ids": "IDs", "url": "URL", "doi": "DOI", "teleop": "teleoperation"}


def form_schema() -> dict[str, Any]:
    """The JSON Schema of ``StudyConfig`` with references inlined and union options titled."""
    schema = StudyConfig.model_json_schema()
    defs = schema.pop("$defs", {})
    optional = _per_model(StudyConfig, lambda model: {name for name, field in model.model_fields.items()
                                                      if field.exclude_if is not None})
    titles = _per_model(StudyConfig, lambda model: {name: field.title for name, field in model.model_fields.items()
                                                    if field.title})
    form = _resolve(schema, defs, optional, titles)
    form["title"] = "Study configuration"
    for name in COLLAPSED:
        form["properties"][name]["options"] = {**form["properties"][name].get("options", {}), "collapsed": True}
    return form


def _resolve(node: Any, defs: dict[str, Any], optional: dict[str, set[str]], titles: dict[str, dict[str, str]]) -> Any:
    if isinstance(node, list):
        return [_resolve(item, defs, optional, titles) for item in node]
    if not isinstance(node, dict):
        return node
    if "$ref" in node:  # the model first (its title names its fields' facts), then the field's own keys over it
        name = node["$ref"].split("/")[-1]
        rest = {k: v for k, v in node.items() if k != "$ref"}
        return {**_resolve(copy.deepcopy(defs[name]), defs, optional, titles), **_resolve(rest, defs, optional, titles)}
    out = {k: _resolve(v, defs, optional, titles) for k, v in node.items() if k != "discriminator"}
    if isinstance(out.get("description"), str):  # docstrings' ``code`` marks, for a person to read
        out["description"] = out["description"].replace("``", "")
    tag = node.get("discriminator", {}).get("propertyName", "kind")  # the field that names a union's option
    for union in ("oneOf", "anyOf"):
        if union in out:
            out[union] = [_titled(option, tag) for option in out[union]]
    if out.get("type") == "object" and "properties" not in out:
        out = _map_or_document(out)
    if out.get("type") in ("number", "integer") and not {"enum", "const"} & out.keys():
        out = _number_input(out)
    if out.get("type") == "boolean":
        out["format"] = "checkbox"
    if out.get("type") == "object" and "properties" in out:
        model = out.get("title", "")
        omittable = optional.get(model, set())
        out["required"] = [name for name in out["properties"] if name not in omittable]
        named = titles.get(model, {})
        out["properties"] = {name: _laid_out(name, prop, named.get(name)) for name, prop in out["properties"].items()}
    return out


def _number_input(node: dict[str, Any]) -> dict[str, Any]:
    """A number input (json-editor sets its inclusive ``minimum``/``maximum`` as min/max) stepping by 1 for an
    integer or any amount for a number (a spinner's step would mark 0.1848 invalid); a required number without a
    default starts from its first example, else its minimum, rather than from a 0 that may be out of bounds."""
    step = node.get("multipleOf", 1 if node["type"] == "integer" else "any")
    start = {}
    if "default" not in node and (node.get("examples") or "minimum" in node):
        start = {"default": node["examples"][0] if node.get("examples") else node["minimum"]}
    return {**node, "format": "number", "step": step, **start}


def _map_or_document(node: dict[str, Any]) -> dict[str, Any]:
    """A map with a closed set of keys (a trust-agnostic policy's ``actions``: low, high) as an object with those
    properties; a free-form document (a model JSON) as JSON text in a text area (``json_document``: the form's
    own editor parses it), since a form of its unknown fields could not round-trip its nested values."""
    keys = node.get("propertyNames", {}).get("enum")
    if keys:
        rest = {k: v for k, v in node.items() if k not in ("propertyNames", "additionalProperties")}
        value = node.get("additionalProperties", {})
        choices = f": {' or '.join(map(str, value['enum']))}" if "enum" in value else ""
        return {**rest, "properties": {key: {"description": f"For {key}{choices}", **value} for key in keys},
                "additionalProperties": False}
    if node.get("additionalProperties", True) is True:
        return {**node, "format": "textarea", "options": {**node.get("options", {}), "json_document": True}}
    return node


def _laid_out(name: str, prop: dict[str, Any], title: str | None) -> dict[str, Any]:
    """A property titled by its field's ``title=`` or its name in words (not by its model's class name), constants
    hidden, long texts in a text area."""
    prop = {**prop, "title": title or readable(name)}
    items = prop.get("items")
    if isinstance(items, dict) and "properties" in items:  # "Block 1", "Delete Block", not "BlockConfig 1"
        prop["items"] = {**items, "title": model_words(items.get("title", name))}
    if "const" in prop:
        prop["options"] = {**prop.get("options", {}), "hidden": True}
    long = prop.get("maxLength", SHORT_TEXT + 1) > SHORT_TEXT
    if prop.get("type") == "string" and long and not {"pattern", "enum", "const"} & prop.keys():
        prop["format"] = "textarea"
    return prop


def readable(name: str) -> str:
    """A field name in words: ``time_limit_s`` → "Time limit (s)", ``doi`` → "DOI"."""
    words = [WORDS.get(word, word) for word in name.split("_")]
    return " ".join([words[0][:1].upper() + words[0][1:], *words[1:]])


def model_words(title: str) -> str:
    """A model's class name in words, without the words that only say it is a model: ``BlockConfig`` → "Block",
    ``PracticeTrial`` → "Practice trial"."""
    words = [w for w in re.findall(r"[A-Z][a-z0-9]*|[a-z0-9]+", title) if w not in ("Config", "Spec")] or [title]
    return " ".join([words[0], *(w.lower() for w in words[1:])])


def _titled(option: dict[str, Any], tag: str) -> dict[str, Any]:
    """A union option titled for the form's choice (its tag field, a constant, is hidden by ``_laid_out``)."""
    titled = {**option, "title": _option_title(option, tag)}
    if "const" in option:  # the choice says it all, e.g. the model "paper": shown, not editable
        titled["readOnly"] = True
    return titled


def _option_title(option: dict[str, Any], tag: str) -> str:
    """The option's tag (a policy's kind), constant, "none" for null, or its type."""
    tagged = option.get("properties", {}).get(tag, {})
    if "const" in tagged:
        return str(tagged["const"])
    if "const" in option:
        return str(option["const"])
    if option.get("type") == "null":
        return "none"
    if option.get("type") == "object" and "properties" not in option:
        return "document"
    return option.get("title") or option.get("type") or "value"


def _per_model(model: type[BaseModel], facts: Any, seen: dict[str, Any] | None = None) -> dict[str, Any]:
    """``facts(m)`` per model title, for ``model`` and every model in its fields (at any depth)."""
    seen = {} if seen is None else seen
    title = model.model_config.get("title") or model.__name__
    if title in seen:
        return seen
    seen[title] = facts(model)
    for field in model.model_fields.values():
        for inner in _models_in(field.annotation):
            _per_model(inner, facts, seen)
    return seen


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]
