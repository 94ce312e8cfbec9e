"""Issue 41: no participant-facing English literal is left in the participant pages or in what the server says to
participants. The scan reads every string literal of the pages' scripts (each module that join.js and participant.js
import, directly or not), the text of the HTML pages, and the string literals of the server modules that word the
participant's state and errors; a new English sentence, label or capitalised word there fails it.

A literal passes when it is a catalogue key (the first argument of t, tn, tr or N_, which must exist), has no
letters, or is code: an id, class, event or field name (one lower-case word, snake_case, kebab-case, camelCase), a
path, a key code, a CSS value or selector. What is code but reads like prose is listed in ``ALLOWED`` with the file.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from server import i18n

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "static"
ENTRY_SCRIPTS = ("join.js", "participant.js")
#: Participant-page modules whose words are not in the catalogues yet, each with why. Remove a file from here once
#: its strings are catalogue keys (the scan then covers it).
PENDING: dict[str, str] = {}
#: Literals that are code but read like words, per file.
ALLOWED = {
    "fallback2d.js": {"dark yellow",  # the scene's colour names (data, never shown)
                      "px system-ui, sans-serif", "px system-ui, -apple-system, \"Segoe UI\", Roboto, sans-serif",
                      "600 "},
    "teleop.js": {"trial over"},  # the socket's close reason (protocol, never shown)
    "views.js": {"input, textarea"},  # a selector
    "i18n.js": {"*"},
}
#: Words that are code in the pages: key codes and DOM names (capitalised, so not caught as an identifier).
CODE_WORDS = {"Space", "Shift", "Escape", "Enter", "Tab", "ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight", "TEXTAREA",
              "Accept", "Content-Type", "Idempotency-Key", "POST", "GET", "PUT", "Element", "CSS", "Cache-Control",
              "Vary", "Accept-Encoding", "ETag"}
#: What reads as words: two words in a row, a capitalised word, a sentence's end.
PROSE = re.compile(r"(?<![\w.#-])[A-Za-z]+[ \u00a0]+[A-Za-z]{2,}(?![\w\[-])|\b[A-Z][a-z]{2,}\b|\s[a-z]{2,}[.!?…]$")
#: A literal put on the page as it is: the value (or a branch of the value) of a text property.
SHOWN = re.compile(r"\b(?:textContent|innerText|title|placeholder|alt)\s*=\s*(?:[^;]*[?:]\s*)?$")


def imported_scripts() -> list[str]:
    """The pages' modules: the entry scripts and everything they import, transitively."""
    seen: list[str] = []
    todo = list(ENTRY_SCRIPTS)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.append(name)
        todo += re.findall(r"""from\s+["']\./([\w.-]+\.js)["']""", (STATIC / "js" / name).read_text())
    return sorted(seen)


def js_literals(source: str) -> list[tuple[int, str, str]]:
    """Every string literal of a script (template literals by their fixed parts), as (line, text, code before it on
    its line); comments and regular expressions are skipped."""
    out: list[tuple[int, str, str]] = []
    i, n, line, last = 0, len(source), 1, ""
    while i < n:
        c = source[i]
        if c == "\n":
            line, i = line + 1, i + 1
            continue
        if source.startswith("//", i):
            i = source.find("\n", i)
            i = n if i < 0 else i
            continue
        if source.startswith("/*", i):
            end = source.find("*/", i + 2)
            line += source.count("\n", i, end)
            i = end + 2
            continue
        if c == "/" and last in ("", "(", ",", "=", ":", "[", "!", "&", "|", "?", "{", "}", ";", "return"):
            j = i + 1
            in_class = False
            while j < n and (source[j] != "/" or in_class):
                in_class = (in_class or source[j] == "[") and source[j] != "]"
                j += 2 if source[j] == "\\" else 1
            i, last = j + 1, "regex"
            continue
        if c in "\"'`":
            j, parts, text, depth = i + 1, [], "", 0
            while j < n and source[j] != c:
                if source[j] == "\\":
                    text += source[j + 1]
                    j += 2
                    continue
                if c == "`" and source.startswith("${", j):
                    parts.append(text)
                    text, depth, j = "", 1, j + 2
                    while depth and j < n:  # (nested literals in ${...} are short code here: skipped with it)
                        depth += {"{": 1, "}": -1}.get(source[j], 0)
                        j += 1
                    continue
                text += source[j]
                j += 1
            parts.append(text)
            before = source[source.rfind("\n", 0, i) + 1:i]
            out += [(line, part, before) for part in parts if part]
            line += source.count("\n", i, j)
            i, last = j + 1, "string"
            continue
        if not c.isspace():
            word = re.match(r"[A-Za-z_$][\w$]*", source[i:])
            last = word[0] if word else c
            i += len(word[0]) if word else 1
            continue
        i += 1
    return out


def problem(text: str, before: str, keys: set[str], allowed: set[str]) -> str | None:
    """Why a literal is participant-facing English (None: it is not)."""
    if re.search(r"\b(?:tn|tr|t|N_)\(\s*$", before):
        return None if text in keys else f"unknown catalogue key {text!r}"
    stripped = text.strip()
    if text in allowed or text in keys or stripped in CODE_WORDS or not re.search(r"[A-Za-z]", text):
        return None
    if PROSE.search(text):
        return f"English: {text!r}"
    if SHOWN.search(before) and re.fullmatch(r"[A-Za-z]{2,}", stripped):
        return f"a word shown on the page: {text!r}"
    return None  # code: an id, class, event or field name, a path, a selector


@pytest.fixture(scope="module")
def keys() -> set[str]:
    return set(i18n.translated(i18n.read_catalog("en"), "en"))


def test_the_scan_covers_every_participant_script() -> None:
    scripts = imported_scripts()
    assert {"participant.js", "join.js", "api.js", "i18n.js", "trial.js", "views.js", "steps.js", "teleop.js",
            "teleop-panel.js", "fallback2d.js", "events.js", "viewerpace.js"} <= set(scripts), scripts
    assert not [name for name in scripts if name.startswith("admin")]


@pytest.mark.parametrize("name", imported_scripts())
def test_no_english_literal_in_the_participant_scripts(name: str, keys: set[str]) -> None:
    if name in PENDING:
        pytest.xfail(f"{name}: {PENDING[name]}")
    found = [f"{name}:{line}: {why}" for line, text, before in js_literals((STATIC / "js" / name).read_text())
             if (why := problem(text, before, keys, ALLOWED.get(name, set())))]
    assert not found, "\n".join(found)


def test_the_scan_finds_a_new_english_literal(keys: set[str]) -> None:
    """The scan is not blind: a sentence, a capitalised label, a word put on the page and an unknown key are caught;
    code is not."""
    source = '''const a = "Please try again"; el.textContent = "closed"; const b = `Robot ${x}`; t("no.such.key");
      const c = "consent-agree"; const d = t("join.retry"); log("decline_asked", { view: "end_effector" });
      const r = /decision window has closed/; // "a comment, not a literal"
      const e = `${n} s left`;'''
    found = [why for _, text, before in js_literals(source) if (why := problem(text, before, keys, set()))]
    assert found == ["English: 'Please try again'", "a word shown on the page: 'closed'", "English: 'Robot '",
                     "unknown catalogue key 'no.such.key'", "English: ' s left'"], found


@pytest.mark.parametrize("page", ["join.html", "participant.html"])
def test_no_english_text_in_the_participant_pages(page: str, keys: set[str]) -> None:
    html = (STATIC / page).read_text()
    html = re.sub(r"<!--.*?-->", "", html, flags=re.DOTALL)
    # Without JavaScript no catalogue can load: the noscript line is written in each shipped language, marked lang.
    noscript = re.findall(r"<noscript>(.*?)</noscript>", html, flags=re.DOTALL)
    assert len(noscript) == 1 and {"en", "de"} <= set(re.findall(r'lang="(\w+)"', noscript[0]))
    html = re.sub(r"<noscript>.*?</noscript>", "", html, flags=re.DOTALL)
    texts = [t.strip() for t in re.findall(r">([^<]+)<", html) if re.search(r"[A-Za-z]", t)]
    assert texts == [], texts
    attributes = re.findall(r'(?<![\w-])(?:aria-label|title|alt|placeholder)="([^"]*[A-Za-z][^"]*)"', html)
    assert attributes == [], attributes
    used = set(re.findall(r'data-i18n(?:-[a-z-]+)?="([^"]+)"', html))
    assert used and used <= keys, sorted(used - keys)


#: The server modules that word what a participant reads (the state, the teleoperation guidance, errors).
SERVER_MODULES = ("server/services/state.py", "server/services/wording.py", "server/services/sessions.py",
                  "server/services/joining.py", "server/services/screening.py", "server/routes/participant.py",
                  "server/routes/messages.py", "server/services/teleop_views.py", "experiment/world/guidance.py")


#: Server literals that are English on purpose, per module: parts of errors' English ``detail`` (for API clients and
#: logs; the pages show the error's catalogue key instead) and English names kept for records and bots.
ALLOWED_SERVER = {
    "server/routes/participant.py": {"from this address", "for this study", "the session is at "},
    "server/services/sessions.py": {"unknown session link; please use the link you were given"},  # _UNKNOWN_TOKEN
    "server/services/joining.py": {"This study is full right now. Please try again in a few minutes."},
    # describe_target's English words (records, bots, the socket's scene description); participants read the item's
    # name from its parts (target_parts) through the catalogues.
    "experiment/world/guidance.py": {"dark yellow", "bottom shelf", "top shelf", "far right", "right of centre",
                                     "left of centre", "far left", " on the "},
}


def python_literals(path: Path) -> list[tuple[int, str]]:
    """String literals of a module that are not docstrings."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
                  and node.body and isinstance(node.body[0], ast.Expr)
                  and isinstance(node.body[0].value, ast.Constant)}
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings]


def raised_detail_literals(path: Path) -> set[str]:
    """The literal parts of errors' ``detail`` (the first argument of a raise): English for API clients and logs,
    never shown on a page (the page shows the error's catalogue key, ``message``)."""
    parts: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and node.exc.args:
            for inner in ast.walk(node.exc.args[0]):
                if isinstance(inner, ast.Constant) and isinstance(inner.value, str):
                    parts.add(inner.value)
    return parts


@pytest.mark.parametrize("module", SERVER_MODULES)
def test_the_server_words_participants_read_come_from_the_catalogues(module: str, keys: set[str]) -> None:
    path = ROOT / module
    details = raised_detail_literals(path)
    found = [f"{module}:{line}: {text!r}" for line, text in python_literals(path)
             if text not in details and PROSE.search(text) and text not in keys
             and text not in ALLOWED_SERVER.get(module, set()) and text not in CODE_WORDS
             and not text.startswith(("%", "^")) and "{" not in text]
    assert not found, "\n".join(found)


def test_every_error_a_participant_can_get_names_a_catalogue_sentence(keys: set[str]) -> None:
    from server import errors

    kinds = [cls for cls in vars(errors).values() if isinstance(cls, type) and issubclass(cls, errors.AppError)]
    assert len(kinds) >= 10
    assert all(cls.message in keys for cls in kinds), [cls.__name__ for cls in kinds if cls.message not in keys]
    for module in SERVER_MODULES:
        for key in re.findall(r"message=N_\(\"([^\"]+)\"\)", (ROOT / module).read_text()):
            assert key in keys, (module, key)
    # The pages show an error's sentence by its key, never the English detail.
    for name in imported_scripts():
        source = (STATIC / "js" / name).read_text()
        shown = [line for line in source.splitlines() if re.search(r"\berr\.detail\b", line) and "log(" not in line]
        assert not shown, (name, shown)
