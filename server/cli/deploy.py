"""``trustlab deploy``: the policy-evaluation study of a model, by the admin API's code path.

The study config comes from ``experiment.evaluation.evaluation_config`` and is
created by ``server.services.deployments.deploy_evaluation_study``, exactly
as ``POST /api/admin/models/{id}/evaluation-study`` does; here the model is a
file and the trust-agnostic baseline comes from a ``trials.csv``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from experiment.agnostic import intervention_rates
from experiment.config import StudyConfig
from experiment.evaluation import DEFAULT_TEMPLATE, evaluation_config
from experiment.iohmm import ModelError
from experiment.provenance import model_hash, study_provenance
from experiment.records import DataError, read_sequences
from experiment.task import Complexity
from experiment.trust_states_document import load_trust_model_document
from server.cli.common import DatabaseOpt, cli_settings, database_session, refuse
from server.errors import AppError


def _config(model_json: str, trials: Path, template: str, p_high: float | None, title: str | None) -> StudyConfig:
    document = load_trust_model_document(model_json)
    _, sequences = read_sequences(trials)
    rates = intervention_rates(sequences)
    if (reason := rates.missing_reason()) is not None:
        raise DataError(f"{trials}: {reason}")
    return evaluation_config(document, rates.rates, template_name=template, p_high=p_high, title=title)


def _create(config: StudyConfig, slug: str, database_url: str | None, open_study: bool) -> tuple[bool, str, str]:
    """(created, the study's status, the stored config's hash: with the study's own completion codes)."""
    from server.db.migrate import upgrade
    from server.services.deployments import deploy_evaluation_study
    from server.services.studies import current_version

    settings = cli_settings(database_url=database_url)
    upgrade(settings.database_url)
    with database_session(settings) as session:
        study, created = deploy_evaluation_study(session, config, slug, status="open" if open_study else "draft")
        return created, study.status, current_version(session, study).config_hash


def deploy(model_json: Annotated[str, typer.Argument(help="Model JSON of 2 to 4 trust states (from 'trustlab fit' or "
                                                          "the admin API's model document), or the word 'paper'.")],
           trials: Annotated[Path, typer.Option(help="trials.csv whose intervention rates make the trust-agnostic "
                                                     "baseline (practice and excluded rows are ignored).")],
           slug: Annotated[str | None, typer.Option(help="Slug of the study to create (participants join at "
                                                         "/join/SLUG).")] = None,
           template: Annotated[str, typer.Option(help="Evaluation design: policy-evaluation, demo or "
                                                      "demo-fast.")] = DEFAULT_TEMPLATE,
           p_high: Annotated[float | None, typer.Option(min=0.0, max=1.0, help="P(high complexity) the trust-aware "
                                                        "policy is solved for (default: the design's fraction).")
                             ] = None,
           title: Annotated[str | None, typer.Option(help="Study title (default: the design's and the model "
                                                          "hash).")] = None,
           out: Annotated[Path | None, typer.Option(help="Write the study config JSON here instead of creating the "
                                                         "study.")] = None,
           open_study: Annotated[bool, typer.Option("--open", help="Open the study to participants at once (default: "
                                                                   "it is created as a draft; open it on the admin "
                                                                   "page or with POST /api/admin/studies/SLUG/open).")
                                 ] = False,
           database_url: DatabaseOpt = None,
           as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False) -> None:
    """Create the policy-evaluation study of a model: trust-aware with the model, trust-agnostic from TRIALS' rates.

    Two counterbalanced blocks, the model also being the study's belief model. Running it again with the same
    arguments finds the study it created; a slug taken by another study is an error.
    """
    if (slug is None) == (out is None):
        refuse("give --slug SLUG to create the study in the database, or --out FILE to write its config (one of them)")
    created, status, stored_hash = None, None, None
    try:
        config = _config(model_json, trials, template, p_high, title)
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(config.model_dump_json(indent=2) + "\n", encoding="utf-8")
        else:
            created, status, stored_hash = _create(config, slug or "", database_url, open_study)
    except (DataError, ModelError, ValueError, OSError) as exc:
        refuse(str(exc))
    except AppError as exc:
        refuse(exc.detail)
    payload = _summary(config, slug, created, out, template) | {"status": status}
    if stored_hash is not None:  # the study's (its completion codes are its own), not the one written to --out
        payload["config_hash"] = stored_hash
    if as_json:
        typer.echo(json.dumps(payload))
    else:
        _print(payload, config)


def _summary(config: StudyConfig, slug: str | None, created: bool | None, out: Path | None,
             template: str) -> dict[str, Any]:
    from server.services.studies import config_hash

    blocks, _ = study_provenance(config)
    agnostic = next(b.policy for b in config.blocks if b.policy.kind == "trust_agnostic")
    return {"slug": slug, "created": created, "out": None if out is None else str(out), "title": config.title,
            "template": template, "config_hash": config_hash(config), "model_hash": model_hash(config.model),
            "intervention_rate": {Complexity.LOW.value: agnostic.intervention_rate_low,
                                  Complexity.HIGH.value: agnostic.intervention_rate_high},
            "policy_hash": {name: b.policy_hash for name, b in blocks.items()}}


def _print(payload: dict[str, Any], config: StudyConfig) -> None:
    slug, rates = payload["slug"], payload["intervention_rate"]
    where = (f"wrote the study config to {payload['out']}" if payload["out"] is not None else
             f"created study {slug!r}" if payload["created"] else
             f"study {slug!r} already exists with this configuration; unchanged")
    typer.echo(f"{where}: {config.title}")
    typer.echo(f"  model {payload['model_hash']} (trust-aware block and belief model); trust-agnostic rates "
               f"{rates['low']:.4f} (low), {rates['high']:.4f} (high)")
    if payload["out"] is None and payload["status"] == "draft":
        typer.echo(f"  the study is a draft: open it on the admin page, or with POST /api/admin/studies/{slug}/open "
                   f"(or run this again with --open); until then only preview sessions can run")
    elif payload["out"] is None:
        typer.echo(f"  the study is {payload['status']}; participants join at /join/{slug} of the server on this "
                   f"database ('trustlab serve')")
