"""Section 3: the policies the model implies (paper §5.1).

The trust-aware policy is the belief-MDP solution (``experiment.belief_mdp``)
for the model of section 2; the figure shows Q(auto) − Q(ask) against the
belief of high trust for each complexity, so both the action and how much is
at stake are visible, with the threshold marked. The trust-agnostic baseline
comes from the intervention rates observed in the same data
(``experiment.agnostic``).

A model of three or four trust states has no threshold: its policy is the
belief MDP over the belief simplex (``experiment.trust_states_policy``), on
the grid a deployed study of the default budget uses, drawn as where on the
simplex the robot asks and said in words.
"""

from __future__ import annotations

import numpy as np

from experiment import defaults
from experiment.agnostic import intervention_rates, trust_agnostic_policy
from experiment.belief_mdp import BeliefMDPSolution, myopic_threshold, solve_belief_mdp
from experiment.config import TrustAwareSpec
from experiment.engine import simplex_resolution
from experiment.iohmm import ModelError
from experiment.report.content import FigureBlock, Missing, Paragraph, Section, TableBlock, fmt
from experiment.report.data import ExportData
from experiment.report.model import KStateModelInfo, ModelInfo
from experiment.report.plots import COLOURS, new_figure, policy_on_simplex, to_png
from experiment.task import Complexity, Experience, RobotAction, TaskParams
from experiment.trust_states_policy import KPolicySolution, ask_share, describe, mean_belief_where, solve_k_state_policy


def observed_p_high(data: ExportData) -> float:
    """Share of high-complexity trials in the model data (the design's p_high for a counts schedule)."""
    complexities = [row["complexity"] for rows in data.trials.values() for row in rows]
    return complexities.count(Complexity.HIGH.value) / len(complexities)


def policy_section(info: ModelInfo | KStateModelInfo, data: ExportData, task: TaskParams,
                   p_high: float | None) -> Section:
    section = Section("policy", "The trust-aware policy and the trust-agnostic baseline (paper §5.1)")
    chosen = observed_p_high(data) if p_high is None else p_high
    source = "the share of high-complexity trials in these data" if p_high is None else "given"
    if isinstance(info, KStateModelInfo):
        _k_state_policy(section, info, task, chosen, source)
        section.add(*_agnostic(data, task, section))
        return section
    section.add(Paragraph(f"Belief MDP solved by value iteration (γ = {defaults.DISCOUNT}, 1,001-point belief grid, "
                          f"exact Bayesian belief update) with P(C = high) = {chosen:.4f} ({source}) and the "
                          "task's success probabilities and reward table."))
    try:
        solution = solve_belief_mdp(info.params, task, p_high=chosen)
    except (ModelError, ValueError) as exc:
        hint = (" These data never exercise that input combination (too few trials, or a design whose policies never "
                "take that action); compute the policy from a model fitted to a model-estimation study (give it as "
                "the model)." if info.fit is not None else "")
        section.add(Missing(f"The policy cannot be computed from this model: {exc}.{hint}"))
    else:
        section.add(_policy_figure(solution, info, task))
        section.figures = {"p_high": chosen, "threshold": {c.value: solution.thresholds[c] for c in Complexity},
                           "action": {c.value: (a.value if a else None) for c, a in solution.constant_action.items()}}
    section.add(*_agnostic(data, task, section))
    return section


def _policy_figure(solution: BeliefMDPSolution, info: ModelInfo, task: TaskParams) -> FigureBlock:
    fig, axes = new_figure(10, 3.6, ncols=2)
    numbers = []
    for ax, c in zip(axes, Complexity, strict=True):
        q = solution.q[Experience.NEGATIVE.code, c.code]  # E_t does not change the policy (paper §5.1)
        gain = q[:, RobotAction.AUTO.code] - q[:, RobotAction.ASK.code]
        b = solution.beliefs
        ax.fill_between(b, 0, 1, where=gain > 0, transform=ax.get_xaxis_transform(), color=COLOURS["auto"],
                        label="acts autonomously (auto)")
        ax.fill_between(b, 0, 1, where=gain <= 0, transform=ax.get_xaxis_transform(), color=COLOURS["ask"],
                        label="asks for help (ask)")
        ax.plot(b, gain, color="black", linewidth=1.5, label="Q(auto) − Q(ask)")
        ax.axhline(0, color="#4a5568", linewidth=0.8)
        numbers += _mark_thresholds(ax, solution, info, task, c)
        ax.set_xlim(0, 1)
        ax.set_title(f"C = {c.value}: {_action_text(solution, c)}", fontsize=10)
        ax.set_xlabel("belief that trust is high, b = P(T = high)")
    axes[0].set_ylabel("Q(auto) − Q(ask)  (points)")
    handles = {h.get_label(): h for ax in axes for h in ax.get_legend_handles_labels()[0]}
    axes[1].legend(handles.values(), handles.keys(), loc="upper left", fontsize=8, bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(f"Trust-aware policy: action against belief (p_high = {solution.p_high:.3f}, γ = {solution.discount})")
    caption = ("Difference of the optimal expected discounted rewards of acting and of asking, in points, against "
               "the robot's belief that the human's trust is high. Green: the robot acts autonomously; red: it asks. "
               "Solid vertical line: the threshold; dashed: the one-step (myopic) threshold; dotted: the paper's ≈ "
               "0.73.")
    return FigureBlock("fig_policy", "Trust-aware policy (paper §5.1)", caption, to_png(fig), numbers)


def _mark_thresholds(ax, solution: BeliefMDPSolution, info: ModelInfo, task: TaskParams,
                     c: Complexity) -> list[tuple[str, str]]:
    threshold, numbers = solution.thresholds[c], []
    if threshold is not None:
        ax.axvline(threshold, color="black", linewidth=1.5, label="threshold")
        ax.annotate(f"threshold {threshold:.3f}", (threshold, 0.97), xycoords=("data", "axes fraction"),
                    xytext=(-6, 0), textcoords="offset points", ha="right", va="top", fontsize=8,
                    bbox=dict(boxstyle="round,pad=0.2", facecolor="white", edgecolor="none", alpha=0.8))
    myopic = myopic_threshold(info.params, task, c)
    if myopic is not None:
        ax.axvline(myopic, color="black", linewidth=1, linestyle="--", label="myopic (one-step) threshold")
    if c == Complexity.HIGH:
        ax.axvline(defaults.PAPER_TRUST_AWARE_THRESHOLD_HIGH, color=COLOURS["paper"], linewidth=1, linestyle=":",
                   label="paper's threshold ≈ 0.73")
    numbers.append((f"threshold, {c.value} complexity", _action_text(solution, c)))
    numbers.append((f"myopic threshold, {c.value}", fmt(myopic)))
    if c == Complexity.HIGH:
        numbers.append(("paper's threshold, high", f"≈ {defaults.PAPER_TRUST_AWARE_THRESHOLD_HIGH}"))
    return numbers


def _action_text(solution: BeliefMDPSolution, c: Complexity) -> str:
    if solution.thresholds[c] is not None:
        return f"ask below b = {solution.thresholds[c]:.4f}, auto above"
    action = solution.constant_action[c]
    if action is not None:
        return f"always {action.value}, whatever the belief"
    return "switches at b = " + ", ".join(f"{s:.3f}" for s in solution.switches[c]) + " (not threshold-shaped)"


def _k_state_policy(section: Section, info: KStateModelInfo, task: TaskParams, p_high: float, source: str) -> None:
    """The policy of a model of K ≥ 3 trust states: where on the belief simplex the robot asks, drawn and in words."""
    budget = TrustAwareSpec.model_fields["grid"].default  # a deployed study's budget of belief points
    resolution = simplex_resolution(info.n_states, budget)
    try:
        solution = solve_k_state_policy(info.params, task, p_high=p_high, resolution=resolution)
    except (ModelError, ValueError) as exc:
        section.add(Missing(f"The policy cannot be computed from this model: {exc}."))
        return
    section.add(Paragraph(
        f"A model of {info.n_states} trust states has no threshold: the robot's belief is a distribution over the "
        f"states, a point of the belief simplex. Belief MDP solved by value iteration on the simplex (γ = "
        f"{solution.discount}, {len(solution.beliefs):,} grid beliefs with step 1/{resolution}, the grid a deployed "
        f"study uses with the default budget of {budget:,} points; exact Bayesian belief update) with P(C = high) = "
        f"{p_high:.4f} ({source}) and the task's success probabilities and reward table."))
    section.add(Paragraph("Where the robot asks: " + "; ".join(_in_words(solution)) + "."),
                _simplex_figure(solution), _where_table(solution))
    shares, asks, acts = (ask_share(solution), mean_belief_where(solution, RobotAction.ASK),
                          mean_belief_where(solution, RobotAction.AUTO))
    section.figures = {"p_high": p_high, "n_states": info.n_states, "resolution": resolution,
                       "grid_points": len(solution.beliefs), "description": describe(solution),
                       "ask_share": {c.value: shares[c] for c in Complexity},
                       "mean_belief_where_ask": {c.value: _listed(asks[c]) for c in Complexity},
                       "mean_belief_where_auto": {c.value: _listed(acts[c]) for c in Complexity}}


def _in_words(solution: KPolicySolution) -> list[str]:
    """``describe``'s lines as clauses, with what the mean beliefs mean."""
    k = solution.n_states
    shares = ask_share(solution)
    asks, acts = mean_belief_where(solution, RobotAction.ASK), mean_belief_where(solution, RobotAction.AUTO)
    out = []
    for c in Complexity:
        if shares[c] in (0.0, 1.0):
            out.append(f"in {c.value} complexity it always {'asks' if shares[c] == 1.0 else 'acts alone'}, whatever "
                       "the belief")
            continue
        ask, act = asks[c], acts[c]
        assert ask is not None and act is not None  # both actions occur when the share is strictly between 0 and 1
        out.append(f"in {c.value} complexity it asks on {_percent(shares[c])} of the belief simplex: on average "
                   f"where it asks the belief puts {_lowest_highest(ask, k)}, where it acts alone "
                   f"{_lowest_highest(act, k)}")
    return out


def _percent(share: float) -> str:
    """A share strictly between 0 and 1 as a percentage that does not round to 0 % or 100 %."""
    whole = f"{share:.0%}"
    return f"{share:.1%}" if whole in ("0%", "100%") else whole


def _lowest_highest(belief: np.ndarray, k: int) -> str:
    return f"{belief[0]:.2f} on the lowest trust state and {belief[k - 1]:.2f} on the highest"


def _listed(vector: np.ndarray | None) -> list[float] | None:
    return None if vector is None else [float(x) for x in vector]


def _simplex_figure(solution: KPolicySolution) -> FigureBlock:
    k = solution.n_states
    asks = solution.policy == RobotAction.ASK.code
    fig = policy_on_simplex(solution.beliefs, asks, [c.value for c in Complexity])
    fig.suptitle(f"Trust-aware policy on the belief simplex of {k} trust states (p_high = {solution.p_high:.3f}, "
                 f"γ = {solution.discount})")
    middle = ("the middle state has the rest, 1 − x − y" if k == 3 else
              "the two middle states share the rest; a point's colour is the share of the grid beliefs with those "
              "two coordinates at which the robot asks")
    caption = (f"Each point is a belief of the grid: x is the belief in the highest trust state (state {k - 1}), y in "
               f"the lowest (state 0); {middle}. Red: the robot asks for help; green: it acts alone. The corner "
               "(0, 0) is certainty of a middle state, (1, 0) of the highest, (0, 1) of the lowest.")
    shares = ask_share(solution)
    numbers = [(f"share of the simplex where it asks, {c.value} complexity", f"{shares[c]:.1%}") for c in Complexity]
    return FigureBlock("fig_policy_simplex", f"Trust-aware policy on the belief simplex ({k} states)", caption,
                       to_png(fig), numbers)


def _where_table(solution: KPolicySolution) -> TableBlock:
    k = solution.n_states
    shares = ask_share(solution)
    asks, acts = mean_belief_where(solution, RobotAction.ASK), mean_belief_where(solution, RobotAction.AUTO)

    def belief(vector: np.ndarray | None) -> str:
        return "—" if vector is None else "(" + ", ".join(f"{x:.2f}" for x in vector) + ")"

    rows = [[c.value, f"{shares[c]:.1%}", belief(asks[c]), belief(acts[c])] for c in Complexity]
    return TableBlock("Where the robot asks, per complexity",
                      ["complexity", "share of the belief simplex where it asks",
                       f"mean belief (state 0 … state {k - 1}) where it asks", "mean belief where it acts alone"],
                      rows, "Shares and means over the grid beliefs (every belief of the grid counts the same).")


def _agnostic(data: ExportData, task: TaskParams, section: Section) -> list[Paragraph | Missing | TableBlock]:
    rates = intervention_rates(data.sequences())
    missing = [c.value for c in Complexity if rates.rates[c] is None]
    if missing:
        return [Missing(f"No trust-agnostic baseline: no autonomous attempts in {' or '.join(missing)} complexity, "
                        "so no intervention rate.")]
    baseline = trust_agnostic_policy(rates.rates, task)
    paper = {Complexity.LOW: (defaults.PAPER_INTERVENTION_RATE_LOW, defaults.PAPER_EXPECTED_REWARD_AUTO_LOW),
             Complexity.HIGH: (defaults.PAPER_INTERVENTION_RATE_HIGH, defaults.PAPER_EXPECTED_REWARD_AUTO_HIGH)}
    rows = [[c.value, f"{rates.interventions[c]} / {rates.auto_trials[c]}", fmt(rates.rates[c], 4),
             fmt(paper[c][0], 4), fmt(baseline.expected_reward_auto[c]), fmt(paper[c][1], 2),
             fmt(baseline.expected_reward_ask[c]), baseline.action[c].value] for c in Complexity]
    section.figures["agnostic"] = baseline.to_dict()
    return [TableBlock("Trust-agnostic baseline: observed intervention rates and expected rewards (paper §5.1)",
                       ["complexity", "interventions / autonomous attempts", "P(intervene | auto)", "paper",
                        "E[R | auto] (points)", "paper", "E[R | ask] (points)", "action"], rows,
                       "The paper's 2.79 for low complexity ignores interventions; its formula with the printed "
                       "rate gives 2.77 (SPEC §11).")]

