"""The report section "Which model the data support": the comparison of numbers of trust states (issue 40).

Shown when the report's model document carries the ``"selection"`` that chose it
(``experiment.model_selection.Selection.to_dict``, e.g. a model of ``trustlab fit --states 2,3,4`` or of the
dashboard's comparison): a table of every candidate, a figure of the held-out log-likelihood per trial ± SE
against the number of states, and the reason for the choice.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from experiment.report.content import FigureBlock, Paragraph, Section, TableBlock, fmt
from experiment.report.plots import COLOURS, new_figure, to_png

TITLE = "Which model the data support"


def selection_section(document: dict[str, Any]) -> Section | None:
    """The section of a model document's selection; None when the document has none."""
    selection = document.get("selection")
    if not selection:
        return None
    chosen, candidates = selection["chosen"], selection["candidates"]
    section = Section("selection", TITLE)
    section.add(Paragraph(
        f"Numbers of trust states {', '.join(str(c['n_states']) for c in candidates)} were compared by "
        f"{selection['folds']}-fold cross-validation by participant (seed {selection['seed']}): each fold's "
        "participants are scored under the fit on the others, per trial. The model of this report has the number "
        "chosen. BIC (its sample size: the trials) and ICL (BIC plus the uncertainty of the state paths) are shown "
        "beside the choice, not used for it (docs/analysis.md)."))
    rows = [[str(c["n_states"]), fmt(c["loglik"], 2), str(c["n_free"]), fmt(c["bic"], 1), fmt(c["icl"], 1),
             f"{fmt(c['held_out_per_trial'], 4)} ± {fmt(c['held_out_se'], 4)}",
             "chosen" if c["n_states"] == chosen else ""] for c in candidates]
    section.add(TableBlock("Candidate numbers of trust states",
                           ["Trust states", "Log-likelihood", "Parameters", "BIC", "ICL",
                            "Held-out log-likelihood per trial ± SE", "Choice"], rows,
                           note="Higher log-likelihoods are better; lower BIC and ICL are better."),
                _held_out_figure(candidates, chosen),
                Paragraph(f"Chosen: {selection['reason']}."))
    section.figures = {"chosen": chosen, "reason": selection["reason"], "folds": selection["folds"],
                       "seed": selection["seed"],
                       "candidates": [{key: c[key] for key in ("n_states", "loglik", "n_free", "bic", "icl",
                                                               "held_out_per_trial", "held_out_se")}
                                      for c in candidates]}
    return section


def _held_out_figure(candidates: list[dict[str, Any]], chosen: int) -> FigureBlock:
    """Held-out log-likelihood per trial ± SE against K; the chosen K filled and labelled."""
    fig, (ax,) = new_figure(4.2, 3.0)
    ks = np.array([c["n_states"] for c in candidates])
    held = np.array([c["held_out_per_trial"] for c in candidates], dtype=float)
    se = np.array([c["held_out_se"] for c in candidates], dtype=float)
    ax.errorbar(ks, held, yerr=se, fmt="o", color=COLOURS["fit"], markerfacecolor="white", capsize=4)
    pick = ks == chosen
    ax.plot(ks[pick], held[pick], "o", color=COLOURS["fit"], markersize=8, zorder=4, label=f"chosen: {chosen} states")
    ax.set_xticks(ks)
    ax.set_xlim(ks.min() - 0.5, ks.max() + 0.5)
    ax.set_xlabel("trust states")
    ax.set_ylabel("held-out log-likelihood per trial")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    numbers = [(f"{c['n_states']} states", f"{fmt(c['held_out_per_trial'], 4)} ± {fmt(c['held_out_se'], 4)}")
               for c in candidates]
    return FigureBlock("selection_held_out", "Held-out log-likelihood per trial by number of trust states",
                       "Mean over folds of the held-out log-likelihood per trial, ± 1 standard error across folds; "
                       "the filled point is the chosen number of states.", to_png(fig), numbers)
