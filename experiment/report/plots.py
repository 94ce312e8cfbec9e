"""Matplotlib helpers for the report: object-oriented API on the Agg canvas (no pyplot, no global state).

Figures are drawn with ``matplotlib.figure.Figure`` and rendered to PNG bytes
by the Agg backend, so report generation is safe in a server's worker
threads and needs no display.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LinearSegmentedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

DPI = 110
#: One colour per meaning, used in every figure.
COLOURS = {"high": "#2b6cb0", "low": "#dd6b20", "rely": "#2f855a", "intervene": "#c53030",
           "fit": "#2b6cb0", "paper": "#1a202c", "ask": "#fed7d7", "auto": "#c6f6d5"}
#: From "the robot acts alone" (0) to "the robot asks" (1).
ASK_MAP = LinearSegmentedColormap.from_list("ask", [COLOURS["rely"], COLOURS["intervene"]])
#: Numbers: a sequence or a 1-D array.
Values = Sequence[float] | np.ndarray
PAPER_MARKER: dict[str, Any] = dict(marker="D", color=COLOURS["paper"], markersize=5, linestyle="none", zorder=5)


def new_figure(width: float, height: float, ncols: int = 1, nrows: int = 1,
               sharey: bool = False) -> tuple[Figure, np.ndarray]:
    """A figure with an (nrows, ncols) array of axes."""
    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, sharey=sharey, squeeze=False)
    return fig, axes.ravel()


def to_png(fig: Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    return buffer.getvalue()


def probability_bars(ax: Axes, groups: Sequence[str], series: Sequence[tuple[str, str, Values]],
                     errors: Sequence[float], notes: Sequence[str], paper: Sequence[Values] | None) -> None:
    """Grouped bars of probabilities with ±1 SE error bars (clipped to [0, 1]) and the paper's values.

    groups: (G,) x labels. series: (label, colour key, values (G,)) per bar of a group; errors
    (G,): one SE per group (the series of a group are complementary probabilities, same SE);
    notes (G,): why a group has no SE (e.g. "boundary"), written under its label; paper: per
    series (G,) values or NaN. The values are printed in a band above the bars.
    """
    x = np.arange(len(groups))
    width = 0.8 / len(series)
    for i, (label, colour, values) in enumerate(series):
        pos = x + (i - (len(series) - 1) / 2) * width
        vals = np.asarray(values, dtype=float)
        err = np.asarray(errors, dtype=float)
        lower, upper = np.clip(vals - err, 0, 1), np.clip(vals + err, 0, 1)
        ax.bar(pos, np.nan_to_num(vals), width * 0.9, color=COLOURS[colour], label=label)
        has_error = np.isfinite(err) & np.isfinite(vals)
        ax.errorbar(pos[has_error], vals[has_error], yerr=[(vals - lower)[has_error], (upper - vals)[has_error]],
                    fmt="none", ecolor="black", capsize=4, linewidth=1.2)
        for p, v in zip(pos, vals, strict=True):  # values in a band above the plot, clear of bars and error bars
            ax.text(p, 1.09, f"{v:.2f}" if math.isfinite(v) else "—", ha="center", va="center", fontsize=8,
                    color=COLOURS[colour], fontweight="bold")
        if paper is not None:
            ax.plot(pos, np.asarray(paper[i], dtype=float), **PAPER_MARKER, label="paper" if i == 0 else None)
    if all(np.isnan(np.asarray(values, dtype=float)).all() for _, _, values in series):
        ax.text(0.5, 0.5, "no such trials in these data", transform=ax.transAxes, ha="center", va="center",
                fontsize=9, color="#4a5568")
    ax.axhline(1.02, color="#cbd5e0", linewidth=0.8)
    ax.set_xticks(x, [f"{g}\n({n})" if n else g for g, n in zip(groups, notes, strict=True)])
    ax.set_ylim(0, 1.16)
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.grid(axis="y", alpha=0.3)


def box_by_level(ax: Axes, levels: Values, samples: Sequence[np.ndarray], colour: str) -> None:
    """Box plots of samples at x = levels (empty ones skipped), jittered points, and n under each tick."""
    filled = [(lv, s) for lv, s in zip(levels, samples, strict=True) if len(s)]
    ax.set_xticks(list(levels), [f"{lv:g}\nn={len(s)}" for lv, s in zip(levels, samples, strict=True)])
    if not filled:
        return
    xs, data = [lv for lv, _ in filled], [s for _, s in filled]
    ax.boxplot(data, positions=xs, widths=0.5, manage_ticks=False, showfliers=False,
               patch_artist=True, boxprops=dict(facecolor=COLOURS[colour], alpha=0.35),
               medianprops=dict(color="black", linewidth=1.5))
    rng = np.random.default_rng(0)  # jitter only: fixed so the figure is reproducible
    for x, s in zip(xs, data, strict=True):
        ax.scatter(x + rng.uniform(-0.15, 0.15, len(s)), s, s=7, color=COLOURS[colour], alpha=0.45, linewidths=0)


def named_boxes(ax: Axes, names: Sequence[str], samples: Sequence[np.ndarray], colours: Sequence[str]) -> None:
    """Box plots of one sample per name, with every value as a jittered point and its n in the label."""
    positions = np.arange(1, len(names) + 1)
    boxes = ax.boxplot(list(samples), positions=positions, widths=0.5, showfliers=False, patch_artist=True,
                       medianprops=dict(color="black", linewidth=1.5),
                       tick_labels=[f"{n}\n(n={len(s)})" for n, s in zip(names, samples, strict=True)])
    rng = np.random.default_rng(0)
    for box, colour, x, s in zip(boxes["boxes"], colours, positions, samples, strict=True):
        box.set_facecolor(COLOURS[colour])
        box.set_alpha(0.35)
        ax.scatter(x + rng.uniform(-0.12, 0.12, len(s)), s, s=10, color=COLOURS[colour], alpha=0.7, linewidths=0)
    ax.grid(axis="y", alpha=0.3)


def policy_on_simplex(beliefs: np.ndarray, asks: np.ndarray, complexities: Sequence[str]) -> Figure:
    """Where the robot asks, one panel per complexity: beliefs (M, K) of the grid, asks (C, M) bool.

    x is P(the highest trust state), y P(the lowest); with three states that is the whole simplex (the middle
    state is 1 − x − y), with four each point is the share of grid beliefs there at which the robot asks.
    """
    fig, axes = new_figure(4.2 * len(complexities), 4.0, ncols=len(complexities), sharey=True)
    x, y = beliefs[:, -1], beliefs[:, 0]
    points, where = np.unique(np.round(np.stack([x, y], axis=1), 9), axis=0, return_inverse=True)
    where = where.reshape(-1)
    for ax, name, ask in zip(axes, complexities, asks, strict=True):
        share = np.bincount(where, weights=ask.astype(float), minlength=len(points)) / np.bincount(where)
        ax.scatter(points[:, 0], points[:, 1], c=share, cmap=ASK_MAP, vmin=0.0, vmax=1.0, s=9, marker="s",
                   linewidths=0)
        ax.plot([0, 1], [1, 0], color=COLOURS["paper"], linewidth=0.8)  # x + y ≤ 1
        ax.set_title(f"{name} complexity")
        ax.set_xlabel("P(highest trust state)")
        ax.set_xlim(-0.03, 1.03)
        ax.set_ylim(-0.03, 1.03)
        ax.set_aspect("equal")
    axes[0].set_ylabel("P(lowest trust state)")
    handles = [Line2D([], [], marker="s", linestyle="none", color=ASK_MAP(v), label=label)
               for v, label in ((1.0, "robot asks"), (0.0, "robot acts alone"))]
    axes[-1].legend(handles=handles, loc="upper right", frameon=False)
    return fig
