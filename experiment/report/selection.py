"""The report section "Which model the data support": the comparison of numbers of trust states (issue 40).

Shown when the report's model document carries the ``"selection"`` that chose it
(``experiment.model_selection.Selection.to_dict``, e.g. a model of ``trustlab fit --states 2,3,4`` or of the
dashboard's comparison): a table of every candidate, a figure of the held-out log-likelihood per trial ± SE
against the number of states, and the reason for the choice.

A model fitted with the trust ratings (``trustlab fit --with-ratings``, the dashboard's "Use trust ratings") has
``"ratings_comparison"`` (``model_selection.RatingsComparison.to_dict``) and ``"ratings"``
(``trust_ratings.RatingEmission.to_document``): the section then also says what the ratings added (the verdict,
held-out reliance with and without them, each state's mean rating and SD). With one number of states fitted with
ratings nothing was chosen (no ``"selection"``): that part is a short section of its own, "What the trust ratings
add".
"""

from __future__ import annotations

from typing import Any

import numpy as np

from experiment.report.content import FigureBlock, Paragraph, Section, TableBlock, fmt
from experiment.report.plots import COLOURS, new_figure, to_png

TITLE = "Which model the data support"
RATINGS_TITLE = "What the trust ratings add"


def selection_section(document: dict[str, Any]) -> Section | None:
    """The section of a model document's selection and of its comparison with and without trust ratings; None when
    the document has neither."""
    selection, comparison = document.get("selection"), document.get("ratings_comparison")
    if not selection:
        if not comparison:
            return None
        section = Section("ratings", RATINGS_TITLE)
        section.add(*_ratings_blocks(comparison, document.get("ratings")))
        section.figures = _ratings_figures(comparison, document.get("ratings"))
        return section
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
    if comparison:
        section.add(*_ratings_blocks(comparison, document.get("ratings"), heading=True))
        section.figures["ratings"] = _ratings_figures(comparison, document.get("ratings"))
    return section


def _ratings_blocks(comparison: dict[str, Any], ratings: dict[str, Any] | None,
                    heading: bool = False) -> list[Paragraph | TableBlock]:
    """The verdict, held-out reliance with and without the ratings, and each state's rating (mean and SD)."""
    verdict = str(comparison["verdict"])
    k = comparison["n_states"]
    out: list[Paragraph | TableBlock] = [Paragraph(
        (f"{RATINGS_TITLE}: this" if heading else "This")
        + f" model was fitted with the trust ratings ({comparison['n_ratings']} ratings, each placed at the last "
        "trial of its shelf and modelled as a beta-binomial of the trust state) as a second observation beside "
        f"reliance. The same {k} states were fitted again without them, in the same folds; both fits are scored on "
        "the held-out participants' reliance alone, the quantity the robot's policy uses. "
        f"{verdict[0].upper()}{verdict[1:]}.")]
    out.append(TableBlock("Held-out reliance with and without the trust ratings",
                          ["Fit", "Held-out log-likelihood of reliance per trial"],
                          [["with the ratings", fmt(comparison["held_out_with_ratings"], 4)],
                           ["without the ratings", fmt(comparison["held_out_without_ratings"], 4)],
                           ["difference (with − without) ± paired SE",
                            f"{fmt(comparison['difference_per_trial'], 4)} ± {fmt(comparison['difference_se'], 4)}"]],
                          note="Mean over folds; higher is better. The paired SE is over the held-out participants."))
    if ratings:
        lowest, highest = ratings["scale"]
        rows = [[f"state {j}", fmt(mean, 1), fmt(sd, 1)]
                for j, (mean, sd) in enumerate(zip(ratings["mean_rating"], ratings["sd_rating"], strict=True))]
        out.append(TableBlock("Trust rating by trust state",
                              ["Trust state (lowest reliance first)", f"Mean rating ({lowest}–{highest})",
                               "SD of a rating"], rows,
                              note="The rating emission's mean and standard deviation per state (a rating's spread "
                                   "includes how differently people use the scale)."))
    return out


def _ratings_figures(comparison: dict[str, Any], ratings: dict[str, Any] | None) -> dict[str, Any]:
    keys = ("n_states", "n_ratings", "held_out_with_ratings", "held_out_without_ratings", "difference_per_trial",
            "difference_se", "verdict")
    figures = {key: comparison[key] for key in keys}
    if ratings:
        figures |= {"scale": ratings["scale"], "mean_rating": ratings["mean_rating"], "sd_rating": ratings["sd_rating"]}
    return figures


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
