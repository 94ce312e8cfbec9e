"""Which language a participant sees: one of the study's offered languages, chosen once at the join.

A study offers one or more languages (``StudyConfig.languages``, BCP 47 tags such as ``"en"``, ``"de"``, ``"ar"``;
the first is the default). ``resolve_language`` picks one for a new participant from the join link's ``lang``
parameter, else from the browser's ``Accept-Language`` header, else the default; the server stores the result on
the participant (``Participant.language``) and every page and message of the session uses it, so a reload, a new tab
or a changed browser setting never switches language in the middle of a study.

Pure: no web, no catalogues (``server.i18n`` holds those and falls back to English for a language it has no
catalogue for).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Final

#: The default of ``StudyConfig.languages``: the pages' own language when a study says nothing.
DEFAULT_LANGUAGES: Final = ("en",)
#: A BCP 47 language tag as studies write it: a primary language subtag of 2–3 letters, then optional subtags
#: (script, region, variant) of 1–8 letters or digits: "en", "de", "pt-BR", "zh-Hant", "ar".
TAG_PATTERN: Final = r"^[A-Za-z]{2,3}(-[A-Za-z0-9]{1,8})*$"
MAX_TAG_LENGTH: Final = 16  # Participant.language is String(16)
_TAG = re.compile(TAG_PATTERN)
#: At most this many entries of an Accept-Language header are read (a header is client input).
MAX_ACCEPT_ENTRIES: Final = 20


def valid_tag(tag: str) -> bool:
    return len(tag) <= MAX_TAG_LENGTH and _TAG.fullmatch(tag) is not None


def canonical_tag(tag: str) -> str:
    """The tag as BCP 47 writes it by convention: language lower case, a 2-letter region upper case, a 4-letter
    script title case ("pt-br" → "pt-BR", "ZH-hant" → "zh-Hant"). Matching ignores case anyway."""
    first, *rest = tag.split("-")
    parts = [first.lower()]
    for sub in rest:
        parts.append(sub.upper() if len(sub) == 2 else sub.title() if len(sub) == 4 else sub.lower())
    return "-".join(parts)


def primary(tag: str) -> str:
    """The primary language subtag: "de" of "de-CH"."""
    return tag.split("-", 1)[0].lower()


def match_language(wanted: str, offered: Sequence[str]) -> str | None:
    """The offered tag that serves ``wanted``: the same tag (case ignored), else one of the same primary language
    ("de-CH" is served by "de", "de" by "de-AT"), the first listed winning; None when none does."""
    if not valid_tag(wanted):
        return None
    lowered = wanted.lower()
    for tag in offered:
        if tag.lower() == lowered:
            return tag
    return next((tag for tag in offered if primary(tag) == primary(wanted)), None)


def parse_accept_language(header: str | None) -> list[str]:
    """The language tags of an ``Accept-Language`` header, most wanted first (by q, then by order); ``*``, tags that
    are not BCP 47 and entries with q=0 are left out. "de-CH,de;q=0.9,en;q=0.8" → ["de-CH", "de", "en"]."""
    if not header:
        return []
    ranked: list[tuple[float, int, str]] = []
    for index, entry in enumerate(header.split(",")[:MAX_ACCEPT_ENTRIES]):
        tag, _, params = entry.strip().partition(";")
        q = 1.0
        for param in params.split(";"):
            name, _, value = param.strip().partition("=")
            if name.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        tag = tag.strip()
        if q > 0 and valid_tag(tag):
            ranked.append((-q, index, tag))
    return [tag for _, _, tag in sorted(ranked)]


def resolve_language(offered: Sequence[str], *, requested: str | None = None,
                     accept_language: str | None = None) -> str:
    """The language a new participant sees, from the study's ``offered`` languages (the first is the default).

    ``requested``: the join link's ``lang`` parameter; it wins when the study offers it (a link the lab made for a
    language). ``accept_language``: the browser's header; its most wanted language the study offers wins. Otherwise
    the study's default. A language the study does not offer is never chosen.
    """
    if not offered:
        return DEFAULT_LANGUAGES[0]
    if requested and (chosen := match_language(requested.strip(), offered)) is not None:
        return chosen
    for tag in parse_accept_language(accept_language):
        if (chosen := match_language(tag, offered)) is not None:
            return chosen
    return offered[0]
