"""The participant pages' and messages' words: gettext catalogues read with Babel, one per language.

``server/locales/<language>/LC_MESSAGES/participant.po`` holds every participant-facing text of the pages
(``static/``) and of the server (robot messages, hints, error sentences) under a key ("join.full.title"), with
``{name}`` placeholders. English (``en``) is the source and is complete; a key another language lacks (or has
marked fuzzy) is shown in English. Plural texts are gettext plurals whose forms follow CLDR's plural categories
(Babel writes each catalogue's ``Plural-Forms`` from CLDR): form *i* is the language's *i*-th category in CLDR's order
(zero, one, two, few, many, other), so the pages receive them by category and pick with ``Intl.PluralRules``.

The server translates with ``Translator`` (the participant's language, ``Participant.language``); the pages fetch
the same catalogue as JSON from ``GET /api/messages/{language}`` (``catalogue_json``) and translate with
``static/js/i18n.js``. ``trustlab i18n`` extracts the keys, updates the catalogues and checks them (docs/languages.md).
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from babel import Locale
from babel.messages.catalog import Catalog
from babel.messages.pofile import read_po
from babel.numbers import format_decimal

from experiment.languages import match_language

LOCALES_DIR = Path(__file__).resolve().parent / "locales"
DOMAIN = "participant"
SOURCE_LANGUAGE = "en"
#: CLDR's plural categories in the order gettext plural forms number them (babel.plural.to_gettext).
CLDR_CATEGORIES = ("zero", "one", "two", "few", "many", "other")
#: A text shown in English on a right-to-left page is isolated (FIRST STRONG ISOLATE … POP DIRECTIONAL ISOLATE), so
#: that its words and punctuation keep their order.
ISOLATE = ("\u2068", "\u2069")
_PLACEHOLDER = re.compile(r"\{(\w+)\}")

Text = str | dict[str, str]  # a text, or a plural text by CLDR category


def po_path(language: str) -> Path:
    return LOCALES_DIR / language / "LC_MESSAGES" / f"{DOMAIN}.po"


@functools.cache
def shipped_languages() -> tuple[str, ...]:
    """The languages with a catalogue, English first."""
    found = sorted(p.parents[1].name for p in LOCALES_DIR.glob(f"*/LC_MESSAGES/{DOMAIN}.po"))
    return tuple(sorted(found, key=lambda tag: tag != SOURCE_LANGUAGE))


def plural_categories(language: str) -> tuple[str, ...]:
    """The language's CLDR plural categories, in gettext's order of plural forms."""
    tags = Locale.parse(language.replace("-", "_")).plural_form.tags | {"other"}
    return tuple(c for c in CLDR_CATEGORIES if c in tags)


def read_catalog(language: str) -> Catalog:
    with po_path(language).open("rb") as file:
        return read_po(file, locale=language.replace("-", "_"), domain=DOMAIN)


def translated(catalog: Catalog, language: str) -> dict[str, Text]:
    """The catalogue's translated, non-fuzzy messages by key (a plural one by CLDR category)."""
    categories = plural_categories(language)
    texts: dict[str, Text] = {}
    for message in catalog:
        if not message.id or message.fuzzy:
            continue
        key = str(message.id[0] if isinstance(message.id, tuple | list) else message.id)
        if isinstance(message.string, tuple | list):
            forms = {c: str(s) for c, s in zip(categories, message.string, strict=False) if s}
            if "other" in forms:
                texts[key] = forms
        elif message.string:
            texts[key] = str(message.string)
    return texts


@dataclass(frozen=True)
class Catalogue:
    """One language's words: its own where it has them, English for the rest (``fallback``: those keys)."""

    language: str
    direction: Literal["ltr", "rtl"]
    messages: Mapping[str, Text]
    fallback: frozenset[str]

    def text(self, key: str, count: float | None = None) -> str:
        entry = self.messages.get(key)
        if entry is None:
            raise KeyError(f"no message {key!r} in the {self.language} catalogue (nor in English)")
        if isinstance(entry, str):
            return entry
        category = plural_category(self.language if key not in self.fallback else SOURCE_LANGUAGE, count or 0)
        return entry.get(category, entry["other"])


def plural_category(language: str, count: float) -> str:
    return str(Locale.parse(language.replace("-", "_")).plural_form(abs(count)))


def serving(language: str) -> str:
    """The shipped catalogue's language that serves ``language`` (the same primary language), else English."""
    return match_language(language, shipped_languages()) or SOURCE_LANGUAGE


def catalogue(language: str) -> Catalogue:
    """The catalogue serving ``language`` (a shipped one of the same primary language, else English)."""
    return _catalogue(serving(language))


@functools.cache  # keyed by the shipped languages only: a client's tag never grows the cache
def _catalogue(shipped: str) -> Catalogue:
    english = translated(read_catalog(SOURCE_LANGUAGE), SOURCE_LANGUAGE)
    own = translated(read_catalog(shipped), shipped) if shipped != SOURCE_LANGUAGE else english
    direction = Locale.parse(shipped.replace("-", "_")).text_direction
    return Catalogue(language=shipped, direction="rtl" if direction == "rtl" else "ltr",
                     messages={**english, **own}, fallback=frozenset(english) - frozenset(own))


def fill(text: str, params: Mapping[str, object]) -> str:
    """``{name}`` placeholders replaced by ``params`` (a missing one is left as it is, never an error)."""
    return _PLACEHOLDER.sub(lambda m: str(params[m[1]]) if m[1] in params else m[0], text)


class Translator:
    """Texts in one participant's language: ``t("key", name=value)``, ``tn("key", count, ...)`` for plurals."""

    def __init__(self, language: str):
        self.catalogue = catalogue(language)

    @property
    def language(self) -> str:
        return self.catalogue.language

    def t(self, key: str, **params: object) -> str:
        return self._isolated(key, fill(self.catalogue.text(key), self._numbers(params)))

    def tn(self, key: str, count: float, **params: object) -> str:
        return self._isolated(key, fill(self.catalogue.text(key, count), self._numbers({"count": count, **params})))

    def _isolated(self, key: str, text: str) -> str:
        if self.catalogue.direction == "rtl" and key in self.catalogue.fallback:
            return ISOLATE[0] + text + ISOLATE[1]
        return text

    def _numbers(self, params: Mapping[str, object]) -> dict[str, object]:
        """Numbers written as the language writes them ("2,5" in German)."""
        locale = self.language.replace("-", "_")
        return {name: format_decimal(value, locale=locale, group_separator=False)
                if isinstance(value, int | float) and not isinstance(value, bool) else value
                for name, value in params.items()}


def catalogue_json(language: str) -> tuple[bytes, str]:
    """The catalogue the pages load (``GET /api/messages/{language}``) as JSON, and its ETag."""
    return _catalogue_json(serving(language))


@functools.cache
def _catalogue_json(shipped: str) -> tuple[bytes, str]:
    cat = _catalogue(shipped)
    body = json.dumps({"language": cat.language, "direction": cat.direction,
                       "plural_categories": list(plural_categories(cat.language)),
                       "fallback": sorted(cat.fallback),
                       "messages": dict(sorted(cat.messages.items()))},
                      ensure_ascii=False, separators=(",", ":")).encode()
    return body, '"' + hashlib.sha256(body).hexdigest()[:32] + '"'


def placeholders(text: Text) -> set[str]:
    forms = text.values() if isinstance(text, dict) else [text]
    return {name for form in forms for name in _PLACEHOLDER.findall(form)}


def N_(key: str) -> str:  # gettext's name for a key marked for extraction
    """Marks a catalogue key used by name elsewhere (an error's ``message``), so that extraction finds it."""
    return key
