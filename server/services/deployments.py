"""Deploying a model: the policy-evaluation study, created by one code path for the admin API and the CLI."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig
from experiment.engine import StudyRuntime
from experiment.evaluation import evaluation_config, rates_of
from experiment.iohmm import ModelError
from experiment.lifecycle import StudyStatus
from experiment.provenance import model_hash
from server.errors import Conflict, Invalid
from server.models import AuditAction, FittedModel, Study, StudyVersion
from server.services.audit import audit
from server.services.completion_codes import with_private_codes
from server.services.fits import evaluation_blocker, model_document
from server.services.studies import config_hash, create_study, set_status


def deploy_model(session: Session, model: FittedModel, *, slug: str, template_name: str, p_high: float | None,
                 title: str | None, status: str = StudyStatus.DRAFT) -> tuple[Study, bool]:
    """The evaluation study of a finished model (p_high None: the one its thresholds were solved for)."""
    document = model_document(model)  # 409 while the fit runs or when it failed
    blocked = evaluation_blocker(model)  # what the model's read model says, so the page knows before the click
    if blocked is not None:
        raise Conflict(f"cannot make an evaluation study of model {model.id}: {blocked}")
    assert model.agnostic is not None
    try:
        config = evaluation_config(document, rates_of(model.agnostic), template_name=template_name,
                                   p_high=model.p_high if p_high is None else p_high, title=title)
    except (ModelError, ValueError) as exc:
        raise Invalid(f"cannot make an evaluation study of model {model.id}: {exc}") from None
    return deploy_evaluation_study(session, config, slug, status=status)


def deploy_evaluation_study(session: Session, config: StudyConfig, slug: str, *,
                            status: str = StudyStatus.DRAFT) -> tuple[Study, bool]:
    """Create the study (True), or return the one an identical earlier request created (False).

    ``status`` "open" opens it too (an identical earlier one still a draft is opened; a closed one stays closed:
    a repeated deploy never reopens a study).

    Identical: the study's first version has the same config hash (its own completion codes aside). Any other
    study with that slug is a 409. The study's policies must solve (409 with
    the reason otherwise). Fitted models whose content hash is the config's
    model list the study among their evaluation studies.
    """
    existing = session.scalar(select(Study).where(Study.slug == slug))
    if existing is not None:
        first = session.scalars(select(StudyVersion).where(StudyVersion.study_id == existing.id)
                                .order_by(StudyVersion.version).limit(1)).one()
        # The stored config has the study's own completion codes in place of the public defaults.
        if first.config_hash == config_hash(with_private_codes(config, first.config)):
            if status == StudyStatus.OPEN and existing.status == StudyStatus.DRAFT:
                set_status(session, existing, StudyStatus.OPEN)
            return existing, False
        raise Conflict(f"a study with slug {slug!r} already exists with another configuration; choose another slug")
    try:
        StudyRuntime(config)
    except (ModelError, ValueError) as exc:
        raise Conflict(f"the evaluation study cannot run: {exc}") from None
    study = create_study(session, config, slug, status=status)
    deployed = model_hash(config.model)
    for model in session.scalars(select(FittedModel).where(FittedModel.content_hash == deployed)):
        model.evaluation_studies = [*model.evaluation_studies, slug]
    audit(session, AuditAction.MODEL_DEPLOY, study_id=study.id, model_hash=deployed, slug=slug)
    return study, True
