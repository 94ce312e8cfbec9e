"""Section 2 for a model of three or four trust states (issue 40): its parameters, reliance and transitions.

The two-state section (``experiment.report.model``) follows the paper's Figs. 4–6 and Table 2. A model of K ≥ 3
states has no paper values to compare with, so its section shows what the model says: a table of every parameter
of the ``trustlab-iohmm-k`` document (``trust_states_document.parameter_names``) with its standard error and status
as the document holds them, P(rely | state) by complexity, and the transitions as one K × K matrix per input
(complexity, robot action, experience) with the probabilities written in. States are numbered from the lowest
trust (state 0) to the highest, as in the document.
"""

from __future__ import annotations

import math
from itertools import product

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import LinearSegmentedColormap

from experiment.report.content import Caution, FigureBlock, Paragraph, Section, TableBlock, fmt
from experiment.report.data import ExportData
from experiment.report.model import SHORT_STATUS, STATUS_TEXT, KStateModelInfo, fit_cautions
from experiment.report.plots import COLOURS, new_figure, to_png
from experiment.task import Complexity, Experience, RobotAction
from experiment.trust_states_document import state_names

#: Bars of P(rely | state): a light and a dark shade of the reliance colour for low and high complexity.
COMPLEXITY_SHADES = {Complexity.LOW: "#9ae6b4", Complexity.HIGH: COLOURS["rely"]}
#: Transition matrices: white (0) to the colour of high trust (1).
TRANSITION_MAP = LinearSegmentedColormap.from_list("transition", ["#ffffff", COLOURS["high"]])
EXPERIENCE_TEXT = {Experience.POSITIVE: "E+", Experience.NEGATIVE: "E−"}


def k_state_model_section(info: KStateModelInfo, data: ExportData) -> Section:
    k = info.n_states
    section = Section("model", f"The trust model: {k} trust states")
    section.add(Paragraph(
        f"{info.source} Log-likelihood of these data under the model: {fmt(info.loglik, 3)} ({data.n_trials} trials "
        f"of {len(data.trials)} participants). The model has {k} trust states, numbered from the lowest trust "
        f"(state 0) to the highest (state {k - 1}) by their reliance in high complexity; the paper's model has two, "
        "so no paper values are shown."))
    section.add(*_cautions(info), _reliance_figure(info), _transition_figure(info), _table(info))
    section.figures = {"n_states": k, "loglik": info.loglik, "n_trials": data.n_trials,
                       "n_participants": len(data.trials),
                       "status_counts": {s: info.status.count(s) for s in sorted(set(info.status))},
                       "params": {name: float(value) for name, value in zip(info.names, info.values, strict=True)},
                       "fitted_here": False}
    return section


def _cautions(info: KStateModelInfo) -> list[Caution | Paragraph]:
    out = fit_cautions(info.loglik_problem, list(info.status))
    fit = info.document.get("fit")
    if isinstance(fit, dict) and {"restarts", "seed", "converged"} <= fit.keys():
        out.append(Paragraph(f"Fitted by EM with {fit['restarts']} random restarts (seed {fit['seed']}); converged: "
                             f"{'yes' if fit['converged'] else 'no'}."))
        if not fit["converged"]:
            out.append(Caution("The fit did not meet its convergence test; the estimates may still move with more "
                               "iterations or restarts."))
    return out


# -- names -------------------------------------------------------------------------------------------

def parameter_label(name: str) -> str:
    """A K-state parameter name in words: P(T′ = state 2 | T = state 1, E′ = E+, C = low, a = auto)."""
    parts = name.split(".")
    if parts[0] == "transitions":
        c, a, e = parts[1:4]
        i, j = (p.removeprefix("from_").removeprefix("to_").replace("_", " ") for p in parts[4:6])
        return f"P(T′ = {j} | T = {i}, E′ = {'E+' if e == 'positive' else 'E−'}, C = {c}, a = {a})"
    if parts[0] == "emissions":
        return f"P(o = rely | T = {parts[3].removeprefix('p_rely_').replace('_', ' ')}, C = {parts[1]}, a = auto)"
    return f"P(T₁ = {parts[1].replace('_', ' ')})"


def _value_text(info: KStateModelInfo, i: int) -> str:
    value, se, status = info.values[i], info.stderr[i], info.status[i]
    if not math.isfinite(value):
        return "—"
    return f"{value:.3f} ± {se:.3f}" if math.isfinite(se) else f"{value:.3f} ({STATUS_TEXT[status]})"


# -- figures ------------------------------------------------------------------------------------------

def _reliance_figure(info: KStateModelInfo) -> FigureBlock:
    """P(rely | state, C, a = auto): a group of bars per state, one bar per complexity, ±1 SE where there is one."""
    k = info.n_states
    fig, (ax,) = new_figure(1.7 * k + 3.2, 3.6)
    x = np.arange(k)
    width = 0.38
    numbers = []
    for n, c in enumerate(Complexity):
        names = [f"emissions.{c.value}.auto.p_rely_state_{j}" for j in range(k)]
        index = [info.names.index(name) for name in names]
        values, errors = info.values[index], info.stderr[index]
        pos = x + (n - 0.5) * width
        ax.bar(pos, values, width * 0.92, color=COMPLEXITY_SHADES[c], edgecolor=COLOURS["rely"],
               label=f"C = {c.value}")
        has = np.isfinite(errors)
        lower, upper = np.clip(values - errors, 0, 1), np.clip(values + errors, 0, 1)
        ax.errorbar(pos[has], values[has], yerr=[(values - lower)[has], (upper - values)[has]], fmt="none",
                    ecolor="black", capsize=4, linewidth=1.2)
        for p, v, i in zip(pos, values, index, strict=True):
            ax.text(p, 1.09, f"{v:.2f}", ha="center", va="center", fontsize=8, color=COLOURS["paper"],
                    fontweight="bold")
            note = SHORT_STATUS.get(info.status[i], "")
            if note:
                ax.text(p, 0.02, note, ha="center", va="bottom", rotation=90, fontsize=7, color="#1a202c")
            numbers.append((parameter_label(info.names[i]), _value_text(info, i)))
    ax.axhline(1.02, color="#cbd5e0", linewidth=0.8)
    ax.set_xticks(x, [f"state {j}" + (" (lowest)" if j == 0 else " (highest)" if j == k - 1 else "")
                      for j in range(k)])
    ax.set_xlabel("trust state T")
    ax.set_ylabel("P(human relies | T, C, a = auto)")
    ax.set_ylim(0, 1.16)
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, bbox_to_anchor=(1.0, 1.0), title="complexity", title_fontsize=8)
    fig.suptitle("Reliance by trust state, P(o = rely | T, C, a = auto); error bars ±1 SE")
    caption = ("Probability that the human relies on the robot acting alone, for each trust state (lowest first) and "
               "complexity. When the robot asks, the human always assists, in every state. Error bars: ±1 Laplace "
               "standard error (clipped to [0, 1]); a bar without one has a note (boundary, unidentified, …) or the "
               "model file gives none. The values are printed above the bars.")
    return FigureBlock("fig_states_reliance", f"Reliance by trust state ({k} states)", caption, to_png(fig), numbers)


def _inputs(info: KStateModelInfo) -> list[tuple[RobotAction, Experience]]:
    """(a, E′) columns of the transition figure: those with an estimate in either complexity."""
    shown = []
    for a, e in product(RobotAction, (Experience.POSITIVE, Experience.NEGATIVE)):
        if any(np.isfinite(info.params.transition[c.code, a.code, e.code]).any() for c in Complexity):
            shown.append((a, e))
    return shown


def _transition_figure(info: KStateModelInfo) -> FigureBlock:
    """One K × K matrix per input: rows the trust state before the trial, columns after it, numbers written in."""
    k, inputs = info.n_states, _inputs(info)
    side = 1.0 + 0.55 * k
    fig, axes = new_figure(side * len(inputs) + 1.2, 2 * side + 0.9, ncols=len(inputs), nrows=2)
    grid = axes.reshape(2, len(inputs))
    image = None
    for (row, c), (col, (a, e)) in product(enumerate(Complexity), enumerate(inputs)):
        matrix = info.params.transition[c.code, a.code, e.code]
        image = _matrix(grid[row, col], matrix, k)
        grid[row, col].set_title(f"C = {c.value}, a = {a.value}, {EXPERIENCE_TEXT[e]}", fontsize=9)
        if col == 0:
            grid[row, col].set_ylabel("from state T")
        if row == 1:
            grid[row, col].set_xlabel("to state T′")
    if image is not None:
        fig.colorbar(image, ax=list(axes), shrink=0.6, label="P(T′ | T, E′, C, a)")
    fig.suptitle("Trust transitions P(T′ | T, E′, C, a): one matrix per input (rows: before, columns: after)")
    caption = ("Probability of the next trust state T′ (columns) given the state before the trial T (rows), for "
               "each complexity C, robot action a and experience E′ the trial gave (E+ positive, E− negative). States "
               "are numbered from the lowest trust (0); the diagonal is staying, right of it moving up, left of it "
               "moving down. Each row sums to 1. A grey row is an input the data never exercised (no estimate). "
               "Standard errors are in the parameter table below. Beside: per input (complexity, action, "
               "experience) and state before, the probabilities of staying / moving up / moving down.")
    numbers = []
    for c, (a, e) in product(Complexity, inputs):
        matrix = info.params.transition[c.code, a.code, e.code]
        for i in range(k):
            if np.isfinite(matrix[i]).all():
                numbers.append((f"{c.value}, {a.value}, {EXPERIENCE_TEXT[e]}, from state {i}", _moves(matrix[i], i)))
    return FigureBlock("fig_states_transitions", f"Trust transitions ({k} states)", caption, to_png(fig), numbers)


def _matrix(ax: Axes, matrix: np.ndarray, k: int):
    shown = np.ma.masked_invalid(matrix)
    ax.set_facecolor("#e2e8f0")  # an input row without an estimate
    image = ax.imshow(shown, cmap=TRANSITION_MAP, vmin=0.0, vmax=1.0)
    for i, j in product(range(k), range(k)):
        value = matrix[i, j]
        text = f"{value:.2f}" if math.isfinite(value) else "—"
        ax.text(j, i, text, ha="center", va="center", fontsize=8,
                color="white" if math.isfinite(value) and value > 0.6 else COLOURS["paper"])
    ax.set_xticks(range(k), [str(j) for j in range(k)])
    ax.set_yticks(range(k), [str(j) for j in range(k)])
    ax.tick_params(length=0, labelsize=8)
    return image


def _moves(row: np.ndarray, i: int) -> str:
    """P(stay), P(move up), P(move down) from state i."""
    return f"{row[i]:.2f} / {row[i + 1:].sum():.2f} / {row[:i].sum():.2f}"


# -- the table ----------------------------------------------------------------------------------------

def _table(info: KStateModelInfo) -> TableBlock:
    rows = [[name, parameter_label(name), fmt(info.values[i]), fmt(info.stderr[i]) if info.status[i] == "estimated"
             else "—", STATUS_TEXT[info.status[i]]] for i, name in enumerate(info.names)]
    return TableBlock(f"Parameters of the {info.n_states}-state model, standard errors and how well each is "
                      "determined", ["parameter (model JSON)", "meaning", "estimate", "SE", "status"], rows,
                      f"States {', '.join(state_names(info.n_states))}, from the lowest trust to the highest. SE: as "
                      "the model file gives it (Laplace, sqrt(diag((−H)⁻¹)) over the free coordinates: see its "
                      "fit.stderr_method). No SE is shown for a parameter on the boundary, not identified or not "
                      "exercised; a transition row of an input the data never exercised has no estimate (—).")
