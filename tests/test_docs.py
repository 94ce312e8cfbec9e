"""The documentation: the site builds in strict mode (a broken link between pages fails), the README's links reach
pages that exist, and the results log is one JSON object a line that every benchmark script appends to."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
#: What every line of docs/results.jsonl has (benchmarks/results_log.py writes them; the history was converted).
RESULT_KEYS = {"date", "script", "commit", "config", "figures", "note"}


def test_the_docs_build_in_strict_mode(tmp_path):
    # mkdocs is in the test extra (CI installs it): missing is a failure, not a skip
    assert importlib.util.find_spec("mkdocs") is not None, "mkdocs is missing: pip install -e '.[test]'"
    assert importlib.util.find_spec("material") is not None, "mkdocs-material is missing: pip install -e '.[test]'"
    built = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                           cwd=ROOT, capture_output=True, text=True, timeout=300,
                           env=os.environ | {"NO_MKDOCS_2_WARNING": "1"})
    assert built.returncode == 0, built.stdout + built.stderr
    assert (tmp_path / "site" / "architecture" / "index.html").exists()


def test_every_page_is_in_the_nav():
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    pages = sorted(path.name for path in DOCS.glob("*.md"))
    assert [page for page in pages if f": {page}" not in nav] == []


def test_the_readmes_links_reach_pages_and_headings_that_exist():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)]+)\)", readme)
    assert links, "the README links to the docs"
    for link in links:
        path, _, anchor = link.partition("#")
        assert not re.match(r"[a-z]+://", path), f"{link}: the README links only into the repository"
        target = ROOT / path
        assert target.exists(), f"{link}: no such file"
        if anchor:
            headings = re.findall(r"^#+ (.+)$", target.read_text(encoding="utf-8"), re.M)
            assert anchor in {slug(heading) for heading in headings}, f"{link}: no such heading"


def slug(heading: str) -> str:
    """The anchor MkDocs (and GitHub) give a heading, for the headings these docs use."""
    return re.sub(r"[\s]+", "-", re.sub(r"[^\w\s-]", "", heading.strip().lower()))


def test_the_results_log_is_json_lines_that_every_benchmark_appends_to():
    lines = (DOCS / "results.jsonl").read_text(encoding="utf-8").splitlines()
    assert len(lines) >= 39  # the README's performance history, then every run since
    for number, line in enumerate(lines, 1):
        entry = json.loads(line)
        assert RESULT_KEYS <= entry.keys(), f"line {number}: {sorted(RESULT_KEYS - entry.keys())} missing"
        assert entry["script"].startswith("bench_") and (ROOT / "benchmarks" / entry["script"]).exists(), number
    for script in sorted((ROOT / "benchmarks").glob("bench_*.py")):
        assert "append_result(" in script.read_text(encoding="utf-8"), f"{script.name} does not log its figures"
