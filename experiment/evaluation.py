"""Close the loop (SPEC §6): trial data → fitted model, its policy and baseline → the evaluation study.

``fit_bundle`` fits the IOHMM to the data of one study and computes from the
same data everything the next study needs: the trust-aware policy (belief-MDP
thresholds for a chosen p_high) and the trust-agnostic baseline (observed
intervention rates → expected rewards → actions). ``evaluation_config``
turns a model document and those rates into the configuration of a
policy-evaluation study: two counterbalanced blocks, trust-aware with the
model inline and trust-agnostic with the rates, the model also being the
study's belief model. The admin API and ``trustlab deploy`` both go through
these two functions.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from experiment.agnostic import baseline_from_rates, intervention_rates
from experiment.belief_mdp import BeliefMDPSolution, myopic_threshold, solve_belief_mdp
from experiment.config import BlockConfig, StudyConfig, TrustAwareSpec
from experiment.engine import simplex_resolution
from experiment.fit import FitResult, fit_iohmm
from experiment.iohmm import IOHMMParams, ModelError
from experiment.model_selection import fit_with_ratings, model_document, select_states
from experiment.provenance import content_hash
from experiment.sequences import Sequence
from experiment.task import Complexity, TaskParams
from experiment.templates import template
from experiment.trust_ratings import Ratings
from experiment.trust_states import KStateParams
from experiment.trust_states_document import trust_model_from_document
from experiment.trust_states_em import EMSettings
from experiment.trust_states_policy import ask_share, solve_k_state_policy

#: Designs an evaluation study can be made from: each has one trust-aware and one trust-agnostic block.
EVALUATION_TEMPLATES = ("policy-evaluation", "demo", "demo-fast")
DEFAULT_TEMPLATE = "policy-evaluation"


def policy_document(solution: BeliefMDPSolution, params: IOHMMParams, task: TaskParams) -> dict[str, Any]:
    """The solved policy as JSON (``trustlab policy --json``): thresholds per complexity and the myopic ones."""
    return solution.to_dict() | {"myopic_threshold": {c.value: myopic_threshold(params, task, c) for c in Complexity}}


def _block(config: StudyConfig, kind: str) -> BlockConfig:
    blocks = [b for b in config.blocks if b.policy.kind == kind]
    if len(blocks) != 1:
        raise ValueError(f"an evaluation design needs exactly one {kind} block; {config.title!r} has {len(blocks)}")
    return blocks[0]


def _design(template_name: str) -> StudyConfig:
    if template_name not in EVALUATION_TEMPLATES:
        raise ValueError(f"unknown evaluation design {template_name!r}; use one of {', '.join(EVALUATION_TEMPLATES)}")
    return template(template_name)


def design_p_high(template_name: str = DEFAULT_TEMPLATE) -> float:
    """P(C = high) of the trust-aware block of an evaluation design (0.5 in the paper's study 2)."""
    return _block(_design(template_name), "trust_aware").schedule.p_high


@dataclass(frozen=True)
class ModelBundle:
    fit: FitResult | None  # the two-state fit (None for a model of the number of states ``states_bundle`` chose)
    document: dict[str, Any]  # the model JSON (SPEC §9) with standard errors, statuses and ``fitted_on``
    content_hash: str  # ``experiment.provenance.content_hash(document)``
    policy: dict[str, Any]  # ``policy_document`` for p_high, plus ``error`` (None, or why it cannot be solved)
    agnostic: dict[str, Any]  # ``experiment.agnostic.baseline_from_rates`` of the same data

    @property
    def loglik(self) -> float:
        return float(self.document["loglik"])


def fit_bundle(sequences: list[Sequence], *, restarts: int, seed: int, p_high: float, fitted_on: dict[str, Any],
               task: TaskParams = TaskParams(), max_iter: int = 1000,
               progress: Callable[[int, int], None] | None = None) -> ModelBundle:
    """Fit (``fit_iohmm``), hash, solve the policy for ``p_high`` and compute the trust-agnostic baseline,
    all from ``sequences``."""
    result = fit_iohmm(sequences, restarts=restarts, seed=seed, max_iter=max_iter, progress=progress)
    document = result.to_document(fitted_on=fitted_on)
    return ModelBundle(result, document, content_hash(document), policy_summary(document, p_high, task),
                       baseline_from_rates(intervention_rates(sequences), task))


#: Share of a ``states_bundle``'s progress budget the comparison of the numbers of states takes (the rest: the
#: chosen model's own fit, which at K = 2 is the paper's fit and its polish).
SELECTION_PROGRESS_SHARE = 0.9


def states_bundle(sequences: list[Sequence], *, states: list[int], folds: int, restarts: int, seed: int,
                  p_high: float, fitted_on: dict[str, Any], task: TaskParams = TaskParams(), budget: int = 1000,
                  progress: Callable[[int, int], None] | None = None, ratings: Ratings | None = None) -> ModelBundle:
    """As ``fit_bundle``, for the number of trust states the data support among ``states`` (``select_states``
    with ``folds``-fold cross-validation when there are several; the model in ``"selection"`` keeps the
    comparison) or of the one number given. With ``ratings``: ``model_selection.fit_with_ratings`` (the model
    with the rating emission, compared with the fit without on held-out reliance). ``progress(done, budget)``
    covers the comparison and the final fit; it may raise to cancel."""
    if ratings is not None:
        document = fit_with_ratings(sequences, ratings, states, restarts=restarts, seed=seed, folds=folds,
                                    fitted_on=fitted_on, progress=None if progress is None else
                                    lambda _label, done, total: progress(budget * done // total, budget)).document
        return ModelBundle(None, document, content_hash(document), policy_summary(document, p_high, task),
                           baseline_from_rates(intervention_rates(sequences), task))
    selection, share = None, int(budget * SELECTION_PROGRESS_SHARE) if len(states) > 1 else 0
    if len(states) > 1:
        selection = select_states(sequences, states, folds=folds, seed=seed, settings=EMSettings(restarts=restarts),
                                  progress=None if progress is None else
                                  lambda _label, done, total: progress(share * done // total, budget))
    chosen = states[0] if selection is None else selection.chosen
    document = model_document(sequences, chosen, restarts=restarts, seed=seed, fitted_on=fitted_on,
                              selection=selection, progress=None if progress is None else
                              lambda done, total: progress(share + (budget - share) * done // total, budget))
    return ModelBundle(None, document, content_hash(document), policy_summary(document, p_high, task),
                       baseline_from_rates(intervention_rates(sequences), task))


def policy_summary(document: dict[str, Any], p_high: float, task: TaskParams = TaskParams()) -> dict[str, Any]:
    """The trust-aware policy of a model document for ``p_high``, or ``error`` saying why it cannot be solved.

    Two states: ``policy_document`` (thresholds on the belief of high trust). More: no threshold describes a
    policy on the belief simplex; the summary gives the share of the belief grid where the robot asks, solved on
    the grid a deployed study of the default ``grid`` budget uses (``engine.simplex_resolution``).
    """
    model = trust_model_from_document(document)
    try:
        if isinstance(model, IOHMMParams):
            return policy_document(solve_belief_mdp(model, task, p_high=p_high), model, task) | {"error": None}
        return _k_state_summary(model, p_high, task)
    except ModelError as exc:  # e.g. a transition the policy needs was never exercised by the data
        return {"p_high": p_high, "error": str(exc)}


def _k_state_summary(model: KStateParams, p_high: float, task: TaskParams) -> dict[str, Any]:
    grid = TrustAwareSpec.model_fields["grid"].default  # a deployed study's budget of belief points
    solution = solve_k_state_policy(model, task, p_high=p_high, resolution=simplex_resolution(model.n_states, grid))
    return {"p_high": p_high, "n_states": model.n_states, "grid": len(solution.counts),
            "discount": solution.discount, "belief_update": solution.belief_update,
            "ask_share": {c.value: share for c, share in ask_share(solution).items()}, "error": None}


def evaluation_config(document: dict[str, Any], rates: Mapping[Complexity, float | None], *,
                      template_name: str = DEFAULT_TEMPLATE, p_high: float | None = None,
                      title: str | None = None) -> StudyConfig:
    """A policy-evaluation study deploying ``document`` (a model of 2 to 4 trust states:
    ``experiment.trust_states_document``) against the baseline of intervention ``rates``.

    The design's trust-aware block gets the model inline (``p_high`` None: the
    block's schedule fraction) and its trust-agnostic block the rates; the model
    is also the study's belief model, so every trial's belief comes from it.
    Raises ValueError (unknown design, missing rate) or ModelError (bad document).
    """
    base = _design(template_name)
    aware, agnostic = _block(base, "trust_aware"), _block(base, "trust_agnostic")
    missing = [c.value for c in Complexity if rates.get(c) is None]
    if missing:
        raise ValueError(f"the trust-agnostic baseline needs an intervention rate for {' and '.join(missing)} "
                         "complexity")
    short = content_hash(document)[:12]
    data = base.model_dump(mode="json")
    data["title"] = title or f"{base.title}: model {short}"
    data["description"] = (f"Trust-aware policy of model {short} against the trust-agnostic baseline from intervention "
                           f"rates {rates[Complexity.LOW]:.4f} (low) and {rates[Complexity.HIGH]:.4f} (high); "
                           f"block order counterbalanced.")
    data["model"] = document
    for block in data["blocks"]:
        if block["name"] == aware.name:
            block["policy"] |= {"model": document, "p_high": p_high}
        elif block["name"] == agnostic.name:
            block["policy"] = {"kind": "trust_agnostic", "intervention_rate_low": rates[Complexity.LOW],
                               "intervention_rate_high": rates[Complexity.HIGH], "actions": None}
    return StudyConfig.model_validate(data)


def rates_of(agnostic: Mapping[str, Any]) -> dict[Complexity, float | None]:
    """The intervention rates of a stored baseline (``baseline_from_rates``)."""
    return {c: agnostic["rates"][c.value]["rate"] for c in Complexity}
