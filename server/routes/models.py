"""Admin API: fit a study's data, read fitted models, deploy one in a policy-evaluation study."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, BackgroundTasks, Depends, FastAPI, Path, Request, Response

from experiment.evaluation import design_p_high
from server.app_services import services_of
from server.bodies import StrictJsonRoute
from server.deps import AdminDep, SessionDep, SettingsDep, StudyDep
from server.routes.admin import study_detail
from server.schemas import EvaluationStudyCreate, FitCreate, ModelRead, StudyDetailRead, error_responses
from server.services import deployments, fits


@contextlib.asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Fits a stopped server left running have failed; on shutdown, the running fit is interrupted."""
    services = services_of(app)
    if services.settings.primary:  # fits run on the primary only (server.workers)
        fits.fail_interrupted_fits(services.database)
    try:
        yield
    finally:
        # In a thread: the fit may be waiting for the database turn, which the loop grants.
        await asyncio.to_thread(services.fits.stop)


router = APIRouter(route_class=StrictJsonRoute, prefix="/api/admin", tags=["models"], dependencies=[AdminDep],
                   lifespan=_lifespan)


def _worker(request: Request) -> fits.FitWorker:
    return services_of(request.app).fits


WorkerDep = Annotated[fits.FitWorker, Depends(_worker)]
ModelId = Annotated[int, Path(ge=1, le=2**31 - 1, description="Id of a fitted model")]
_EXISTING: dict[int | str, dict[str, Any]] = {200: {"model": ModelRead, "description": (
    "The same fit (same data, restarts, seed, p_high, states and folds) was requested before: the running or "
    "finished model.")}}


@router.post("/studies/{slug}/fits", response_model=ModelRead, status_code=202,
             responses=_EXISTING | error_responses(404, 409))
def request_fit(study: StudyDep, body: FitCreate, session: SessionDep, worker: WorkerDep, response: Response,
                background: BackgroundTasks) -> ModelRead:
    """Fit the IOHMM to the study's data (included participants, non-practice trials) in the background.

    With ``states``, the model has the number of trust states the data support among them (cross-validation by
    participant in ``folds`` folds; the comparison in the model's ``selection``) or the one number given.
    Poll ``GET /api/admin/models/{id}`` until ``status`` is ``done`` (or ``failed``, with ``error``).
    409 when the study has no data to fit.
    """
    p_high = design_p_high() if body.p_high is None else body.p_high
    spec = fits.FitSpec(body.restarts, body.seed, p_high, None if body.states is None else tuple(body.states),
                        body.folds, body.with_ratings)
    model, job = fits.request_fit(session, study, spec, include_preview=body.include_preview)
    if job is None:
        response.status_code = 200
    else:
        background.add_task(worker.submit, job)  # after the response, so after the row is committed
    return fits.model_read(session, model)


@router.get("/studies/{slug}/models", response_model=list[ModelRead], responses=error_responses(404))
def list_models(study: StudyDep, session: SessionDep) -> list[ModelRead]:
    """The study's fitted models, newest first."""
    return [fits.model_read(session, m) for m in fits.list_models(session, study)]


@router.get("/models/{model_id}", response_model=ModelRead, responses=error_responses(404))
def get_model(model_id: ModelId, session: SessionDep) -> ModelRead:
    """Status and progress; once done: parameters with standard errors and status, log-likelihood, thresholds,
    trust-agnostic baseline, provenance and content hash."""
    return fits.model_read(session, fits.get_model(session, model_id))


@router.get("/models/{model_id}/document", responses={
    200: {"content": {"application/json": {}}, "description": "The model JSON (SPEC §9), as a download"},
    **error_responses(404, 409)})
def model_document(model_id: ModelId, session: SessionDep) -> Response:
    """The fitted model JSON (409 until the fit is done)."""
    model = fits.get_model(session, model_id)
    document: dict[str, Any] = fits.model_document(model)
    assert model.content_hash is not None
    return Response(json.dumps(document, indent=2) + "\n", media_type="application/json", headers={
        "Content-Disposition": f'attachment; filename="model-{model.id}-{model.content_hash[:12]}.json"',
        "Cache-Control": "no-store"})


@router.post("/models/{model_id}/evaluation-study", response_model=StudyDetailRead, status_code=201,
             responses={200: {"model": StudyDetailRead, "description": "Created before by the same request."},
                        **error_responses(404, 409)})
def create_evaluation_study(model_id: ModelId, body: EvaluationStudyCreate, session: SessionDep, settings: SettingsDep,
                            response: Response) -> StudyDetailRead:
    """A policy-evaluation study: trust-aware with this model against the trust-agnostic baseline of its data.

    Two counterbalanced blocks; the model is also the study's belief model. Repeating the request returns
    the study it created (200); a slug taken by another study is a 409.
    """
    model = fits.get_model(session, model_id)
    study, created = deployments.deploy_model(session, model, slug=body.slug, template_name=body.template,
                                              p_high=body.p_high, title=body.title, status=body.status)
    if not created:
        response.status_code = 200
    result = study_detail(session, study, settings)
    assert isinstance(result, StudyDetailRead)
    return result
