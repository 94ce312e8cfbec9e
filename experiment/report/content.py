"""What a report is made of: sections of paragraphs, cautions, figures and tables.

Section builders return these plain objects; ``experiment.report.html`` turns
them into a page. Figures carry their PNG bytes, so the same report can be
written as ``report.html`` + ``figures/*.png`` or as one page with the images
inlined.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Caution:
    """Something a reader must not miss (weak data, a result that cannot be trusted)."""

    text: str


@dataclass(frozen=True)
class Missing:
    """Why (part of) a section could not be computed, or is not applicable for this design."""

    text: str


@dataclass(frozen=True)
class FigureBlock:
    name: str  # file stem under figures/
    title: str
    caption: str
    png: bytes = field(repr=False)
    numbers: list[tuple[str, str]] = field(default_factory=list)  # (label, value) shown beside the figure


@dataclass(frozen=True)
class TableBlock:
    caption: str
    header: list[str]
    rows: list[list[str]]
    note: str = ""
    header_groups: list[tuple[str, int]] = field(default_factory=list)  # (label, columns spanned) above header


Block = Paragraph | Caution | Missing | FigureBlock | TableBlock


@dataclass
class Section:
    key: str  # anchor id
    title: str
    blocks: list[Block] = field(default_factory=list)
    #: Machine-readable key figures of the section (``--json``, ``report.json``).
    figures: dict[str, Any] = field(default_factory=dict)

    def add(self, *blocks: Block) -> Section:
        self.blocks.extend(blocks)
        return self

    def figure_blocks(self) -> list[FigureBlock]:
        return [b for b in self.blocks if isinstance(b, FigureBlock)]


def fmt(value: float | None, digits: int = 3) -> str:
    """A number for the page: fixed decimals, '—' when missing or not finite."""
    if value is None or not math.isfinite(value):
        return "—"
    return f"{value:.{digits}f}"


def fmt_p(p: float | None) -> str:
    """A p-value: 4 significant digits, scientific below 1e-4."""
    if p is None or not math.isfinite(p):
        return "—"
    return f"{p:.4g}" if p >= 1e-4 else f"{p:.2e}"
