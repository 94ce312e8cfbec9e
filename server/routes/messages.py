"""The participant pages' words (``server.i18n``): one catalogue per language as JSON, and a study's language for a
join page that has no session yet."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Path, Query, Request, Response
from sqlalchemy import select

from experiment.languages import DEFAULT_LANGUAGES, TAG_PATTERN, resolve_language
from server import i18n
from server.bodies import StrictJsonRoute
from server.deps import UnitsDep
from server.models import Study
from server.schemas import LanguageRead, MessagesRead
from server.services.joining import LANGUAGE_PARAM
from server.services.studies import current_version

router = APIRouter(route_class=StrictJsonRoute, prefix="/api", tags=["participant"])

#: The catalogues change only with a new server version: a browser keeps one an hour and then asks again (ETag).
CATALOGUE_CACHE = "public, max-age=3600"
Language = Annotated[str, Path(max_length=16, pattern=TAG_PATTERN)]


@router.get("/messages/{language}", response_model=MessagesRead)
def messages(language: Language, request: Request) -> Response:
    """Every participant-facing text in ``language`` (a shipped catalogue of that language, else English), by key,
    plural texts by CLDR plural category, with the language's writing direction. Cached (``Cache-Control``, ``ETag``;
    ``If-None-Match`` answers 304)."""
    body, etag = i18n.catalogue_json(language)
    headers = {"Cache-Control": CATALOGUE_CACHE, "ETag": etag, "Vary": "Accept-Encoding"}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    return Response(body, media_type="application/json", headers=headers)


@router.get("/studies/{slug}/language", response_model=LanguageRead)
async def study_language(slug: Annotated[str, Path(max_length=200)], units: UnitsDep,
                         lang: Annotated[str | None, Query(alias=LANGUAGE_PARAM, max_length=64)] = None,
                         accept_language: Annotated[str | None, Header(max_length=1000)] = None) -> LanguageRead:
    """The language a join of this study now gets (the join page's words before the join): the link's ``lang``
    if the study offers it, else the browser's preferred one it offers, else its default. A study that does not
    exist (or has no version) answers with the best shipped catalogue: the page then says so in that language."""
    def work(session) -> list[str]:
        study = session.scalar(select(Study).where(Study.slug == slug))
        if study is None:
            return list(i18n.shipped_languages())
        return list(current_version(session, study).config.get("languages", DEFAULT_LANGUAGES))
    offered = await units.run(work)
    chosen = resolve_language(offered, requested=lang, accept_language=accept_language)
    return LanguageRead(language=chosen, direction=i18n.catalogue(chosen).direction)
