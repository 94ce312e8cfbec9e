"""Section 4: the model's belief against self-reported trust, and reliance against trust (paper §4.4–4.5, Table 4).

The belief is the one stored with each shelf-survey answer in ``surveys.csv``:
P(trust high) under the *study's* configured model and belief update when the
answer was given (the end of the shelf), not under a model fitted here.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from experiment import defaults
from experiment.analysis import fit_linear, fit_logistic, logistic, median_by_answer
from experiment.report.content import FigureBlock, Missing, Paragraph, Section, TableBlock, fmt
from experiment.report.data import ExportData, number
from experiment.report.plots import COLOURS, box_by_level, new_figure, to_png

SCALE = np.arange(defaults.SHELF_SCALE_MIN, defaults.SHELF_SCALE_MAX + 1)


@dataclass(frozen=True)
class ShelfAnswers:
    """One row per answered shelf survey: (n,) arrays."""

    participant: list[str]
    block_name: list[str]
    trust: np.ndarray
    reliance: np.ndarray  # NaN where not answered
    belief: np.ndarray  # NaN where not stored


def shelf_answers(data: ExportData) -> ShelfAnswers:
    """The trust and reliance answers after each shelf, paired by participant and shelf, with the stored belief."""
    by_shelf: dict[tuple[str, str], dict[str, float | str | None]] = defaultdict(dict)
    for row in data.included_surveys():
        if row["context"].startswith("shelf:") and row["item"] in ("trust", "reliance"):
            entry = by_shelf[(row["participant_id"], row["context"])]
            entry[row["item"]] = number(row, "value")
            entry["block_name"] = row["block_name"]
            if row["item"] == "trust":
                entry["belief"] = number(row, "belief")
    shelves = [(pid, e) for (pid, _), e in by_shelf.items() if e.get("trust") is not None]

    def nan(v: float | str | None) -> float:
        return np.nan if v is None else float(v)

    return ShelfAnswers([pid for pid, _ in shelves], [str(e["block_name"]) for _, e in shelves],
                        np.array([nan(e["trust"]) for _, e in shelves]),
                        np.array([nan(e.get("reliance")) for _, e in shelves]),
                        np.array([nan(e.get("belief")) for _, e in shelves]))


def trust_section(data: ExportData, block_policies: dict[str, str]) -> Section:
    section = Section("trust", "Belief against self-reported trust, reliance against trust (paper §4.4–4.5)")
    if data.surveys is None:
        return section.add(Missing("No surveys.csv in the export: the shelf-survey analyses need it."))
    answers = shelf_answers(data)
    if answers.trust.size == 0:
        return section.add(Missing("No shelf-survey trust answers in surveys.csv (the design has no shelf "
                                   "questionnaire with a 'trust' item, or nobody answered one yet)."))
    section.add(Paragraph(f"{answers.trust.size} shelf surveys of {len(set(answers.participant))} participants. The "
                          "belief is the one stored with each answer: P(trust = high) at the end of the shelf under "
                          "the study's configured model (the model the study ran with, not the one fitted above)."))
    section.add(*_belief_part(answers, section), *_reliance_part(answers, section), _table4(answers, block_policies))
    return section


def _belief_part(answers: ShelfAnswers, section: Section) -> list[FigureBlock | Missing]:
    has = np.isfinite(answers.belief)
    if not has.any():
        return [Missing("No belief stored with the trust answers, so there is nothing to compare them with.")]
    trust, belief = answers.trust[has], answers.belief[has]
    levels, medians = median_by_answer(trust, belief)
    fig, axes = new_figure(8, 4.2)
    ax = axes[0]
    scale = np.union1d(SCALE, trust)  # the shelf scale, and any answer a lab's own scale allows beyond it
    box_by_level(ax, scale, [belief[trust == lv] for lv in scale], "high")
    ax.plot(levels, medians, "o", color="black", markersize=5, label="median belief per answer", zorder=4)
    grid = np.linspace(scale[0], scale[-1], 200)
    paper = logistic(grid, defaults.PAPER_LOGISTIC_L, defaults.PAPER_LOGISTIC_K, defaults.PAPER_LOGISTIC_R0)
    ax.plot(grid, paper, "--", color=COLOURS["paper"], linewidth=1, label="paper's logistic fit")
    out: list[FigureBlock | Missing] = []
    numbers = [("shelf surveys with a belief", str(int(has.sum()))), ("distinct answers", str(levels.size))]
    try:
        fit = fit_logistic(levels, medians)
    except ValueError as exc:
        out.append(Missing(f"No logistic fit: {exc}."))
    else:
        ax.plot(grid, fit(grid), color=COLOURS["fit"], linewidth=2, label="logistic fit to the medians")
        numbers += _logistic_numbers(fit)
        section.figures["logistic"] = {"L": fit.L, "k": fit.k, "r0": fit.r0, "sse": fit.sse, "rmse": fit.rmse,
                                       "n": fit.n}
    ax.set(xlim=(scale[0] - 0.6, scale[-1] + 0.6), ylim=(-0.02, 1.02),
           xlabel="trust answer r (0 = not at all, 10 = completely)",
           ylabel="belief P(T = high) at the end of the shelf")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("Model belief against self-reported trust (paper Figs. 7–8)")
    caption = ("Each box: the beliefs at the end of the shelves whose trust answer was r (box: quartiles, whiskers: "
               "1.5 IQR, points: every shelf). Black dots: median belief per answer; blue: the logistic "
               "P(r) = L / (1 + e^(−k (r − r0))) fitted to those medians by least squares (as MATLAB fit); dashed: "
               "the paper's fit.")
    out.insert(0, FigureBlock("fig_belief_vs_trust", "Belief against trust (paper §4.4)", caption, to_png(fig),
                              numbers))
    return out


def _logistic_numbers(fit) -> list[tuple[str, str]]:
    return [("L (paper 0.8849)", fmt(fit.L, 4)), ("k (paper 1.184)", fmt(fit.k, 4)),
            ("r0 (paper 2.932)", fmt(fit.r0, 4)), (f"SSE (paper {defaults.PAPER_LOGISTIC_SSE})", fmt(fit.sse, 4)),
            (f"RMSE = sqrt(SSE/(n−3)) (paper {defaults.PAPER_LOGISTIC_RMSE})", fmt(fit.rmse, 4)),
            ("medians fitted (n)", str(fit.n))]


def _reliance_part(answers: ShelfAnswers, section: Section) -> list[FigureBlock | Missing]:
    has = np.isfinite(answers.reliance)
    if has.sum() < 3:
        return [Missing("Fewer than 3 shelf surveys with both a trust and a reliance answer: no reliance analysis.")]
    trust, reliance = answers.trust[has], answers.reliance[has]
    fig, axes = new_figure(8, 4.2)
    ax = axes[0]
    scale = np.union1d(SCALE, trust)
    box_by_level(ax, scale, [reliance[trust == lv] for lv in scale], "rely")
    levels, medians = median_by_answer(trust, reliance)
    ax.plot(levels, medians, "o", color="black", markersize=5, label="median reliance per answer", zorder=4)
    ax.plot(scale, defaults.PAPER_RELIANCE_SLOPE * scale + defaults.PAPER_RELIANCE_INTERCEPT, "--",
            color=COLOURS["paper"], linewidth=1, label="paper: 0.63 r + 3.27")
    numbers: list[tuple[str, str]] = [("shelf surveys with both answers", str(int(has.sum())))]
    fits = {}
    for key, (x, y, style, label) in {"medians": (levels, medians, "-", "fit to the medians"),
                                      "all": (trust, reliance, ":", "fit to all answers")}.items():
        try:
            fits[key] = fit_linear(x, y)
        except ValueError as exc:
            numbers.append((f"linear {label}", f"none ({exc})"))
            continue
        ax.plot(scale, fits[key](scale), style, color=COLOURS["fit"], linewidth=2, label=label)
        numbers += _linear_numbers(fits[key], label)
    section.figures["reliance"] = {k: {"slope": f.slope, "intercept": f.intercept, "r2": f.r2, "n": f.n}
                                   for k, f in fits.items()}
    ax.set(xlim=(scale[0] - 0.6, scale[-1] + 0.6), xlabel="trust answer r (0–10)", ylabel="reliance answer (0–10)",
           ylim=(min(SCALE[0], reliance.min()) - 0.3, max(SCALE[-1], reliance.max()) + 0.3))
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("Self-reported reliance against trust (paper Figs. 9–10)")
    caption = ("Boxes: the reliance answers of the shelves whose trust answer was r. Lines: least-squares lines "
               "Rel(r) = slope·r + intercept fitted to the median reliance per trust answer (as §4.5 describes) and "
               "to all answer pairs; dashed: the paper's line. Brackets give 95 % confidence intervals.")
    return [FigureBlock("fig_reliance_vs_trust", "Reliance against trust (paper §4.5)", caption, to_png(fig), numbers)]


def _linear_numbers(fit, label: str) -> list[tuple[str, str]]:
    return [(f"slope, {label} (paper 0.63)", f"{fit.slope:.3f} [{fit.slope_ci[0]:.3f}, {fit.slope_ci[1]:.3f}]"),
            (f"intercept, {label} (paper 3.27)",
             f"{fit.intercept:.3f} [{fit.intercept_ci[0]:.3f}, {fit.intercept_ci[1]:.3f}]"),
            (f"R², {label} (n = {fit.n})", fmt(fit.r2))]


_PAPER_TABLE4 = {("trust", "trust_agnostic"): defaults.PAPER_SHELF_TRUST_AGNOSTIC,
                 ("trust", "trust_aware"): defaults.PAPER_SHELF_TRUST_AWARE,
                 ("reliance", "trust_agnostic"): defaults.PAPER_SHELF_RELIANCE_AGNOSTIC,
                 ("reliance", "trust_aware"): defaults.PAPER_SHELF_RELIANCE_AWARE}


def participant_means(answers: ShelfAnswers, item: str, block: str) -> np.ndarray:
    """(n_participants,) each participant's mean answer over the shelves of one block."""
    values = answers.trust if item == "trust" else answers.reliance
    per: dict[str, list[float]] = defaultdict(list)
    for pid, name, v in zip(answers.participant, answers.block_name, values, strict=True):
        if name == block and np.isfinite(v):
            per[pid].append(float(v))
    return np.array([np.mean(v) for v in per.values()])


def _table4(answers: ShelfAnswers, block_policies: dict[str, str]) -> TableBlock:
    rows = []
    for item in ("trust", "reliance"):
        for block in sorted(set(answers.block_name)):
            means = participant_means(answers, item, block)
            policy = block_policies.get(block, "")
            paper = _PAPER_TABLE4.get((item, policy))
            var = float(np.var(means, ddof=1)) if means.size > 1 else None
            rows.append([item, f"{block} ({policy})" if policy and policy != block else block, str(means.size),
                         fmt(float(np.mean(means)) if means.size else None, 2),
                         fmt(float(np.median(means)) if means.size else None, 2), fmt(var, 2),
                         " / ".join(f"{v:.2f}" for v in paper) if paper else "—"])
    return TableBlock("Shelf-survey answers per block (paper Table 4)",
                      ["item", "block (policy)", "participants", "mean", "median", "variance",
                       "paper mean / median / variance"],
                      rows, "Statistics over participants of each participant's mean answer in the block "
                      "(variance with n − 1).")
