"""Values as an export can always write them: standard JSON in UTF-8.

A database may hold values no standard writer accepts, stored before requests were read strictly (or written by
hand): strings with lone UTF-16 surrogates (not Unicode, so not encodable as UTF-8), NaN or Infinity (not JSON
numbers), objects nested hundreds of levels deep (past what readers recurse into). Exports write such a value in
a repaired form, and ``trustlab check-data --repair`` stores that same form:

- a lone surrogate becomes U+FFFD (the Unicode replacement character);
- NaN, Infinity and -Infinity become null;
- an object or array nested deeper than ``MAX_DEPTH`` levels becomes the string ``TOO_DEEP`` (its content is
  dropped);
- an object key that is not a string becomes its ``str()``.

Everything else is kept as it is. ``problems`` says what is wrong with a value without changing it;
``read_json_text`` reads a stored JSON text however deep it nests (past ``MAX_DEPTH`` already cut).
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

#: Nesting kept (the value itself is level 1): the bound request bodies are read with (``server.strict_json``).
MAX_DEPTH = 32
#: What an object or array nested deeper than ``MAX_DEPTH`` is written as.
TOO_DEEP = "[removed: nested deeper than 32 levels]"
REPLACEMENT = "\ufffd"

_SURROGATE = re.compile("[\ud800-\udfff]")


def repair_text(text: str) -> str:
    """``text`` with every lone surrogate replaced by U+FFFD (the same string when it has none)."""
    return _SURROGATE.sub(REPLACEMENT, text) if _SURROGATE.search(text) else text


def repair_json(value: Any, decimals: int | None = None) -> Any:
    """``value`` (parsed JSON) in its repaired form, and with every float rounded to ``decimals`` places if given."""
    return _repair(value, decimals, 1)


def _repair(value: Any, decimals: int | None, depth: int) -> Any:
    if type(value) is str:
        return repair_text(value)
    if type(value) is float:
        if not math.isfinite(value):
            return None
        return round(value, decimals) if decimals is not None else value
    if isinstance(value, dict | list | tuple):
        if depth > MAX_DEPTH:
            return TOO_DEEP
        if isinstance(value, dict):
            return {repair_text(k if type(k) is str else str(k)): _repair(v, decimals, depth + 1)
                    for k, v in value.items()}
        return [_repair(v, decimals, depth + 1) for v in value]
    return value


def text_problems(text: str | None) -> list[str]:
    """What keeps ``text`` from being written as UTF-8 (empty if nothing)."""
    return ["a lone UTF-16 surrogate (written as U+FFFD)"] if text and _SURROGATE.search(text) else []


def problems(value: Any) -> list[str]:
    """What keeps ``value`` (parsed JSON) from being written as standard JSON, each kind once (empty if nothing).

    Iterative: a value of any depth is looked at without recursion."""
    found: dict[str, None] = {}
    stack: list[tuple[Any, int]] = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, str):
            found.update(dict.fromkeys(text_problems(item)))
        elif isinstance(item, float) and not math.isfinite(item):
            found["a non-finite number, NaN or Infinity (written as null)"] = None
        elif isinstance(item, dict | list | tuple):
            if depth > MAX_DEPTH:
                found[f"nested deeper than {MAX_DEPTH} levels (written as {TOO_DEEP!r})"] = None
                continue
            if isinstance(item, dict):
                for key, child in item.items():
                    if not isinstance(key, str):
                        found["an object key that is not a string (written as text)"] = None
                    else:
                        found.update(dict.fromkeys(text_problems(key)))
                    stack.append((child, depth + 1))
            else:
                stack.extend((child, depth + 1) for child in item)
    return list(found)


def read_json_text(text: str | None) -> Any:
    """A stored JSON text as Python reads it (leniently: NaN and lone surrogates pass, for ``repair_json``). A text
    nested too deep for the parser's recursion has its containers past ``MAX_DEPTH`` cut to ``TOO_DEEP`` first; a
    text that is not JSON at all (no trustlab version writes one) is kept as a string, so the row is still written."""
    if text is None:
        return None
    try:
        try:
            return json.loads(text)
        except RecursionError:
            return json.loads(cut_deep_json_text(text))
    except ValueError:
        return text


def cut_deep_json_text(text: str, max_depth: int = MAX_DEPTH) -> str:
    """``text`` (JSON) with every object or array nested deeper than ``max_depth`` replaced by the string
    ``TOO_DEEP``: one pass over the characters, no recursion (used only when a text is too deep to parse)."""
    out: list[str] = []
    depth, in_string, escaped, skip_from = 0, False, False, None  # skip_from: the depth whose container is cut
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "{[":
            depth += 1
            if skip_from is None and depth > max_depth:
                skip_from = depth
                out.append(json.dumps(TOO_DEEP))
                continue
        elif char in "}]":
            depth -= 1
            if skip_from is not None and depth == skip_from - 1:  # the cut container's own end
                skip_from = None
                continue
        if skip_from is None:
            out.append(char)
    return "".join(out)
