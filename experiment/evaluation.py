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
from experiment.config import BlockConfig, StudyConfig
from experiment.fit import FitResult, fit_iohmm
from experiment.iohmm import IOHMMParams, ModelError
from experiment.provenance import content_hash
from experiment.sequences import Sequence
from experiment.task import Complexity, TaskParams
from experiment.templates import template

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
    fit: FitResult
    document: dict[str, Any]  # the model JSON (SPEC §9) with standard errors, statuses and ``fitted_on``
    content_hash: str  # ``experiment.provenance.content_hash(document)``
    policy: dict[str, Any]  # ``policy_document`` for p_high, plus ``error`` (None, or why it cannot be solved)
    agnostic: dict[str, Any]  # ``experiment.agnostic.baseline_from_rates`` of the same data


def fit_bundle(sequences: list[Sequence], *, restarts: int, seed: int, p_high: float, fitted_on: dict[str, Any],
               task: TaskParams = TaskParams(), max_iter: int = 1000,
               progress: Callable[[int, int], None] | None = None) -> ModelBundle:
    """Fit (``fit_iohmm``), hash, solve the policy for ``p_high`` and compute the trust-agnostic baseline,
    all from ``sequences``."""
    result = fit_iohmm(sequences, restarts=restarts, seed=seed, max_iter=max_iter, progress=progress)
    document = result.to_document(fitted_on=fitted_on)
    try:
        solution = solve_belief_mdp(result.params, task, p_high=p_high)
        policy = policy_document(solution, result.params, task) | {"error": None}
    except ModelError as exc:  # e.g. a transition the policy needs was never exercised by the data
        policy = {"p_high": p_high, "error": str(exc)}
    return ModelBundle(result, document, content_hash(document), policy,
                       baseline_from_rates(intervention_rates(sequences), task))


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
