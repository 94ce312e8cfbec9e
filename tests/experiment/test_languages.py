"""The participant's language: the link's lang parameter, then the browser's Accept-Language, then the default."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from experiment.config import StudyConfig
from experiment.languages import canonical_tag, match_language, parse_accept_language, resolve_language
from experiment.templates import TEMPLATES


def test_the_link_parameter_wins_when_the_study_offers_it() -> None:
    assert resolve_language(["en", "de"], requested="de", accept_language="en") == "de"
    assert resolve_language(["en", "de"], requested="DE") == "de"
    assert resolve_language(["en", "de"], requested="de-AT") == "de"  # same primary language
    assert resolve_language(["en", "de"], requested="fr", accept_language="de") == "de"  # not offered: the browser's
    assert resolve_language(["en", "de"], requested="<script>") == "en"


def test_the_browser_preference_picks_among_the_offered_languages() -> None:
    assert resolve_language(["en", "de"], accept_language="fr-FR,fr;q=0.9,de-CH;q=0.8,en;q=0.5") == "de"
    assert resolve_language(["en", "de"], accept_language="en;q=0.2, de;q=0.9") == "de"  # by q, not by order
    assert resolve_language(["de", "en"], accept_language="fr, ja") == "de"  # none offered: the first
    assert resolve_language(["en", "ar"], accept_language="ar-EG") == "ar"
    assert resolve_language(["en", "de"], accept_language="de;q=0, en") == "en"  # q=0: not wanted
    assert resolve_language(["en"], accept_language=None) == "en"


def test_accept_language_is_read_defensively() -> None:
    assert parse_accept_language("de-CH,de;q=0.9,en;q=0.8,*;q=0.1") == ["de-CH", "de", "en"]
    assert parse_accept_language("de;q=abc, en") == ["en"]
    assert parse_accept_language(",".join(["x" * 40] * 1000)) == []
    assert match_language("pt-br", ["en", "pt-BR"]) == "pt-BR"
    assert canonical_tag("zh-hant-tw") == "zh-Hant-TW"


def test_the_config_offers_languages_and_keeps_old_hashes() -> None:
    config = TEMPLATES["demo"]()
    demo = config.model_dump(mode="json")
    assert config.languages == ["en"] and config.default_language == "en"
    assert "languages" not in config.model_dump(mode="json")  # the default is left out: the config hash stays
    both = StudyConfig.model_validate({**demo, "languages": ["de", "EN"]})
    assert both.languages == ["de", "en"] and both.model_dump(mode="json")["languages"] == ["de", "en"]
    for bad in ([], ["en", "en"], ["english!"], ["e"]):
        with pytest.raises(ValidationError):
            StudyConfig.model_validate({**demo, "languages": bad})


def test_texts_per_language_cover_the_offered_languages_and_single_texts_are_warned() -> None:
    from experiment.config_problems import text_gaps

    demo = TEMPLATES["demo"]().model_dump(mode="json")
    both = {**demo, "languages": ["de", "en"]}
    texts = {**demo["texts"], "consent": {"de": "Willkommen", "EN": "Welcome"}, "debrief": "Danke / Thanks"}
    config = StudyConfig.model_validate({**both, "texts": texts})
    assert config.texts.in_language("en", "de").consent == "Welcome"
    assert config.texts.in_language("fr", "de").consent == "Willkommen"  # (not offered: the default's)
    assert config.texts.in_language("en", "de").debrief == "Danke / Thanks"  # one text serves every language
    assert [w.path for w in text_gaps(config)] == ["texts.debrief"]  # the lab's one text in a study of two
    assert text_gaps(TEMPLATES["demo"]()) == []
    for bad in ({"de": "Willkommen"}, {"de": "Willkommen", "en": " "}, {"de": "x", "english": "y"}, {}):
        with pytest.raises(ValidationError):
            StudyConfig.model_validate({**both, "texts": {**demo["texts"], "consent": bad}})
    # A single string is stored as before: the config hash of an existing study stays.
    assert StudyConfig.model_validate(demo).model_dump(mode="json") == demo
