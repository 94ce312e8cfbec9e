"""The model registry: fit a study's data in the background and keep the model with its provenance.

A fit request reads the study's ``trials.csv`` exactly as the export writes it
(``server.export``), inside the request's transaction, and keeps
the rows ``trustlab fit`` would use (``experiment.records``: non-practice
trials of participants not excluded). The same data, restarts, seed,
p_high, states and folds give the same ``fit_key``; a repeated request returns the model that
is running or done instead of fitting again. The fit itself
(``experiment.evaluation.fit_bundle``; with ``states``, ``states_bundle``: the number of trust states the
data support, or the one given) runs in one background thread per
server process (``FitWorker``: fits are CPU-bound, one at a time), which
writes its progress and then the result. Rows still ``running`` when a server
starts belong to a process that died: they become ``failed`` (``trustlab serve``
is one process; several worker processes on one database would need a lease).
The evaluation study of a model is made by ``server.services.deployments``.
"""

from __future__ import annotations

import codecs
import csv
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass
from functools import reduce
from typing import Any, cast

from sqlalchemy import CursorResult, select, update
from sqlalchemy.orm import Session

from experiment.config import StudyConfig
from experiment.defaults import RATING_ITEM, SELECTION_FOLDS
from experiment.evaluation import ModelBundle, fit_bundle, states_bundle
from experiment.iohmm import PARAMETER_NAMES, flatten
from experiment.provenance import code_version, content_hash, data_hash
from experiment.records import DataError, grouped_sequences, parse_model_trials
from experiment.sequences import Sequence
from experiment.task import Complexity
from experiment.trust_ratings import Ratings, rating_scale_of, ratings_at_shelf_ends
from experiment.trust_states_document import K_FORMAT, parameter_names
from server import export
from server.db.units import SessionFactory
from server.errors import Conflict, NotFound
from server.models import AuditAction, FitStatus, FittedModel, Study, StudyVersion, utcnow
from server.schemas import (
    AgnosticBaselineRead,
    FitProgressRead,
    ModelProvenanceRead,
    ModelRead,
    ParameterEstimateRead,
    PolicyThresholdsRead,
    RatingsComparisonRead,
    RatingsRead,
    SelectionRead,
)
from server.services.audit import audit

log = logging.getLogger("trustlab")

#: EM iteration budget of a fit; progress is reported against it.
MAX_ITERATIONS = 1000
#: Shortest time between two progress writes of a running fit.
PROGRESS_INTERVAL_S = 0.25
INTERRUPTED = "the server stopped before this fit finished; request it again"


# -- the data a fit sees ----------------------------------------------------------------------

@dataclass(frozen=True)
class FitData:
    participants: list[str]
    sequences: list[Sequence]
    versions: list[int]
    n_trials: int
    data_hash: str  # of the model columns (and, with ratings, of the ratings placed at their trials)
    ratings: Ratings | None = None


def study_fit_data(session: Session, study: Study, *, include_preview: bool = False,
                   with_ratings: bool = False) -> FitData:
    """The study's trials as ``trials.csv`` holds them (preview sessions only with ``include_preview``), reduced to
    what a fit uses, and with ``with_ratings`` the shelf trust ratings of ``surveys.csv``; 409 when there are
    none."""
    target = export.ExportTarget(study.id, study.slug, study.title, include_preview=include_preview)
    where = f"{study.slug}/trials.csv"
    chunks = export.iter_csv(lambda: nullcontext(session), target, "trials.csv")
    try:
        grouped = parse_model_trials(_lines(chunks), where, keep=("version", "shelf"))
        participants, sequences = grouped_sequences(grouped, where)
        ratings = None
        versions = sorted({int(row["version"]) for rows in grouped.values() for row in rows})
        if with_ratings:
            low, high = _rating_scale(session, study, versions)
            shelves = {pid: [(int(row["block"]), int(row["shelf"])) for row in rows] for pid, rows in grouped.items()}
            answers = csv.DictReader(_lines(export.iter_csv(lambda: nullcontext(session), target, "surveys.csv")))
            ratings = ratings_at_shelf_ends(participants, shelves, answers, where=f"{study.slug}/surveys.csv",
                                            minimum=low, maximum=high)
            if not ratings.count:
                raise DataError(f"{study.slug}/surveys.csv: no trust rating of a shelf with scored trials (the "
                                "shelf questionnaire's trust item)")
    except DataError as exc:
        raise Conflict(f"cannot fit study {study.slug!r}: {exc}") from None
    digest = data_hash(grouped)  # of the model columns only: the same key as before ratings were read
    if ratings is not None:
        digest = content_hash({"trials": digest, "ratings": [levels.tolist() for levels in
                                                            ratings.levels_by_participant]})
    return FitData(participants, sequences, versions, sum(len(s) for s in sequences), digest, ratings)


def _rating_scale(session: Session, study: Study, versions: list[int]) -> tuple[int, int]:
    """The scale of the trust rating the fitted versions asked (one for all of them), or a DataError."""
    configs = session.scalars(select(StudyVersion.config).where(StudyVersion.study_id == study.id,
                                                                StudyVersion.version.in_(versions)))
    scales = [rating_scale_of(StudyConfig.model_validate(config)) for config in configs]
    asked = {scale for scale in scales if scale is not None}
    if len(asked) < len(set(scales)) or not asked:
        raise DataError(f"a version of the study ({', '.join(map(str, versions))}) asks no trust rating (its shelf "
                        f"questionnaire has no whole-point rating item {RATING_ITEM!r})")
    if len(asked) > 1:
        raise DataError(f"the study's versions ask the trust rating on different scales ({sorted(asked)})")
    return asked.pop()


def _lines(chunks: Iterable[bytes]) -> Iterator[str]:
    """The lines of a streamed UTF-8 CSV (chunk boundaries fall anywhere)."""
    decoder, pending = codecs.getincrementaldecoder("utf-8")(), ""
    for chunk in chunks:
        *lines, pending = (pending + decoder.decode(chunk)).split("\n")
        for line in lines:
            yield line + "\n"
    if pending := pending + decoder.decode(b"", final=True):
        yield pending


@dataclass(frozen=True)
class FitSpec:
    """What a fit request asks for. ``states`` None: the paper's two-state fit; several: the number of trust
    states the data support (``folds``-fold cross-validation by participant); one: that number."""

    restarts: int
    seed: int
    p_high: float
    states: tuple[int, ...] | None = None
    folds: int = SELECTION_FOLDS
    with_ratings: bool = False  # the shelf trust ratings as a second observation (``experiment.trust_ratings``)


def fit_key(data: FitData, spec: FitSpec) -> str:
    key: dict[str, Any] = {"data_hash": data.data_hash, "restarts": spec.restarts, "seed": spec.seed,
                           "p_high": spec.p_high}
    if spec.states is not None or spec.with_ratings:  # a two-state request keeps the key it had before
        key |= {"states": list(spec.states or (2,)), "folds": spec.folds}
    if spec.with_ratings:
        key |= {"with_ratings": True}
    return content_hash(key)


# -- requesting a fit -------------------------------------------------------------------------

@dataclass(frozen=True)
class FitJob:
    model_id: int
    sequences: list[Sequence]
    spec: FitSpec
    fitted_on: dict[str, Any]
    ratings: Ratings | None = None

    def bundle(self, progress: Callable[[int, int], None]) -> ModelBundle:
        spec = self.spec
        if spec.states is None and self.ratings is None:
            return fit_bundle(self.sequences, restarts=spec.restarts, seed=spec.seed, p_high=spec.p_high,
                              fitted_on=self.fitted_on, max_iter=MAX_ITERATIONS, progress=progress)
        return states_bundle(self.sequences, states=list(spec.states or (2,)), folds=spec.folds,
                             restarts=spec.restarts, seed=spec.seed, p_high=spec.p_high, fitted_on=self.fitted_on,
                             budget=MAX_ITERATIONS, progress=progress, ratings=self.ratings)


def request_fit(session: Session, study: Study, spec: FitSpec, *,
                include_preview: bool = False) -> tuple[FittedModel, FitJob | None]:
    """A new running model and the job that fits it, or the existing running/done model of the same request."""
    # one request per study at a time on PostgreSQL (SQLite's transactions are serial anyway)
    session.execute(select(Study.id).where(Study.id == study.id).with_for_update())
    data = study_fit_data(session, study, include_preview=include_preview, with_ratings=spec.with_ratings)
    cross_validated = spec.with_ratings or (spec.states is not None and len(spec.states) > 1)
    if cross_validated and len(data.participants) < spec.folds:
        what = "fit with trust ratings" if spec.with_ratings else "compare numbers of trust states"
        raise Conflict(f"cannot {what} on study {study.slug!r}: {spec.folds}-fold cross-validation by participant "
                       f"needs at least {spec.folds} participants, the data have {len(data.participants)}; ask for "
                       "fewer folds")
    key = fit_key(data, spec)
    existing = session.scalar(select(FittedModel).where(FittedModel.study_id == study.id, FittedModel.fit_key == key,
                                                        FittedModel.status.in_((FitStatus.RUNNING, FitStatus.DONE)))
                              .order_by(FittedModel.id.desc()).limit(1))
    if existing is not None:
        return existing, None
    version = code_version()
    row = FittedModel(study_id=study.id, fit_key=key, status=FitStatus.RUNNING, restarts=spec.restarts,
                      seed=spec.seed, p_high=spec.p_high, data_hash=data.data_hash, study_versions=data.versions,
                      participants=data.participants,
                      n_trials=data.n_trials, code_version=version, progress_done=0, progress_total=MAX_ITERATIONS,
                      evaluation_studies=[])
    session.add(row)
    session.flush()
    audit(session, AuditAction.MODEL_FIT, study_id=study.id, model_id=row.id, restarts=spec.restarts,
          seed=spec.seed, p_high=spec.p_high, data_hash=data.data_hash,
          states=None if spec.states is None else list(spec.states), folds=spec.folds,
          with_ratings=spec.with_ratings)
    fitted_on = {"source": f"trustlab study {study.slug}", "study": study.slug, "study_versions": data.versions,
                 "participants": data.participants, "n_trials": data.n_trials, "data_hash": data.data_hash,
                 "code_version": version}
    return row, FitJob(row.id, data.sequences, spec, fitted_on, data.ratings)


# -- the background worker --------------------------------------------------------------------

class FitInterrupted(RuntimeError):
    pass


class FitWorker:
    """Runs fits one at a time in a background thread of the server process."""

    def __init__(self, factory: SessionFactory):
        self.factory = factory
        self._lock = threading.Lock()
        self._executor: ThreadPoolExecutor | None = None  # started on the first fit (again after a stop)
        self._stopping = threading.Event()

    def submit(self, job: FitJob) -> Future[None]:
        with self._lock:
            if self._executor is None:
                self._stopping = threading.Event()
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="trustlab-fit")
            return self._executor.submit(self.run, job)

    def stop(self) -> None:
        """Interrupt the running fit at its next iteration and drop queued ones (they fail at the next start)."""
        with self._lock:
            executor, self._executor = self._executor, None
            self._stopping.set()
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)

    def run(self, job: FitJob) -> None:
        try:
            bundle = job.bundle(self._progress(job.model_id))
        except FitInterrupted as exc:
            self._finish(job.model_id, status=FitStatus.FAILED, error=str(exc))
        except Exception as exc:  # the failure is recorded with its reason; the server goes on
            log.exception("fit of model %s failed", job.model_id)
            self._finish(job.model_id, status=FitStatus.FAILED, error=f"{type(exc).__name__}: {exc}")
        else:
            self._finish(job.model_id, status=FitStatus.DONE, document=bundle.document,
                         content_hash=bundle.content_hash, loglik=bundle.loglik, policy=bundle.policy,
                         agnostic=bundle.agnostic, progress_done=MAX_ITERATIONS)

    def _progress(self, model_id: int) -> Callable[[int, int], None]:
        last = 0.0

        def report(done: int, total: int) -> None:
            nonlocal last
            if self._stopping.is_set():
                raise FitInterrupted(INTERRUPTED)
            now = time.monotonic()
            if now - last >= PROGRESS_INTERVAL_S:
                last = now
                with self.factory.begin() as session:
                    session.execute(update(FittedModel)
                                    .where(FittedModel.id == model_id, FittedModel.status == FitStatus.RUNNING)
                                    .values(progress_done=done, progress_total=total))
        return report

    def _finish(self, model_id: int, **values: Any) -> None:
        with self.factory.begin() as session:
            session.execute(update(FittedModel)
                            .where(FittedModel.id == model_id, FittedModel.status == FitStatus.RUNNING)
                            .values(finished_at=utcnow(), **values))


def fail_interrupted_fits(factory: SessionFactory) -> int:
    """Mark fits left running by a stopped server as failed (call on start); returns how many."""
    with factory.begin() as session:
        result = session.execute(update(FittedModel).where(FittedModel.status == FitStatus.RUNNING)
                                 .values(status=FitStatus.FAILED, error=INTERRUPTED, finished_at=utcnow()))
        return cast(CursorResult[Any], result).rowcount  # an UPDATE's result is a CursorResult


# -- reading ----------------------------------------------------------------------------------

def get_model(session: Session, model_id: int) -> FittedModel:
    model = session.get(FittedModel, model_id)
    if model is None:
        raise NotFound(f"no fitted model {model_id}")
    return model


def list_models(session: Session, study: Study) -> list[FittedModel]:
    """The study's models, newest first."""
    return list(session.scalars(select(FittedModel).where(FittedModel.study_id == study.id)
                                .order_by(FittedModel.id.desc())))


def model_document(model: FittedModel) -> dict[str, Any]:
    """The model JSON of a finished fit; 409 while it runs or when it failed."""
    if model.status != FitStatus.DONE or model.document is None:
        raise Conflict(_not_done(model))
    return model.document


def evaluation_blocker(model: FittedModel) -> str | None:
    """Why no policy-evaluation study can be made of ``model`` (None: one can), from what the fit stored: the fit
    is not done, its trust-agnostic baseline lacks a rate, or its trust-aware policy cannot be solved (the belief
    MDP needs a parameter the data never exercised; that does not depend on p_high). ``ModelRead`` shows it, so
    the dashboard can say so before the click; the deployment refuses with it (409)."""
    if model.status != FitStatus.DONE or model.document is None:
        return _not_done(model)
    agnostic = model.agnostic or {}
    if agnostic.get("error") or not agnostic.get("rates"):
        return f"there is no trust-agnostic baseline: {agnostic.get('error') or 'no intervention rates'}"
    missing = [c.value for c in Complexity if (agnostic["rates"].get(c.value) or {}).get("rate") is None]
    if missing:
        return f"there is no trust-agnostic baseline: no intervention rate for {' and '.join(missing)} complexity"
    policy = model.policy or {}
    if policy.get("error"):
        return f"the trust-aware policy cannot be solved: {policy['error']}"
    return None


def _not_done(model: FittedModel) -> str:
    if model.status == FitStatus.RUNNING:
        return (f"model {model.id} is still being fitted ({model.progress_done}/{model.progress_total} EM iterations); "
                f"poll GET /api/admin/models/{model.id} until its status is done")
    return f"the fit of model {model.id} failed: {model.error}"


def parameter_estimates(document: dict[str, Any]) -> list[ParameterEstimateRead]:
    """Every parameter of a model document of either format, by dotted name, with its standard error and status."""
    if document.get("format") == K_FORMAT:
        names = parameter_names(document["n_states"])
        values, stderr, status = ({n: reduce(dict.__getitem__, n.split("."), document[part]) for n in names}
                                  for part in ("params", "stderr", "status"))
    else:
        names = PARAMETER_NAMES
        values, stderr, status = (flatten(document[part]) for part in ("params", "stderr", "status"))
    return [ParameterEstimateRead(name=n, value=values[n], stderr=stderr[n], status=status[n]) for n in names]


def ratings_read(document: dict[str, Any]) -> RatingsRead | None:
    """The rating emission and the with/without comparison of a model document, if it was fitted with ratings."""
    ratings = document.get("ratings")
    if ratings is None:
        return None
    comparison = document.get("ratings_comparison")
    return RatingsRead(n_ratings=ratings["n_ratings"], scale=ratings["scale"], mean_rating=ratings["mean_rating"],
                       sd_rating=ratings["sd_rating"], alpha=ratings["alpha"], beta=ratings["beta"],
                       comparison=None if comparison is None else RatingsComparisonRead.model_validate(comparison))


def model_read(session: Session, model: FittedModel) -> ModelRead:
    slug = session.scalar(select(Study.slug).where(Study.id == model.study_id))
    document = model.document
    selection = None if document is None else document.get("selection")
    return ModelRead(
        id=model.id, status=model.status, error=model.error,
        progress=FitProgressRead(iterations_done=model.progress_done, iterations_max=model.progress_total),
        loglik=model.loglik, converged=document["fit"]["converged"] if document else None,
        content_hash=model.content_hash, parameters=[] if document is None else parameter_estimates(document),
        n_states=None if document is None else document.get("n_states", 2),
        selection=None if selection is None else SelectionRead.model_validate(selection),
        ratings=None if document is None else ratings_read(document),
        policy=PolicyThresholdsRead.model_validate(model.policy) if model.policy else None,
        agnostic=AgnosticBaselineRead.model_validate(model.agnostic) if model.agnostic else None,
        provenance=ModelProvenanceRead(study=slug or "", study_id=model.study_id, study_versions=model.study_versions,
                                   participants=model.participants, n_participants=len(model.participants),
                                   n_trials=model.n_trials, restarts=model.restarts, seed=model.seed,
                                   p_high=model.p_high, data_hash=model.data_hash, code_version=model.code_version),
        evaluation_studies=model.evaluation_studies, evaluation_blocked=evaluation_blocker(model),
        created_at=model.created_at, finished_at=model.finished_at)
