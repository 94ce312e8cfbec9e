"""The analysis report: the paper's results section (§4–§5) for any study's export.

``build_report(export_dir)`` reads an export directory (``trials.csv`` and,
when present, ``surveys.csv``, ``participants.csv``, ``manifest.json``), fits
the trust IOHMM unless a model is given, and assembles five sections:
participant flow and data quality; the model (Figs. 4–6, Table 2; for a
model of three or four trust states its parameters, reliance and transitions),
followed, when the model carries the comparison of numbers of trust states that
chose it or the comparison with and without trust ratings, by "Which model the
data support" (or "What the trust ratings add"); the policies (§5.1; for three
or four states, where on the belief simplex the robot asks); belief and reliance against self-reported trust (§4.4–4.5,
Table 4); the policy comparison (§5.2–5.3, Table 3). ``Report.write(dir)``
writes ``report.html`` with ``figures/*.png``, ``report.json`` (the key
figures) and ``model.json``; ``Report.inline_html()`` is the same page with
the figures as data: URIs. A section that lacks data says what is missing;
an export without any model data raises ``DataError``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from experiment.report import html
from experiment.report.compare import block_policies, compare_section
from experiment.report.content import FigureBlock, Section
from experiment.report.data import load_export
from experiment.report.flow import flow_section
from experiment.report.model import ModelInfo, model_section, obtain_model
from experiment.report.model_states import k_state_model_section
from experiment.report.policy import policy_section
from experiment.report.selection import selection_section
from experiment.report.trust import trust_section
from experiment.task import TaskParams

__all__ = ["Report", "ReportFiles", "build_report"]

FIGURES_DIR = "figures"


@dataclass(frozen=True)
class ReportFiles:
    html: Path
    figures: list[Path]
    key_figures: Path
    model: Path


@dataclass
class Report:
    title: str
    source: str
    generated_at: str
    sections: list[Section]
    model_document: dict[str, Any] = field(repr=False)

    def key_figures(self) -> dict[str, Any]:
        """The numbers a reader would quote, per section (strict JSON: NaN as null)."""
        return _jsonable({s.key: s.figures for s in self.sections})

    def figures(self) -> list[FigureBlock]:
        return [f for s in self.sections for f in s.figure_blocks()]

    def inline_html(self) -> str:
        """One self-contained page: figures inlined as data: URIs."""
        return html.render(self, html.data_uri)

    def write(self, out_dir: str | Path) -> ReportFiles:
        """Write report.html, figures/*.png, report.json and model.json into ``out_dir``."""
        out = Path(out_dir)
        (out / FIGURES_DIR).mkdir(parents=True, exist_ok=True)
        paths = []
        for figure in self.figures():
            path = out / FIGURES_DIR / f"{figure.name}.png"
            path.write_bytes(figure.png)
            paths.append(path)
        page = out / "report.html"
        page.write_text(html.render(self, lambda f: f"{FIGURES_DIR}/{f.name}.png"), encoding="utf-8")
        key = out / "report.json"
        key.write_text(json.dumps(self.key_figures(), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        model = out / "model.json"
        model.write_text(json.dumps(_jsonable(self.model_document), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        return ReportFiles(page, paths, key, model)


def build_report(export_dir: str | Path, *, model: str | Path | None = None, restarts: int = 20, seed: int = 0,
                 p_high: float | None = None, task: TaskParams | None = None, title: str | None = None,
                 source: str | None = None, progress: Callable[[int, int], None] | None = None) -> Report:
    """The report of the export in ``export_dir``.

    model: a model JSON file or ``"paper"``; None fits one (``restarts``, ``seed``). p_high:
    P(C = high) for the policy (None: the share of high-complexity trials in the data). task:
    success probabilities and rewards (None: the paper's). title, source: how the page names the
    study and where the data came from (defaults from the export). progress(done, total): the fit's.
    Raises ``DataError`` (no model data, malformed files) or ``ModelError`` (bad model file).
    """
    data = load_export(export_dir)
    task = task or TaskParams()
    info = obtain_model(data, model, restarts, seed, progress)
    selection = selection_section(info.document)
    model_part = model_section(info, data) if isinstance(info, ModelInfo) else k_state_model_section(info, data)
    sections = [flow_section(data), model_part, *([selection] if selection else []),
                policy_section(info, data, task, p_high), trust_section(data, block_policies(data)),
                compare_section(data)]
    manifest = data.manifest or {}
    first = next(iter(data.trials.values()))[0]
    name = title or manifest.get("title") or manifest.get("study") or first.get("study") or data.source.name
    return Report(title=f"Analysis report: {name}", source=source or str(data.source.resolve()),
                  generated_at=datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"), sections=sections,
                  model_document=info.document)


def _jsonable(value: Any) -> Any:
    """NaN/inf -> None and numpy scalars -> Python numbers, recursively."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "tolist"):
        return _jsonable(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value
