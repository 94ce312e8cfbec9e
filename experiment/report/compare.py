"""Section 5: the policies compared (paper §5.2–5.3, Fig. 11–12, Table 3).

Cumulative reward per participant and block, compared between blocks with
the two-sample t-test the paper used (MATLAB ``ttest2``) and, since every
participant did every block, the paired t-test too. Schaefer TPS-HRI scores
before the experiment and after each block, compared the same way; the
paper's p-values are what ``ttest2`` gives (see ``experiment.defaults``).
Designs with one block, or without the Schaefer questionnaire, get a "not
applicable" note instead.
"""

from __future__ import annotations

from collections import defaultdict
from itertools import combinations

import numpy as np

from experiment import defaults
from experiment.analysis import TTestResult, paired_ttest, ttest2
from experiment.instruments import SCHAEFER_14
from experiment.questionnaires import AnswerError, score
from experiment.report.content import FigureBlock, Missing, Paragraph, Section, TableBlock, fmt, fmt_p
from experiment.report.data import ExportData, Row, number
from experiment.report.plots import PAPER_MARKER, named_boxes, new_figure, to_png

PRE = "before"
#: Fewest participants per block (or per Schaefer condition) for a comparison: a t-test needs variation.
MIN_PER_GROUP = 2
_PAPER_MEDIAN_SCORE = {"trust_agnostic": defaults.PAPER_MEDIAN_SCORE_AGNOSTIC,
                       "trust_aware": defaults.PAPER_MEDIAN_SCORE_AWARE}
#: (mean, median, variance) of the scores per condition, Table 3's aggregate row.
_PAPER_SCHAEFER = {
    PRE: (defaults.PAPER_SCHAEFER_MEAN_PRE, defaults.PAPER_SCHAEFER_MEDIAN_PRE, defaults.PAPER_SCHAEFER_VARIANCE_PRE),
    "trust_agnostic": (defaults.PAPER_SCHAEFER_MEAN_AGNOSTIC, defaults.PAPER_SCHAEFER_MEDIAN_AGNOSTIC,
                       defaults.PAPER_SCHAEFER_VARIANCE_AGNOSTIC),
    "trust_aware": (defaults.PAPER_SCHAEFER_MEAN_AWARE, defaults.PAPER_SCHAEFER_MEDIAN_AWARE,
                    defaults.PAPER_SCHAEFER_VARIANCE_AWARE),
}
_PAPER_SCHAEFER_P = {frozenset(("trust_aware", "trust_agnostic")): defaults.PAPER_SCHAEFER_P_AWARE_VS_AGNOSTIC,
                     frozenset((PRE, "trust_agnostic")): defaults.PAPER_SCHAEFER_P_PRE_VS_AGNOSTIC,
                     frozenset((PRE, "trust_aware")): defaults.PAPER_SCHAEFER_P_PRE_VS_AWARE}


def block_policies(data: ExportData) -> dict[str, str]:
    """Block name -> policy kind, by block name (independent of who happened to come first)."""
    out: dict[str, str] = {}
    for rows in data.trials.values():
        for row in rows:
            out.setdefault(_block_name(row), row.get("policy", ""))
    return dict(sorted(out.items()))


def _block_name(row: Row) -> str:
    return row.get("block_name", "") or f"block {row['block']}"


def cumulative_rewards(data: ExportData) -> dict[str, dict[str, float]]:
    """{block name: {participant: cumulative reward}} over complete blocks only.

    A block counts as complete when the participant has as many trials in it as the most
    complete participant (an abandoned session's partial block would bias the comparison).
    """
    totals: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for pid, rows in data.trials.items():
        for row in rows:
            reward = number(row, "reward")
            if reward is not None:
                totals[_block_name(row)][pid].append(reward)
    out = {}
    for block, per in totals.items():
        full = max(len(v) for v in per.values())
        out[block] = {pid: float(sum(v)) for pid, v in per.items() if len(v) == full}
    return out


def compare_section(data: ExportData) -> Section:
    section = Section("comparison",
                      "The policies compared: cumulative reward and Schaefer trust scores (paper §5.2–5.3)")
    policies = block_policies(data)
    section.add(*_reward_part(data, policies, section))
    section.add(*_schaefer_part(data, policies, section))
    return section


def _label(block: str, policies: dict[str, str]) -> str:
    policy = policies.get(block, "")
    return f"{block} ({policy})" if policy and policy != block else block


def _tests(samples: dict[str, dict[str, float]], a: str, b: str) -> tuple[TTestResult | str, TTestResult | str]:
    """ttest2 of the two samples and the paired t-test over participants in both (or why it is undefined)."""
    x, y = samples[a], samples[b]
    both = sorted(set(x) & set(y))
    results: list[TTestResult | str] = []
    for run in (lambda: ttest2(list(x.values()), list(y.values())),
                lambda: paired_ttest([x[p] for p in both], [y[p] for p in both])):
        try:
            results.append(run())
        except ValueError as exc:
            results.append(f"undefined ({exc})")
    return results[0], results[1]


def _test_text(result: TTestResult | str) -> str:
    if isinstance(result, str):
        return result
    return (f"t({result.df:.0f}) = {result.t:.3f}, p = {fmt_p(result.p)}, "
            f"95 % CI of the difference [{result.ci_low:.2f}, {result.ci_high:.2f}]")


def _test_figures(result: TTestResult | str) -> dict[str, float] | None:
    return None if isinstance(result, str) else {"t": result.t, "df": result.df, "p": result.p,
                                                   "mean_x": result.mean_x, "mean_y": result.mean_y}


def _reward_part(data: ExportData, policies: dict[str, str], section: Section) -> list:
    if "reward" not in data.trial_columns:
        return [Missing("trials.csv has no reward column: no cumulative rewards.")]
    rewards = cumulative_rewards(data)
    blocks = [b for b in policies if rewards.get(b)]
    stats = {b: np.array(list(rewards[b].values())) for b in blocks}
    rows = [[_label(b, policies), str(s.size), fmt(s.mean(), 2), fmt(float(np.median(s)), 1),
             fmt(s.std(ddof=1) if s.size > 1 else None, 2), str(_PAPER_MEDIAN_SCORE.get(policies.get(b, ""), "—"))]
            for b, s in stats.items()]
    out: list = [TableBlock("Cumulative reward per block (complete blocks only)",
                            ["block (policy)", "participants", "mean (points)", "median (points)", "SD (points)",
                             "paper median"], rows)]
    section.figures["rewards"] = {b: {"n": int(s.size), "mean": float(s.mean()), "median": float(np.median(s))}
                                  for b, s in stats.items()}
    if len(blocks) < 2:
        return out + [Missing(f"Policy comparison not applicable for this design: it has one block "
                              f"({', '.join(_label(b, policies) for b in blocks)}), so there is no second policy "
                              "to compare with.")]
    if min(s.size for s in stats.values()) < MIN_PER_GROUP:
        return out + [Missing(f"Too few complete blocks to compare the policies: every block needs at least "
                              f"{MIN_PER_GROUP} participants who completed it.")]
    return out + [_reward_figure(rewards, blocks, policies, section)]


def _reward_figure(rewards: dict[str, dict[str, float]], blocks: list[str], policies: dict[str, str],
                   section: Section) -> FigureBlock:
    fig, axes = new_figure(max(5.0, 2.2 * len(blocks) + 1.5), 4.2)
    ax = axes[0]
    named_boxes(ax, [_label(b, policies) for b in blocks], [np.array(list(rewards[b].values())) for b in blocks],
                ["high" if policies.get(b) == "trust_aware" else "low" for b in blocks])
    paper = [_PAPER_MEDIAN_SCORE.get(policies.get(b, ""), np.nan) for b in blocks]
    if np.isfinite(paper).any():
        ax.plot(np.arange(1, len(blocks) + 1), paper, **PAPER_MARKER, label="paper's median")
        ax.legend(loc="best", fontsize=8)
    ax.set(ylabel="cumulative reward in the block (points)", xlabel="block (policy)",
           title="Cumulative reward per policy (paper Fig. 11)")
    numbers, tests = [], {}
    for a, b in combinations(blocks, 2):
        two, paired = _tests(rewards, a, b)
        numbers += [(f"ttest2 {a} vs {b}", _test_text(two)), (f"paired t {a} vs {b}", _test_text(paired))]
        if {policies.get(a), policies.get(b)} == {"trust_aware", "trust_agnostic"}:
            numbers.append(("paper's ttest2 p (trust-aware vs trust-agnostic)", f"{defaults.PAPER_SCORE_TTEST_P}"))
        tests[f"{a} vs {b}"] = {"ttest2": _test_figures(two), "paired": _test_figures(paired)}
    section.figures["reward_tests"] = tests
    caption = ("Each participant's total reward in each block (complete blocks only; box: quartiles, whiskers: "
               "1.5 IQR, points: participants). Tests: two-sample t-test with pooled variance (MATLAB ttest2, as "
               "the paper), and the paired t-test over participants who completed both blocks. Black diamonds: the "
               "paper's medians.")
    return FigureBlock("fig_cumulative_reward", "Cumulative reward per policy (paper §5.2)", caption, to_png(fig),
                       numbers)


# -- Schaefer TPS-HRI ---------------------------------------------------------------------------------

def schaefer_answers(data: ExportData) -> dict[str, dict[str, dict[str, float]]]:
    """{condition: {participant: {item: raw value}}}; condition: "before", or the block it was asked after."""
    out: dict[str, dict[str, dict[str, float]]] = defaultdict(lambda: defaultdict(dict))
    for row in data.included_surveys():
        if row["questionnaire"] == SCHAEFER_14.id and row["value"] != "":  # a lab's own text item has no value
            condition = PRE if row["context"] == PRE else row["block_name"] or row["context"]
            out[condition][row["participant_id"]][row["item"]] = float(row["value"])
    return out


def schaefer_scores(answers: dict[str, dict[str, dict[str, float]]]) -> tuple[dict[str, dict[str, float]], int]:
    """{condition: {participant: score}} (mean of the reverse-coded items, %), and how many were incomplete."""
    scores: dict[str, dict[str, float]] = {}
    incomplete = 0
    for condition, per in answers.items():
        scores[condition] = {}
        for pid, items in per.items():
            try:
                scores[condition][pid] = score(SCHAEFER_14, items)
            except AnswerError:
                incomplete += 1
    return scores, incomplete


def _schaefer_part(data: ExportData, policies: dict[str, str], section: Section) -> list:
    if data.surveys is None:
        return [Missing("No surveys.csv in the export: no Schaefer trust scores.")]
    answers = schaefer_answers(data)
    if not answers:
        return [Missing("Schaefer trust scores not applicable for this design: surveys.csv has no answers to the "
                        f"{SCHAEFER_14.title} ({SCHAEFER_14.id}).")]
    scores, incomplete = schaefer_scores(answers)
    conditions = sorted((c for c in scores if scores[c]), key=lambda c: (c != PRE, c))  # before, then the blocks
    reversed_items = ", ".join(f"'{item.text}'" for item in SCHAEFER_14.items if item.reverse_coded)
    out: list = [Paragraph(f"Schaefer score = mean of the {len(SCHAEFER_14.items)} items after reverse-coding "
                           f"{reversed_items} (0–100 %). Incomplete questionnaires left out: {incomplete}.")]
    if not conditions:
        return out + [Missing("No complete Schaefer questionnaire: no scores.")]
    if min(len(scores[c]) for c in conditions) < MIN_PER_GROUP:
        out.append(Missing(f"Too few Schaefer scores to compare: every condition needs at least {MIN_PER_GROUP}."))
    else:
        out.append(_schaefer_figure(scores, conditions, policies, section))
    out.append(_table3(answers, scores, conditions, policies))
    return out


def _condition_label(condition: str, policies: dict[str, str]) -> str:
    return "pre-experiment" if condition == PRE else f"after {_label(condition, policies)}"


def _paper_key(condition: str, policies: dict[str, str]) -> str:
    return PRE if condition == PRE else policies.get(condition, "")


def _schaefer_figure(scores: dict[str, dict[str, float]], conditions: list[str], policies: dict[str, str],
                     section: Section) -> FigureBlock:
    fig, axes = new_figure(max(5.0, 2.3 * len(conditions) + 1.5), 4.2)
    ax = axes[0]
    colours = ["rely" if c == PRE else "high" if policies.get(c) == "trust_aware" else "low" for c in conditions]
    named_boxes(ax, [_condition_label(c, policies) for c in conditions],
                [np.array(list(scores[c].values())) for c in conditions], colours)
    paper = [_PAPER_SCHAEFER.get(_paper_key(c, policies), (np.nan,))[0] for c in conditions]
    if np.isfinite(paper).any():
        ax.plot(np.arange(1, len(conditions) + 1), paper, **PAPER_MARKER, label="paper's mean")
        ax.legend(loc="best", fontsize=8)
    ax.set(ylabel="Schaefer trust score (%)", ylim=(0, 100), title="Schaefer TPS-HRI scores (paper Fig. 12)")
    numbers, tests = [], {}
    for a, b in combinations(conditions, 2):
        two, paired = _tests(scores, a, b)
        pair = f"{_condition_label(a, policies)} vs {_condition_label(b, policies)}"
        numbers += [(f"ttest2 {pair}", _test_text(two)), (f"paired t {pair}", _test_text(paired))]
        paper_p = _PAPER_SCHAEFER_P.get(frozenset((_paper_key(a, policies), _paper_key(b, policies))))
        if paper_p is not None:
            numbers.append((f"paper's p, {pair}", f"{paper_p}"))
        tests[f"{a} vs {b}"] = {"ttest2": _test_figures(two), "paired": _test_figures(paired)}
    section.figures["schaefer"] = {c: {"n": len(scores[c]), "mean": float(np.mean(list(scores[c].values())))}
                                   for c in conditions} | {"tests": tests}
    when = "before the experiment and after each block" if PRE in conditions else "after each block"
    caption = (f"Trust scores {when} (box: quartiles, whiskers: 1.5 IQR, points: participants). Tests: ttest2 (as "
               "the paper) and paired t-tests over participants with both scores. Black diamonds: the paper's means.")
    return FigureBlock("fig_schaefer", "Schaefer trust scores (paper §5.3)", caption, to_png(fig), numbers)


def _stats(values: list[float]) -> list[str]:
    """Mean, median and variance (n − 1) as table cells."""
    v = np.array(values)
    if not v.size:
        return ["—"] * 3
    return [fmt(v.mean(), 2), fmt(float(np.median(v)), 2), fmt(v.var(ddof=1) if v.size > 1 else None, 2)]


def _table3(answers: dict[str, dict[str, dict[str, float]]], scores: dict[str, dict[str, float]],
            conditions: list[str], policies: dict[str, str]) -> TableBlock:
    header = ["item"] + ["mean", "median", "variance"] * len(conditions)
    groups = [("", 1)] + [(_condition_label(c, policies), 3) for c in conditions]
    rows = []
    for number_, item in enumerate(SCHAEFER_14.items, start=1):
        cells = [f"{number_}. {item.text}{' (reverse-coded)' if item.reverse_coded else ''}"]
        for c in conditions:
            cells += _stats([a[item.id] for a in answers[c].values() if item.id in a])
        rows.append(cells)
    rows.append(["score (aggregate)"] + [s for c in conditions for s in _stats(list(scores[c].values()))])
    paper = [_PAPER_SCHAEFER.get(_paper_key(c, policies)) for c in conditions]
    if any(paper):
        rows.append(["paper: aggregate"] + [f"{v:.2f}" if p else "—" for p in paper for v in (p or (0, 0, 0))])
    return TableBlock("Schaefer items per condition: raw answers (%) and the score (paper Table 3)", header, rows,
                      "Items as answered (reverse-coded items not reversed), as in the paper's table; the score row "
                      "uses reverse-coded values. Variances with n − 1. The paper numbers the items in another "
                      "order (its reverse-coded items are 3, 7 and 8), so only its aggregate row is compared.",
                      header_groups=groups)
