"""Standard JSON only, in and out: what a client sends is read strictly, and what is stored is written strictly.

Python's ``json`` reads more than RFC 8259 JSON: ``NaN``, ``Infinity``, numbers that overflow to infinity
(``1e309``), lone UTF-16 surrogates (``"\\ud800"``, which no UTF-8 writer can encode), and UTF-16/32 bodies;
nesting is bounded only by the interpreter's recursion limit. Any of them, once stored, breaks whatever later
writes the value out (an export, the report). ``loads`` refuses each with a ``StrictJsonError`` naming the
place; ``check`` applies the same rules to a value already read (by pydantic, say); ``dumps`` writes standard
JSON or raises.
"""

from __future__ import annotations

import json
import math
import re
from typing import Annotated, Any

from pydantic import BeforeValidator

#: The deepest nesting a request body may have. A study config, the deepest legitimate body, nests about 10 deep.
MAX_DEPTH = 32

#: A JSON integer in a strict model: 3 or 3.0 (JSON Schema counts both as integers), never true or "3".
WHOLE_FLOAT_AS_INT = BeforeValidator(lambda v: int(v) if isinstance(v, float) and v.is_integer() else v)
JsonInt = Annotated[int, WHOLE_FLOAT_AS_INT]

_SURROGATE = re.compile("[\ud800-\udfff]")


class StrictJsonError(ValueError):
    """The text is not standard JSON within the bounds; ``where`` is a dotted path to the offending value."""

    def __init__(self, message: str, where: str = ""):
        super().__init__(f"{where}: {message}" if where else message)
        self.reason, self.where = message, where


def _refuse_constant(name: str) -> Any:
    raise StrictJsonError(f"{name} is not a JSON number (numbers must be finite)")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise StrictJsonError(f"the number {text[:40]} is too large (numbers must be finite)")
    return value


def loads(data: str | bytes, *, max_depth: int = MAX_DEPTH) -> Any:
    """Read standard JSON: UTF-8 only, finite numbers, no lone surrogates, nested at most ``max_depth`` deep."""
    if isinstance(data, bytes | bytearray):
        try:
            data = bytes(data).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise StrictJsonError(f"not valid UTF-8 (byte {exc.start})") from None
    try:
        value = json.loads(data, parse_constant=_refuse_constant, parse_float=_finite_float)
    except RecursionError:
        raise StrictJsonError(f"nested deeper than {max_depth} levels") from None
    except StrictJsonError:
        raise
    except json.JSONDecodeError as exc:
        raise StrictJsonError(f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except ValueError as exc:  # e.g. an integer of more than 4,300 digits
        raise StrictJsonError(f"not valid JSON: {exc}") from None
    check(value, max_depth=max_depth)
    return value


def check(value: Any, *, max_depth: int = MAX_DEPTH, max_keys: int | None = None,
          max_string: int | None = None, max_int: int | None = None) -> None:
    """Raise ``StrictJsonError`` unless ``value`` is standard JSON within the bounds: finite numbers, strings and
    keys without lone surrogates, at most ``max_depth`` levels, and (when given) at most ``max_keys`` keys in an
    object, ``max_string`` characters in a string or key, and integers no larger than ``max_int`` in magnitude.

    Iterative (no recursion), so a value too deep for the interpreter is refused, not a crash."""
    stack: list[tuple[Any, int, str]] = [(value, 1, "")]
    while stack:
        item, depth, where = stack.pop()
        if isinstance(item, dict | list | tuple):
            if depth > max_depth:
                raise StrictJsonError(f"nested deeper than {max_depth} levels", where)
            if isinstance(item, dict):
                if max_keys is not None and len(item) > max_keys:
                    raise StrictJsonError(f"more than {max_keys} keys in one object", where)
                for key, child in item.items():
                    if not isinstance(key, str):
                        raise StrictJsonError("object keys must be strings", where)
                    _check_string(key, max_string, where)
                    stack.append((child, depth + 1, f"{where}.{key[:40]}" if where else key[:40]))
            else:
                stack.extend((child, depth + 1, f"{where}.{i}" if where else str(i)) for i, child in enumerate(item))
        elif isinstance(item, str):
            _check_string(item, max_string, where)
        elif isinstance(item, bool) or item is None:
            pass
        elif isinstance(item, int):
            if max_int is not None and abs(item) > max_int:
                raise StrictJsonError(f"integers must lie within ±{max_int}", where)
        elif isinstance(item, float):
            if not math.isfinite(item):
                raise StrictJsonError("numbers must be finite (no NaN or Infinity)", where)
        else:
            raise StrictJsonError(f"{type(item).__name__} is not a JSON value", where)


def _check_string(text: str, max_string: int | None, where: str) -> None:
    if _SURROGATE.search(text):
        raise StrictJsonError("a string holds a lone UTF-16 surrogate (not valid Unicode)", where)
    if max_string is not None and len(text) > max_string:
        raise StrictJsonError(f"a string longer than {max_string} characters", where)


def dumps(value: Any, **kwargs: Any) -> str:
    """Standard JSON (``ValueError`` on NaN or Infinity): the database's JSON columns are written with this."""
    return json.dumps(value, allow_nan=False, **kwargs)
