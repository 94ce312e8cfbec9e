"""The report as one HTML page: no script, one inline style sheet, figures as files or data: URIs.

``content_security_policy()`` gives the header under which the page works
when served (it allows exactly the inline style sheet, by hash, and images
from data: URIs or the same origin).
"""

from __future__ import annotations

import base64
import hashlib
import json
from collections.abc import Callable
from html import escape
from typing import TYPE_CHECKING

from experiment.report.content import Caution, FigureBlock, Missing, Paragraph, TableBlock

if TYPE_CHECKING:
    from experiment.report import Report

STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1200px;padding:1.5rem;
color:#1a202c;line-height:1.45}
h1{font-size:1.6rem;margin-bottom:.2rem}h2{border-bottom:2px solid #cbd5e0;padding-bottom:.2rem;margin-top:2.2rem}
.meta{color:#4a5568;font-size:.9rem}nav ol{columns:2;font-size:.95rem}
figure{margin:1.2rem 0;border:1px solid #e2e8f0;padding:.8rem;border-radius:6px}
figure img{display:block;max-width:100%;height:auto;margin:0 auto}
figure .below{display:flex;flex-wrap:wrap;gap:1.2rem;align-items:flex-start;margin-top:.6rem}
figcaption{flex:1 1 360px;font-size:.9rem;color:#2d3748}
figure table{flex:0 1 520px;margin:0}
table{border-collapse:collapse;font-size:.85rem;margin:.6rem 0}
th,td{border:1px solid #cbd5e0;padding:.25rem .5rem;text-align:left;vertical-align:top}
th{background:#edf2f7}td.num{text-align:right;font-variant-numeric:tabular-nums}
.caution{background:#fffaf0;border-left:4px solid #dd6b20;padding:.5rem .8rem;margin:.6rem 0}
.missing{background:#f7fafc;border-left:4px solid #718096;padding:.5rem .8rem;margin:.6rem 0;color:#2d3748}
.note{font-size:.85rem;color:#4a5568;max-width:70rem}
"""


def content_security_policy() -> str:
    """CSP for serving the page: nothing but its own style sheet and images from data: URIs (or the same origin)."""
    digest = base64.b64encode(hashlib.sha256(STYLE.encode()).digest()).decode()
    return (f"default-src 'none'; img-src 'self' data:; style-src 'sha256-{digest}'; base-uri 'none'; "
            "form-action 'none'; frame-ancestors 'self'")


def data_uri(figure: FigureBlock) -> str:
    return "data:image/png;base64," + base64.b64encode(figure.png).decode()


def render(report: Report, image_src: Callable[[FigureBlock], str]) -> str:
    """The page; ``image_src`` gives each figure's src (a relative path, or a data: URI)."""
    counter = iter(range(1, 1000))
    parts = [f"<!doctype html><html lang=en><head><meta charset=utf-8><title>{escape(report.title)}</title>"
             f"<meta name=viewport content='width=device-width,initial-scale=1'><style>{STYLE}</style></head><body>",
             f"<h1>{escape(report.title)}</h1>",
             f"<p class=meta>Data: {escape(report.source)}. Generated {escape(report.generated_at)} by trustlab. "
             "Figures: PNG; probabilities on [0, 1], rewards in points, survey answers on their scales.</p>",
             "<nav><ol>" + "".join(f"<li><a href='#{s.key}'>{escape(s.title)}</a></li>" for s in report.sections)
             + "</ol></nav>"]
    for section in report.sections:
        parts.append(f"<section id='{section.key}'><h2>{escape(section.title)}</h2>")
        parts += [_block(block, image_src, counter) for block in section.blocks]
        parts.append("</section>")
    figures = json.dumps(report.key_figures(), allow_nan=False).replace("</", "<\\/")
    parts.append(f"<script type='application/json' id='key-figures'>{figures}</script></body></html>")
    return "\n".join(parts)


def _block(block: object, image_src: Callable[[FigureBlock], str], counter) -> str:
    if isinstance(block, Paragraph):
        return f"<p>{escape(block.text)}</p>"
    if isinstance(block, Caution):
        return f"<p class=caution><strong>Caution.</strong> {escape(block.text)}</p>"
    if isinstance(block, Missing):
        return f"<p class=missing>{escape(block.text)}</p>"
    if isinstance(block, TableBlock):
        return _table(block)
    assert isinstance(block, FigureBlock)
    numbers = "".join(f"<tr><th>{escape(k)}</th><td class=num>{escape(v)}</td></tr>" for k, v in block.numbers)
    return (f"<figure id='{block.name}'><img src='{escape(image_src(block))}' alt='{escape(block.title)}'>"
            f"<div class=below><figcaption><strong>Figure {next(counter)}. {escape(block.title)}.</strong> "
            f"{escape(block.caption)}</figcaption>" + (f"<table>{numbers}</table>" if numbers else "")
            + "</div></figure>")


def _table(block: TableBlock) -> str:
    head = "".join(f"<th>{escape(h)}</th>" for h in block.header)
    if block.header_groups:
        groups = "".join(f"<th colspan={span}>{escape(label)}</th>" for label, span in block.header_groups)
        head = f"{groups}</tr><tr>{head}"
    body = "".join("<tr>" + "".join(f"<td{_cls(c)}>{escape(c)}</td>" for c in row) + "</tr>" for row in block.rows)
    note = f"<p class=note>{escape(block.note)}</p>" if block.note else ""
    return (f"<table><caption>{escape(block.caption)}</caption><thead><tr>{head}</tr></thead>"
            f"<tbody>{body}</tbody></table>{note}")


def _cls(cell: str) -> str:
    try:
        float(cell.replace("−", "-"))
    except ValueError:
        return ""
    return " class=num"
