"""The results log: every benchmark run appends one JSON line to ``docs/results.jsonl`` (docs/benchmarks.md).

The log is append-only: a line is never edited, a later run is a new line. Each line holds the date (UTC), the
script, the commit it ran (``git rev-parse --short HEAD``, with ``+dirty`` when the tree had changes), the run's
configuration, its figures and a short note. Scripts that put the repository root on ``sys.path`` import it as
``benchmarks.results_log``; the others, run as ``python benchmarks/bench_x.py``, as ``results_log``.
"""

from __future__ import annotations

import json
import subprocess
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
LOG = ROOT / "docs" / "results.jsonl"


def current_commit() -> str | None:
    """The short hash of HEAD, ``+dirty`` if the working tree differs from it; None outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "") if head else None


def append_result(script: str, config: dict[str, Any], figures: dict[str, Any], note: str = "",
                  *, log: Path = LOG) -> dict[str, Any]:
    """Append one run to the log and return the entry. ``script``: the file name (``bench_fit.py``); ``config``:
    what was run (arguments, sizes, backend); ``figures``: what it measured. Values that JSON has no type for
    (numpy numbers, paths) are written as text."""
    entry = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "script": script, "commit": current_commit(),
             "config": config, "figures": figures, "note": note}
    line = json.dumps(entry, ensure_ascii=False, default=_plain)
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a", encoding="utf-8") as f:
        f.write(line + "\n")
    print(f"(appended to {log.relative_to(ROOT) if log.is_relative_to(ROOT) else log})")
    return entry


def _plain(value: Any) -> Any:
    """numpy scalars as numbers, anything else as its text."""
    item = getattr(value, "item", None)
    return item() if callable(item) else str(value)
