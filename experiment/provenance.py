"""Content hashes and provenance: which model and which policy a trial ran under (SPEC §6).

- ``content_hash(value)``: SHA-256 (hex) of the canonical JSON of a document
  (keys sorted, no whitespace, UTF-8, NaN refused), so equal documents have
  equal hashes on every machine.
- ``model_hash(ref)``: the content hash of a model document; the word
  ``"paper"`` stands for ``model_document(paper_params())``.
- ``policy_hash(block, config)``: the content hash of the block's *resolved*
  policy: its spec with the schedule's ``p_high`` filled in where the spec
  leaves it open and the model replaced by its hash, together with the
  study's task (the rewards a policy optimises). Two blocks with equal
  policy hashes choose the same actions from the same beliefs.
- ``TrialProvenance``: what every trial row records, computed once per
  compiled study (``experiment.engine.StudyRuntime``): the model hash (of the
  trust-aware block's own model, otherwise of the study's belief model), the
  policy hash, and the study seed, which with the participant id, the block
  name and the trial index determines every random draw of the trial
  (``experiment.schedule.derive_rng``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import metadata
from typing import Any

from experiment.config import BlockConfig, ModelRef, StudyConfig, TrustAwareSpec
from experiment.iohmm import model_document, paper_params
from experiment.policies import PolicyKind
from experiment.records import MODEL_COLUMNS


def canonical_json(value: Any) -> str:
    """The one JSON text of a document that its hash is taken from."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def content_hash(value: Any) -> str:
    """SHA-256 (hex) of ``canonical_json(value)``."""
    return hashlib.sha256(canonical_json(value).encode("utf-8")).hexdigest()


def model_reference_document(ref: ModelRef) -> dict[str, Any]:
    """The model document a config's model reference stands for."""
    return model_document(paper_params()) if ref == "paper" else dict(ref)


def model_hash(ref: ModelRef) -> str:
    return content_hash(model_reference_document(ref))


def code_version() -> str:
    """The installed trustlab's version (``importlib.metadata``), or ``unknown`` when not installed."""
    try:
        return metadata.version("trustlab")
    except metadata.PackageNotFoundError:
        return "unknown"


def data_hash(grouped_rows: Mapping[str, Iterable[Mapping[str, str]]]) -> str:
    """Hash of the model columns of trial rows grouped by participant, in the given order.

    ``grouped_rows`` is what ``experiment.records.read_model_trials`` returns: the
    rows a fit uses, so equal hashes mean a fit sees the same data.
    """
    return content_hash([[participant, [[row[c] for c in MODEL_COLUMNS] for row in rows]]
                         for participant, rows in grouped_rows.items()])


def block_model_ref(block: BlockConfig, config: StudyConfig) -> ModelRef:
    """The model behind a block's trials: a trust-aware block's own model, else the study's belief model."""
    return block.policy.model if isinstance(block.policy, TrustAwareSpec) else config.model


def resolved_policy(block: BlockConfig, config: StudyConfig) -> dict[str, Any]:
    """The block's policy as it runs: spec with p_high resolved and the model as its hash, plus the task."""
    spec = block.policy.model_dump(mode="json")
    if isinstance(block.policy, TrustAwareSpec):
        spec["model"] = model_hash(block.policy.model)
        spec["p_high"] = block.policy.p_high if block.policy.p_high is not None else block.schedule.p_high
    return {"policy": spec, "task": config.task.model_dump(mode="json")}


def policy_hash(block: BlockConfig, config: StudyConfig) -> str:
    return content_hash(resolved_policy(block, config))


def practice_policy_hash(config: StudyConfig) -> str:
    """Practice trials follow the configured list of robot actions."""
    return content_hash({"policy": {"kind": PolicyKind.PRACTICE, **config.practice.model_dump(mode="json")},
                         "task": config.task.model_dump(mode="json")})


@dataclass(frozen=True)
class TrialProvenance:
    model_hash: str
    policy_hash: str
    seed: int


def study_provenance(config: StudyConfig) -> tuple[dict[str, TrialProvenance], TrialProvenance]:
    """Provenance of the trials of every block (by name) and of practice trials."""
    blocks = {b.name: TrialProvenance(model_hash(block_model_ref(b, config)), policy_hash(b, config), config.seed)
              for b in config.blocks}
    return blocks, TrialProvenance(model_hash(config.model), practice_policy_hash(config), config.seed)
