"""The README's first lines: the two commands, and what it says they need, checked against what the code needs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COMMANDS = [
    "python3 -m venv .venv && .venv/bin/pip install -q -e . && .venv/bin/trustlab serve",
    "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && .venv/bin/python -m pytest",
]


def quick_start() -> tuple[list[str], str]:
    """The README's first code block (its lines) and the paragraph after it (one line of words)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    match = re.search(r"```bash\n(.*?)\n```\n\n(.*?)\n\n", text, re.S)
    assert match, "the README begins with a bash block and a paragraph"
    return match.group(1).splitlines(), " ".join(match.group(2).split())


def test_the_two_commands_and_what_they_need_from_the_system():
    commands, words = quick_start()
    assert commands == COMMANDS
    assert "Run them in two terminals" in words and "serves until you stop it" in words
    # what the test command needs, as the tests and CI need it
    from server.harness.browser import CHROMIUM
    from tests import conftest

    assert f"`chromium` (`{CHROMIUM}`" in words and "`nginx`" in words
    assert "PostgreSQL is optional" in words
    assert "`TRUSTLAB_TEST_POSTGRES_URL`" in words
    assert "TRUSTLAB_TEST_POSTGRES_URL" in Path(conftest.__file__).read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    assert "export TRUSTLAB_TEST_POSTGRES_URL=" in ci and "chromium" in ci and "nginx" in ci
