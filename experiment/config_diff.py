"""A readable diff between two JSON documents (study config versions).

Each change names its place as a path a person reads (``blocks[1].policy.kind``, ``readable``), with the value
before and after.
Objects are compared key by key; lists item by item, so items added at the end or removed from it are changes of
their own. A value whose JSON type changes (a number becomes an object) is one change of the whole value.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

ChangeKind = Literal["changed", "added", "removed"]
_IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class Change:
    path: str  # "" for the whole document
    kind: ChangeKind
    before: Any = None  # None for "added"
    after: Any = None  # None for "removed"


def diff(before: Any, after: Any) -> list[Change]:
    """Every difference between two JSON values, in document order (``before``'s keys first)."""
    changes: list[Change] = []
    _diff(before, after, "", changes)
    return changes


def _diff(before: Any, after: Any, path: str, out: list[Change]) -> None:
    if isinstance(before, dict) and isinstance(after, dict):
        for key in [*before, *(k for k in after if k not in before)]:
            where = _key_path(path, key)
            if key not in after:
                out.append(Change(where, "removed", before=before[key]))
            elif key not in before:
                out.append(Change(where, "added", after=after[key]))
            else:
                _diff(before[key], after[key], where, out)
    elif isinstance(before, list) and isinstance(after, list):
        for index in range(max(len(before), len(after))):
            where = _index_path(path, index)
            if index >= len(after):
                out.append(Change(where, "removed", before=before[index]))
            elif index >= len(before):
                out.append(Change(where, "added", after=after[index]))
            else:
                _diff(before[index], after[index], where, out)
    elif not _same(before, after):
        out.append(Change(path, "changed", before=before, after=after))


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON: 1 and 1.0 are the same number, but true is not 1."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return a == b


def readable(path: Sequence[str | int]) -> str:
    """Keys and indices as a path a person reads: ["blocks", 1, "policy", "kind"] → "blocks[1].policy.kind" (a key
    that is not an identifier is quoted: ``anchors['10']``). The designer's problems use it too."""
    text = ""
    for segment in path:
        text = _index_path(text, segment) if isinstance(segment, int) else _key_path(text, segment)
    return text


def _index_path(path: str, index: int) -> str:
    return f"{path}[{index}]"


def _key_path(path: str, key: str) -> str:
    if _IDENTIFIER.match(key):
        return f"{path}.{key}" if path else key
    return f"{path}[{key!r}]"
