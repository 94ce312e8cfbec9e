"""Babel extraction of catalogue keys from the participant pages and the server (``babel.cfg``; ``pybabel extract``).

The code names texts by key, never by their words: ``t("key", {...})`` and ``tn("key", n, {...})`` (plural) in
``static/js`` and in Python (``Translator.t``/``tn``), ``tr`` where ``t`` names something else (static/js/trial.js),
``N_("key")`` for a key used by name elsewhere (an error's ``message``, a table of keys), and ``data-i18n="key"``
(``data-i18n-<attribute>="key"`` for an attribute) in the HTML pages. Keys are lower-case dotted names
("join.full.title"), so a plain pattern finds them in all three.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import IO, Any

KEY = r"[a-z][a-z0-9_]*(?:\.[a-z0-9_]+)+"
_CALL = re.compile(r"\b(tn|tr|t|N_)\(\s*[\"'](" + KEY + r")[\"']")
_ATTRIBUTE = re.compile(r"\bdata-i18n(?:-[a-z-]+)?=\"(" + KEY + r")\"")

Extracted = tuple[int, str, str | tuple[str, str], list[str]]


def extract_keys(fileobj: IO[bytes], keywords: Any, comment_tags: Any, options: dict[str, Any]) -> Iterator[Extracted]:
    """Babel extraction method: (line, function, key or (key, key) for a plural, comments). The function is named as
    Babel's default keywords know it (gettext, ngettext), so no ``-k`` option is needed."""
    text = fileobj.read().decode(options.get("encoding", "utf-8"))
    for match in _CALL.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        name, key = match[1], match[2]
        yield line, *(("ngettext", (key, key)) if name == "tn" else ("gettext", key)), []
    for match in _ATTRIBUTE.finditer(text):
        yield text.count("\n", 0, match.start()) + 1, "gettext", match[1], []
