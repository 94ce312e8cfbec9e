"""Issue 41: the participant-facing catalogues (server/locales): every key the pages and the server use exists in
every shipped language with the same placeholders and plural forms; German is complete; Arabic has at least the
pages' chrome (headings, buttons, navigation, errors) and falls back to English for the rest; the pages load a
catalogue as JSON from one cached endpoint."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from babel.messages.extract import extract_from_dir
from babel.messages.frontend import parse_mapping_cfg

from server import i18n
from tests.server.factories import make_client

ROOT = Path(__file__).resolve().parents[2]
COMPLETE = ("en", "de")
#: The right-to-left catalogue's required part: the pages' chrome (every heading, button, navigation text and error
#: sentence); everything else may fall back to English (shown isolated, in its own direction).
CHROME_PREFIXES = ("errors.", "join.", "top.", "notice.ok", "loading.", "common.", "consent.title", "consent.question",
                   "consent.agree", "consent.decline", "instructions.title", "instructions.controls", "howto.title",
                   "practice_done.title", "trial.title", "trial.camera", "trial.facts.", "trial.robot",
                   "trial.intervene", "trial.practice_label", "teleop.title", "teleop.steps", "teleop.step.",
                   "teleop.pad", "teleop.fine", "teleop.helper2d", "teleop.refused", "survey.title", "survey.optional",
                   "survey.missing_one", "debrief.title", "debrief.code", "debrief.stay", "debrief.redirect",
                   "code.", "end.", "connection.", "default_texts.title", "default_texts.block_label", "units.seconds",
                   "units.minutes", "withdraw.link", "withdraw.heading", "withdraw.confirm", "withdraw.cancel",
                   "withdraw.end_heading")
CHROME_EXCEPTIONS = {"instructions.controls.intervene", "instructions.controls.moves", "instructions.controls.gripper",
                     "instructions.controls.camera",  # the controls' sentences, not headings
                     "trial.robot_collecting"}  # (a robot's message)


def used_keys() -> dict[str, bool]:
    """Every key the code uses (Babel's extraction with babel.cfg), and whether it is used as a plural."""
    with (ROOT / "babel.cfg").open() as file:
        method_map, options_map = parse_mapping_cfg(file)
    found: dict[str, bool] = {}
    for _, _, message, _, _ in extract_from_dir(str(ROOT), method_map, options_map):
        key = message[0] if isinstance(message, tuple) else message
        found[key] = found.get(key, False) or isinstance(message, tuple)
    return found


@pytest.fixture(scope="module")
def catalogs() -> dict[str, dict[str, i18n.Text]]:
    return {language: i18n.translated(i18n.read_catalog(language), language) for language in i18n.shipped_languages()}


def test_english_german_and_arabic_are_shipped() -> None:
    assert i18n.shipped_languages() == ("en", "ar", "de")


def test_every_key_used_exists_in_every_complete_language(catalogs) -> None:
    used = used_keys()
    assert len(used) > 250  # the extraction finds the pages' and the server's keys (not an empty pass)
    assert {"join.full.title", "trial.intervene", "errors.study_full", "guidance.lower", "units.seconds"} <= set(used)
    for language in COMPLETE:
        texts = catalogs[language]
        missing = sorted(set(used) - set(texts))
        assert not missing, f"{language} lacks {missing}"
        wrong_kind = sorted(key for key, plural in used.items() if plural != isinstance(texts[key], dict))
        assert not wrong_kind, f"{language}: used as plural and not (or the reverse): {wrong_kind}"
        unused = sorted(set(texts) - set(used))
        assert not unused, f"{language} has texts no code uses: {unused}"


def test_translations_keep_the_placeholders_and_plural_forms(catalogs) -> None:
    english = catalogs["en"]
    for language, texts in catalogs.items():
        for key, text in texts.items():
            assert i18n.placeholders(text) == i18n.placeholders(english[key]), (language, key)
            if isinstance(text, dict):
                assert set(text) == set(i18n.plural_categories(language)), (language, key)


def test_german_is_german_and_formal(catalogs) -> None:
    german, english = catalogs["de"], catalogs["en"]
    def words(text: i18n.Text) -> str:  # the text's letters outside placeholders
        return re.sub(r"\{\w+\}|<[^>]+>|[^A-Za-z]", "", str(text))
    same = sorted(key for key in german if german[key] == english[key] and len(words(english[key])) > 3)
    assert same == ["survey.optional", "target.color.orange"], same  # German words too; all else translated
    informal = sorted(key for key, text in german.items() if any(f" {word} " in f" {text} " for word in
                                                                  ("du", "dich", "dir", "dein", "deine")))
    assert not informal, informal


def test_arabic_has_the_chrome_and_falls_back_to_english_for_the_rest(catalogs) -> None:
    used = used_keys()
    chrome = sorted(key for key in used if key.startswith(CHROME_PREFIXES) and key not in CHROME_EXCEPTIONS)
    assert len(chrome) > 90
    missing = sorted(set(chrome) - set(catalogs["ar"]))
    assert not missing, f"Arabic lacks chrome texts {missing}"
    arabic = i18n.catalogue("ar")
    assert arabic.direction == "rtl" and arabic.fallback  # partial: the rest is English
    assert set(arabic.messages) == set(catalogs["en"])
    tr = i18n.Translator("ar")
    assert tr.t("consent.agree") == "أوافق على المشاركة"
    assert tr.t("robot.auto", target="x") == "\u2068I will collect x myself.\u2069"  # English, isolated
    assert [tr.tn("units.seconds", n) for n in (1, 2, 5)] == ["ثانية واحدة", "ثانيتان", "5 ثوانٍ"]


def test_plural_rules_and_numbers_follow_the_language() -> None:
    german = i18n.Translator("de")
    assert german.tn("units.seconds", 1) == "1 Sekunde" and german.tn("units.seconds", 2.5) == "2,5 Sekunden"
    assert i18n.Translator("en").tn("units.seconds", 1) == "1 second"
    assert i18n.Translator("de-AT").language == "de" and i18n.Translator("fr").language == "en"


def test_the_catalogue_endpoint_is_typed_and_cached(database_url) -> None:
    client, _ = make_client(database_url=database_url)
    response = client.get("/api/messages/de")
    assert response.status_code == 200 and response.headers["Cache-Control"] == "public, max-age=3600"
    body = response.json()
    assert body["language"] == "de" and body["direction"] == "ltr" and body["plural_categories"] == ["one", "other"]
    assert body["messages"]["units.seconds"] == {"one": "{count} Sekunde", "other": "{count} Sekunden"}
    assert body["fallback"] == []
    again = client.get("/api/messages/de", headers={"If-None-Match": response.headers["ETag"]})
    assert again.status_code == 304
    arabic = client.get("/api/messages/ar").json()
    assert arabic["direction"] == "rtl" and "zero" in arabic["plural_categories"] and arabic["fallback"]
    assert client.get("/api/messages/fr").json()["language"] == "en"  # no catalogue: English
    assert client.get("/api/messages/not a tag").status_code == 422
    schema = client.get("/openapi.json").json()
    assert "MessagesRead" in schema["components"]["schemas"]


def test_the_join_page_learns_the_studys_language(database_url) -> None:
    from tests.server.factories import fast_config, make_study

    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=fast_config(languages=["de", "en"]))
    assert client.get("/api/studies/s1/language").json() == {"language": "de", "direction": "ltr"}
    assert client.get("/api/studies/s1/language", headers={"Accept-Language": "en-GB"}).json()["language"] == "en"
    assert client.get("/api/studies/s1/language", params={"lang": "en"}).json()["language"] == "en"
    unknown = client.get("/api/studies/nope/language", headers={"Accept-Language": "ar"})
    assert unknown.json() == {"language": "ar", "direction": "rtl"}  # no such study: the shipped catalogues


def test_trustlab_i18n_check_passes_and_names_what_a_language_lacks() -> None:
    from typer.testing import CliRunner

    from server.cli import app

    result = CliRunner().invoke(app, ["i18n", "check"])
    assert result.exit_code == 0, result.output
    assert "de: 100 % of" in result.output and "en: 100 % of" in result.output
    assert re.search(r"ar: \d+ % of \d+ keys translated; English for \d+", result.output)


def test_a_clients_language_tags_never_grow_the_caches() -> None:
    i18n.catalogue("en")
    before = i18n._catalogue.cache_info().currsize
    for n in range(50):
        i18n.catalogue_json(f"x{n:02d}-AB")  # made-up tags, as a client may send
        i18n.Translator(f"zz-{n:02d}")
    assert i18n._catalogue.cache_info().currsize == before
    assert i18n._catalogue_json.cache_info().currsize <= len(i18n.shipped_languages())
