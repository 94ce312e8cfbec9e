"""Section 2: the fitted trust model (paper §4.1–4.3: Figs. 4–6, Table 2).

The model is either fitted here (``experiment.fit``, non-practice trials of
non-excluded participants) or read from a model JSON. Every parameter is shown
with its estimate, its Laplace standard error where the fit gives one, and its
status: a parameter on the boundary (0 or 1), not identified by the data, or
never exercised by them has no standard error, and none is shown.

A model of three or four trust states (a ``trustlab-iohmm-k`` document, issue 40) is read into a
``KStateModelInfo``; its section is ``experiment.report.model_states``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from experiment import defaults
from experiment.fit import FitResult, fit_iohmm, log_likelihood
from experiment.iohmm import (
    PARAMETER_NAMES,
    IOHMMParams,
    ModelError,
    flatten,
    model_document,
    paper_params,
    params_from_document,
)
from experiment.report.content import Caution, FigureBlock, Paragraph, Section, TableBlock, fmt
from experiment.report.data import ExportData
from experiment.report.plots import Values, new_figure, probability_bars, to_png
from experiment.task import Complexity, Experience, RobotAction, Trust
from experiment.trust_states import KStateParams, log_likelihood_k
from experiment.trust_states_document import K_FORMAT, by_name, parameter_names, trust_model_from_document

#: Up to this many model trials a fit is "paper-sized": with the paper's 33 × 71 = 2,343 trials EM
#: lands in different modes and the low-trust parameters are weakly identified (SPEC §11), while
#: 400 × 100 simulated trials recover the emissions within 0.08 (issue 2 notes).
SMALL_DATA_TRIALS = 10_000
#: Caution when at least this share of the exercised parameters has no standard error.
MANY_WITHOUT_SE = 0.25
#: Restarts whose log-likelihood is within this of the best count as having found the best mode.
SAME_MODE = 0.01
STATUS_TEXT = {"estimated": "estimated", "boundary": "on the boundary (0 or 1)",
               "unidentified": "not identified by the data", "not_exercised": "not exercised by the data",
               "given": "as given (no status in the model file)"}
SHORT_STATUS = {"boundary": "boundary", "unidentified": "unidentified", "not_exercised": "not exercised",
                "given": ""}


@dataclass(frozen=True)
class ModelInfo:
    params: IOHMMParams
    stderr: np.ndarray  # (21,) NaN where there is none
    status: list[str]  # (21,) fit status, or "given" for a model file without statuses
    loglik: float  # of these data under the model
    source: str  # one sentence: where the model comes from
    fit: FitResult | None  # when fitted here
    document: dict[str, Any]
    loglik_problem: str = ""  # why the log-likelihood could not be computed (a given model lacking parameters)


@dataclass(frozen=True)
class KStateModelInfo:
    """A model of three or four trust states read from its document (reports never fit one: ``trustlab fit
    --states`` does). Arrays follow ``names`` (``trust_states_document.parameter_names``)."""

    params: KStateParams
    names: list[str]
    values: np.ndarray  # NaN for a transition row the data never exercised
    stderr: np.ndarray  # NaN where there is none
    status: list[str]  # the document's status, or "given" for a document without statuses
    loglik: float
    source: str
    document: dict[str, Any]
    loglik_problem: str = ""

    @property
    def n_states(self) -> int:
        return self.params.n_states


def obtain_model(data: ExportData, model: str | Path | None, restarts: int, seed: int,
                 progress: Callable[[int, int], None] | None) -> ModelInfo | KStateModelInfo:
    """Fit the IOHMM to the export's model data, or read ``model`` (a model JSON file or ``"paper"``; a model of
    three or four trust states gives a ``KStateModelInfo``)."""
    sequences = data.sequences()
    if model is None:
        result = fit_iohmm(sequences, restarts=restarts, seed=seed, progress=progress)
        # The directory by name only: reports are shared, and a full path describes the machine that made them.
        document = result.to_document(fitted_on={"source": f"{data.source.name}/trials.csv",
                                                 "participants": list(data.trials)})
        source = (f"Fitted here by Baum–Welch with {restarts} random restarts (seed {seed}) to {result.n_trials} "
                  f"non-practice trials of {result.n_sequences} non-excluded participants.")
        return ModelInfo(result.params, result.stderr, list(result.status), result.loglik, source, result, document)
    document = model_document(paper_params()) if str(model) == "paper" else _read_document(Path(model))
    source = ("The paper's published estimates (§4.1–4.2)." if str(model) == "paper"
              else f"Read from {model} (not fitted to these data).")
    if isinstance(document, dict) and document.get("format") == K_FORMAT:
        return _k_state_info(document, data, source)
    params = params_from_document(document)
    stderr, status = _document_uncertainty(document)
    try:
        return ModelInfo(params, stderr, status, log_likelihood(params, sequences), source, None, document)
    except ModelError as exc:
        return ModelInfo(params, stderr, status, math.nan, source, None, document, loglik_problem=str(exc))


def _read_document(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ModelError(f"model file not found: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelError(f"model file {path} is not valid JSON: {exc}") from None


def _document_uncertainty(document: dict[str, Any]) -> tuple[np.ndarray, list[str]]:
    """Standard errors and statuses stored in a model JSON; NaN / "given" where it has none."""
    try:
        stderr = np.array([math.nan if v is None else float(v) for v in flatten(document["stderr"]).values()])
        status = [str(s) for s in flatten(document["status"]).values()]
    except (KeyError, TypeError, ValueError, ModelError):
        return np.full(len(PARAMETER_NAMES), math.nan), ["given"] * len(PARAMETER_NAMES)
    return np.where(np.array(status) == "estimated", stderr, math.nan), status


def _k_state_info(document: dict[str, Any], data: ExportData, source: str) -> KStateModelInfo:
    model = trust_model_from_document(document)  # ModelError says what is wrong with the document
    assert isinstance(model, KStateParams)  # a K_FORMAT document is a model of 3 or 4 states
    names = parameter_names(model.n_states)
    values = np.array([float(v) for v in by_name(model.initial, model.transition, model.p_rely).values()])
    stored_stderr, stored_status = (_dotted(document.get(key), names) for key in ("stderr", "status"))
    if all(isinstance(stored_status[n], str) and stored_status[n] in STATUS_TEXT for n in names):
        status = [str(stored_status[n]) for n in names]
        stderr = np.array([float(stored_stderr[n]) if status[i] == "estimated" and _is_number(stored_stderr[n])
                           else math.nan for i, n in enumerate(names)])
    else:  # a hand-written document: no statuses, no standard errors
        status, stderr = ["given"] * len(names), np.full(len(names), math.nan)
    try:
        loglik, problem = log_likelihood_k(model, data.sequences()), ""
    except ModelError as exc:
        loglik, problem = math.nan, str(exc)
    return KStateModelInfo(model, names, values, stderr, status, loglik, source, document, problem)


def _dotted(nested: Any, names: list[str]) -> dict[str, Any]:
    """The leaves of a nested object at the dotted ``names`` (None where one is missing)."""
    out: dict[str, Any] = {}
    for name in names:
        node = nested
        for key in name.split("."):
            node = node.get(key) if isinstance(node, dict) else None
        out[name] = node
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


# -- names, paper values -------------------------------------------------------------------------

def parameter_key(name: str) -> tuple[str, ...]:
    """("initial",) | (c, a, e, t) for a transition | (c, t) for an emission, from a PARAMETER_NAMES entry."""
    parts = name.split(".")
    if parts[0] == "transitions":
        return (parts[1], parts[2], parts[3], parts[4].removeprefix("from_"))
    if parts[0] == "emissions":
        return (parts[1], parts[3].removeprefix("p_rely_"))
    return ("initial",)


def parameter_label(name: str) -> str:
    key = parameter_key(name)
    if len(key) == 4:
        c, a, e, t = key
        return f"P(T′ = high | T = {t}, E′ = {'E+' if e == 'positive' else 'E−'}, C = {c}, a = {a})"
    if len(key) == 2:
        return f"P(o = rely | T = {key[1]}, C = {key[0]}, a = auto)"
    return "P(T₁ = high)"


def paper_value(name: str) -> tuple[float, float]:
    """(estimate, standard error) printed in the paper, NaN where it prints none."""
    key = parameter_key(name)
    if key == ("initial",):
        return defaults.PAPER_INITIAL_HIGH, math.nan
    table = defaults.PAPER_P_HIGH_NEXT if len(key) == 4 else defaults.PAPER_P_RELY
    return table.get(key, math.nan), defaults.PAPER_TABLE2_STDERR.get(key, math.nan)


def _index(name: str) -> int:
    return PARAMETER_NAMES.index(name)


# -- the section -----------------------------------------------------------------------------------

def model_section(info: ModelInfo, data: ExportData) -> Section:
    section = Section("model", "The trust model (paper §4.1–4.3, Figs. 4–6, Table 2)")
    section.add(Paragraph(info.source + f" Log-likelihood of these data under the model: {fmt(info.loglik, 3)} "
                          f"({data.n_trials} trials of {len(data.trials)} participants)."))
    section.add(*_cautions(info, data))
    section.add(_emission_figure(info), *(_transition_figure(info, c) for c in Complexity), _table(info))
    counts = {s: info.status.count(s) for s in sorted(set(info.status))}
    section.figures = {"loglik": info.loglik, "n_trials": data.n_trials, "n_participants": len(data.trials),
                       "status_counts": counts, "params": info.params.to_dict(),
                       "fitted_here": info.fit is not None}
    if info.fit is not None:
        section.figures |= {"restarts": info.fit.restarts, "seed": info.fit.seed, "converged": info.fit.converged}
    return section


def fit_cautions(loglik_problem: str | None, status: list[str]) -> list[Caution | Paragraph]:
    """What any model's section warns of: a model that does not fit the data, and many weakly determined
    parameters (by their statuses)."""
    out: list[Caution | Paragraph] = []
    if loglik_problem:
        out.append(Caution(f"This model does not fit these data: {loglik_problem}."))
    exercised = [s for s in status if s not in ("not_exercised", "given")]
    weak = [s for s in exercised if s in ("boundary", "unidentified")]
    if exercised and len(weak) >= MANY_WITHOUT_SE * len(exercised):
        out.append(Caution(f"{len(weak)} of the {len(exercised)} parameters the fit could estimate are on the boundary "
                           "(0 or 1) or not identified: their values are where the likelihood is largest, not "
                           "measurements, and they have no standard error. Read them as weakly determined."))
    return out


def _cautions(info: ModelInfo, data: ExportData) -> list[Caution | Paragraph]:
    out = fit_cautions(info.loglik_problem, list(info.status))
    if info.fit is not None and data.n_trials <= SMALL_DATA_TRIALS:
        per_participant = defaults.STUDY1_TRIALS_LOW + defaults.STUDY1_TRIALS_HIGH
        paper = defaults.STUDY1_PARTICIPANTS_KEPT * per_participant
        out.append(Caution(f"{data.n_trials} trials is paper-sized data or less (the paper fitted "
                           f"{defaults.STUDY1_PARTICIPANTS_KEPT} × {per_participant} = {paper:,}). At this size EM can "
                           "land in a different mode with a higher likelihood than the true parameters, and the "
                           "low-trust parameters are weakly identified (SPEC §11): compare the standard errors before "
                           "drawing conclusions from single parameters."))
    fit = info.fit
    if fit is not None:
        best = int(np.sum(fit.restart_logliks >= fit.restart_logliks.max() - SAME_MODE))
        out.append(Paragraph(f"{best} of {fit.restarts} restarts reached the best EM log-likelihood (within "
                             f"{SAME_MODE}); the best was then polished. "
                             f"Converged: {'yes' if fit.converged else 'no'}."))
        if not fit.converged:
            out.append(Caution("The fit did not meet the convergence test (projected gradient); the estimates "
                               "may still move with more iterations or restarts."))
    return out


def _note(info: ModelInfo, name: str) -> str:
    return SHORT_STATUS.get(info.status[_index(name)], "")


def _emission_figure(info: ModelInfo) -> FigureBlock:
    fig, axes = new_figure(10, 3.6, ncols=3, sharey=True)
    trusts = [Trust.LOW, Trust.HIGH]
    groups = [f"T = {t.value}" for t in trusts]
    probability_bars(axes[0], groups, [("rely (o+)", "rely", [0, 0]), ("intervene (o−)", "intervene", [1, 1])],
                     [math.nan, math.nan], ["structural", "structural"], [[0, 0], [1, 1]])
    axes[0].set_title("a = ask, any C\n(the human always assists)", fontsize=10)
    for ax, c in zip(axes[1:], Complexity, strict=True):
        names = [f"emissions.{c.value}.auto.p_rely_{t.value}" for t in trusts]
        rely = [info.params.to_vector()[_index(n)] for n in names]
        paper = [paper_value(n)[0] for n in names]
        series: list[tuple[str, str, Values]] = [("rely (o+)", "rely", rely),
                                                 ("intervene (o−)", "intervene", 1 - np.array(rely))]
        probability_bars(ax, groups, series,
                         [info.stderr[_index(n)] for n in names], [_note(info, n) for n in names],
                         [paper, 1 - np.array(paper)])
        ax.set_title(f"a = auto, C = {c.value}", fontsize=10)
    axes[0].set_ylabel("probability of the human action")
    for ax in axes:
        ax.set_xlabel("trust state T")
    axes[2].legend(loc="upper left", fontsize=8, bbox_to_anchor=(1.0, 1.0))
    fig.suptitle("Emission probabilities P(o | T, C, a) (paper Fig. 4); error bars ±1 SE")
    caption = ("Probability that the human relies (o+) or intervenes (o−) given the hidden trust state, the "
               "complexity and the robot's action. Bars: this model; black diamonds: the paper's estimates; "
               "error bars: ±1 Laplace standard error (clipped to [0, 1]); a note under a trust state says why it "
               "has no error bar. The values are printed above the bars.")
    numbers = [(parameter_label(n), _value_text(info, n)) for n in PARAMETER_NAMES if not n.startswith("transitions")]
    return FigureBlock("fig4_emissions", "Emission probabilities (paper Fig. 4)", caption, to_png(fig), numbers)


def _combos(info: ModelInfo, c: Complexity) -> list[tuple[RobotAction, Experience]]:
    """(a, E′) panels for complexity c: those the paper shows, plus any other the data exercise."""
    shown = []
    for a in RobotAction:
        for e in (Experience.POSITIVE, Experience.NEGATIVE):
            names = [f"transitions.{c.value}.{a.value}.{e.value}.from_{t.value}" for t in Trust]
            in_paper = any(math.isfinite(paper_value(n)[0]) for n in names)
            exercised = any(info.status[_index(n)] not in ("not_exercised", "given") for n in names)
            given = any(info.status[_index(n)] == "given" and math.isfinite(info.params.to_vector()[_index(n)])
                        for n in names)
            if in_paper or exercised or given:
                shown.append((a, e))
    return shown


def _transition_figure(info: ModelInfo, c: Complexity) -> FigureBlock:
    combos = _combos(info, c)
    fig, axes = new_figure(3.4 * len(combos), 3.6, ncols=len(combos), sharey=True)
    groups = ["from T = low", "from T = high"]
    for ax, (a, e) in zip(axes, combos, strict=True):
        names = [f"transitions.{c.value}.{a.value}.{e.value}.from_{t.value}" for t in (Trust.LOW, Trust.HIGH)]
        to_high = np.array([info.params.to_vector()[_index(n)] for n in names])
        paper = np.array([paper_value(n)[0] for n in names])
        probability_bars(ax, groups, [("to high", "high", to_high), ("to low", "low", 1 - to_high)],
                         [info.stderr[_index(n)] for n in names], [_note(info, n) for n in names], [paper, 1 - paper])
        what = "asked" if a == RobotAction.ASK else "success" if e == Experience.POSITIVE else "failure or intervention"
        ax.set_title(f"a = {a.value}, E′ = {'E+' if e == Experience.POSITIVE else 'E−'}\n({what})", fontsize=10)
        ax.set_xlabel("trust state before the trial")
    axes[0].set_ylabel("probability of the next trust state")
    axes[-1].legend(loc="upper left", fontsize=8, bbox_to_anchor=(1.0, 1.0))
    figure_no = 5 if c == Complexity.LOW else 6
    fig.suptitle(f"Trust transitions P(T′ | T, E′, C = {c.value}, a) (paper Fig. {figure_no}); error bars ±1 SE")
    caption = (f"Probability of the next trust state T′ after a {c.value}-complexity trial, by the robot's action a "
               "and the experience E′ the trial gave. Bars: this model; black diamonds: the paper; error bars ±1 SE "
               "(clipped to [0, 1]); a note under a trust state says why it has no error bar. The values are printed "
               "above the bars.")
    numbers = [(parameter_label(n), _value_text(info, n)) for n in PARAMETER_NAMES
               if n.startswith(f"transitions.{c.value}.") and info.status[_index(n)] != "not_exercised"]
    return FigureBlock(f"fig{figure_no}_transitions_{c.value}", f"Trust transitions, {c.value} complexity "
                       f"(paper Fig. {figure_no})", caption, to_png(fig), numbers)


def _value_text(info: ModelInfo, name: str) -> str:
    i = _index(name)
    value, se, status = info.params.to_vector()[i], info.stderr[i], info.status[i]
    if not math.isfinite(value):
        return "—"
    return f"{value:.3f} ± {se:.3f}" if math.isfinite(se) else f"{value:.3f} ({STATUS_TEXT[status]})"


def _table(info: ModelInfo) -> TableBlock:
    rows = []
    for i, name in enumerate(PARAMETER_NAMES):
        value, se, status = info.params.to_vector()[i], info.stderr[i], info.status[i]
        if status == "not_exercised" and not math.isfinite(paper_value(name)[0]):
            continue  # an input combination the task cannot produce: nothing to show
        paper, paper_se = paper_value(name)
        rows.append([parameter_label(name), fmt(value), fmt(se) if status == "estimated" else "—",
                     STATUS_TEXT[status], fmt(paper, 2), fmt(paper_se, 2)])
    return TableBlock("Parameters, standard errors and how well each is determined (paper Table 2)",
                      ["parameter", "estimate", "SE", "status", "paper", "paper SE"], rows,
                      "SE = sqrt(diag((−H)⁻¹)) over the interior parameters (the paper prints sqrt(diag(−H)), "
                      "a slip: SPEC §11). No SE is shown for a parameter on the boundary, not identified or not "
                      "exercised. The paper's Table 2 labels its emission rows a−; they are the a+ (auto) "
                      "emissions. Input combinations the task cannot produce are left out.")
