"""``trustlab i18n``: the participant pages' catalogues (server/locales; docs/languages.md).

``extract`` writes the template of every key the code uses (Babel's extraction with babel.cfg), each with its
English text as a comment for translators; ``update`` merges it into every language's catalogue (new keys empty,
keys no longer used kept as obsolete); ``init LANG`` starts a new language; ``check`` compiles each catalogue with
Babel's checkers and says what each language lacks (English must be complete: it is every language's fallback).
The server reads the .po files themselves, so there is no separate compile step.
"""

from __future__ import annotations

from pathlib import Path

import typer
from babel.messages.catalog import Catalog
from babel.messages.extract import extract_from_dir
from babel.messages.frontend import parse_mapping_cfg
from babel.messages.pofile import read_po, write_po

from experiment.languages import canonical_tag, valid_tag
from server import i18n

ROOT = Path(__file__).resolve().parents[2]
TEMPLATE = i18n.LOCALES_DIR / f"{i18n.DOMAIN}.pot"

i18n_app = typer.Typer(help="The participant pages' languages: extract the keys, update and check the catalogues.",
                       no_args_is_help=True)


def register(app: typer.Typer) -> None:
    app.add_typer(i18n_app, name="i18n")


def template() -> Catalog:
    """Every key the code uses, a plural one as a plural, with its English text as a translator's comment."""
    with (ROOT / "babel.cfg").open() as file:
        method_map, options_map = parse_mapping_cfg(file)
    english = i18n.translated(i18n.read_catalog(i18n.SOURCE_LANGUAGE), i18n.SOURCE_LANGUAGE)
    catalog = Catalog(domain=i18n.DOMAIN, project="trustlab", fuzzy=False)
    for filename, lineno, message, _, _ in extract_from_dir(str(ROOT), method_map, options_map):
        key = message[0] if isinstance(message, tuple) else message
        text = english.get(key)
        said = text.get("other", "") if isinstance(text, dict) else text
        catalog.add(message, locations=[(filename, lineno)], auto_comments=[f"en: {said}"] if said else [])
    return catalog


def _write(path: Path, catalog: Catalog) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as file:
        write_po(file, catalog, width=120, sort_output=True, include_lineno=False)


def _read(path: Path, language: str) -> Catalog:
    with path.open("rb") as file:
        return read_po(file, locale=language.replace("-", "_"), domain=i18n.DOMAIN)


@i18n_app.command()
def extract() -> None:
    """Write server/locales/participant.pot: every key the pages and the server use."""
    catalog = template()
    _write(TEMPLATE, catalog)
    typer.echo(f"{len(catalog)} keys -> {TEMPLATE.relative_to(ROOT)}")


@i18n_app.command()
def update() -> None:
    """Merge the template (trustlab i18n extract) into every language's catalogue."""
    new = _read(TEMPLATE, i18n.SOURCE_LANGUAGE)
    for language in i18n.shipped_languages():
        path = i18n.po_path(language)
        catalog = _read(path, language)
        catalog.update(new, no_fuzzy_matching=True)
        _write(path, catalog)
        missing = len([message for message in catalog if message.id and not _done(message.string)])
        typer.echo(f"{language}: {len(catalog)} keys, {missing} to translate")


@i18n_app.command()
def init(language: str = typer.Argument(help="The new language's BCP 47 tag, e.g. es, fr, he")) -> None:
    """Start the catalogue of a new language from the template (every text empty: English until translated)."""
    if not valid_tag(language):
        raise typer.BadParameter(f"not a BCP 47 language tag: {language!r}")
    language = canonical_tag(language)
    path = i18n.po_path(language)
    if path.exists():
        raise typer.BadParameter(f"{path.relative_to(ROOT)} exists already: use trustlab i18n update")
    catalog = Catalog(locale=language.replace("-", "_"), domain=i18n.DOMAIN, project="trustlab", fuzzy=False)
    for message in _read(TEMPLATE, i18n.SOURCE_LANGUAGE):
        if message.id:
            catalog.add(message.id, auto_comments=message.auto_comments)
    _write(path, catalog)
    typer.echo(f"{path.relative_to(ROOT)}: {len(catalog)} keys to translate")


def _done(string: object) -> bool:
    return all(string) if isinstance(string, tuple | list) else bool(string)


@i18n_app.command()
def check() -> None:
    """Check every catalogue (Babel's checkers: placeholders, plural forms) and what each language lacks."""
    used = {str(m.id[0] if isinstance(m.id, tuple | list) else m.id) for m in template() if m.id}
    english = i18n.translated(i18n.read_catalog(i18n.SOURCE_LANGUAGE), i18n.SOURCE_LANGUAGE)
    failed = False
    for language in i18n.shipped_languages():
        catalog = i18n.read_catalog(language)
        texts = i18n.translated(catalog, language)
        problems = [f"{message.id}: {error}" for message, errors in catalog.check() for error in errors]
        problems += [f"{key}: placeholders differ from English" for key, text in texts.items()
                     if key in english and i18n.placeholders(text) != i18n.placeholders(english[key])]
        missing = sorted(used - set(texts))
        if language == i18n.SOURCE_LANGUAGE and missing:
            problems.append(f"English lacks {', '.join(missing)} (every language falls back to it)")
        share = 100 * len(used & set(texts)) / max(1, len(used))
        typer.echo(f"{language}: {share:.0f} % of {len(used)} keys translated"
                   + (f"; English for {len(missing)}" if missing and language != i18n.SOURCE_LANGUAGE else ""))
        for line in problems:
            typer.echo(f"  {line}", err=True)
        failed |= bool(problems)
    if failed:
        raise typer.Exit(1)
