"""``trustlab policy``, ``agnostic``, ``fit`` and ``simulate``: the analysis commands (SPEC §9).

Thin: every command parses its arguments, calls the experiment core and
prints. ``--json`` prints exactly one JSON object on stdout; progress and
messages go to stderr. Bad input gives a one-line error and exit code 2.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict
from functools import wraps
from pathlib import Path
from typing import Annotated, Any, cast

import numpy as np
import typer

from experiment.agnostic import intervention_rates, trust_agnostic_policy
from experiment.belief_mdp import solve_belief_mdp
from experiment.config import StudyConfig
from experiment.config_problems import check_document
from experiment.defaults import (
    RATING_MAX_LEVELS,
    SELECTION_FOLDS,
    SHELF_SCALE_MAX,
    SHELF_SCALE_MIN,
    STATES_MAX,
    STATES_MIN,
)
from experiment.engine import simplex_resolution
from experiment.evaluation import policy_document
from experiment.fit import fit_iohmm
from experiment.iohmm import BeliefUpdate, IOHMMParams, ModelError
from experiment.model_selection import fit_with_ratings, model_document, select_states
from experiment.provenance import content_hash
from experiment.records import DataError, read_sequences, write_survey_rows, write_trials_csv
from experiment.recovery import recover
from experiment.report.plots import policy_on_simplex, to_png
from experiment.sequences import Sequence
from experiment.simulate import (
    compare_blocks,
    paper_comparison,
    power_analysis,
    power_sweep,
    reward_summary,
    simulate_study,
    sweep_document,
)
from experiment.task import Complexity, RobotAction, TaskParams
from experiment.templates import TEMPLATES, template
from experiment.trust_ratings import RatingEmission, Ratings, rating_emission_from_document, read_rated_sequences
from experiment.trust_states import KStateParams
from experiment.trust_states_document import TrustModel, load_trust_model_document, trust_model_from_document
from experiment.trust_states_em import EMSettings
from experiment.trust_states_policy import ask_share, describe, mean_belief_where, solve_k_state_policy
from server.cli.common import labelled_progress, progress_bar, refuse

JsonOpt = Annotated[bool, typer.Option("--json", help="Print one machine-readable JSON object on stdout.")]


def register(app: typer.Typer) -> None:
    app.command()(policy)
    app.command()(agnostic)
    app.command()(fit)
    app.command()(simulate)


def user_errors(command: Callable[..., None]) -> Callable[..., None]:
    """Turn the core's input errors into a one-line message and exit code 2."""
    @wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> None:
        try:
            command(*args, **kwargs)
        except (DataError, ModelError, ValueError, KeyError, OSError) as exc:
            refuse(str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc))
    return wrapper


def _emit(as_json: bool, payload: dict[str, Any], human: Callable[[], None]) -> None:
    if as_json:
        typer.echo(json.dumps(_jsonable(payload), allow_nan=False))
    else:
        human()


def _jsonable(value: Any) -> Any:
    """NaN/inf -> null and numpy scalars -> Python, so stdout is strict JSON."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(value) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


@user_errors
def policy(
    model_json: Annotated[str, typer.Argument(help="Model JSON file, or the word 'paper' for the paper's parameters.")],
    p_high: Annotated[float, typer.Option(min=0.0, max=1.0, help="Probability of a high-complexity trial.")] = 0.5,
    grid: Annotated[int, typer.Option(min=11, max=100_001, help="Number of belief grid points.")] = 1001,
    belief_update: Annotated[str,
                             typer.Option(help="'bayes' (conditions on the human action) or 'paper' (eq. "
                                               "belief-update).")] = "bayes",
    plot: Annotated[Path | None, typer.Option(help="A model of 3 or 4 trust states: write a PNG of where on the "
                                                   "belief simplex the robot asks.")] = None,
    as_json: JsonOpt = False,
) -> None:
    """Solve the belief MDP: the trust-aware policy (its thresholds, or with 3 or 4 trust states where on the
    belief simplex the robot asks)."""
    if belief_update not in ("bayes", "paper"):
        refuse(f"--belief-update must be 'bayes' or 'paper', got {belief_update!r}")
    model = trust_model_from_document(load_trust_model_document(model_json))
    if isinstance(model, IOHMMParams) and plot is not None:
        refuse("--plot draws the belief simplex of a model of 3 or 4 trust states; with two, the thresholds are the "
               "policy")
    if not isinstance(model, IOHMMParams):
        _k_state_policy(model, p_high, grid, cast(BeliefUpdate, belief_update), plot, as_json)
        return
    params = model
    solution = solve_belief_mdp(params, TaskParams(), p_high=p_high, grid=grid,
                                belief_update=cast(BeliefUpdate, belief_update))  # one of the two: checked above
    payload = policy_document(solution, params, TaskParams())

    def human() -> None:
        typer.echo(f"Trust-aware policy ({belief_update} belief update, p_high={p_high}, grid={grid}, "
                   f"{solution.iterations} value-iteration sweeps)")
        for c in Complexity:
            threshold = solution.thresholds[c]
            if threshold is None:
                typer.echo(f"  {c.value:>4} complexity: always "
                           f"{solution.constant_action[c] or 'mixed (not threshold-shaped)'}")
            else:
                typer.echo(f"  {c.value:>4} complexity: ask below belief {threshold:.4f}, act autonomously above")
    _emit(as_json, payload, human)


def _k_state_policy(model: KStateParams, p_high: float, grid: int, belief_update: BeliefUpdate, plot: Path | None,
                    as_json: bool) -> None:
    """A model of 3 or 4 trust states: the policy on the belief simplex, in words (and a plot)."""
    resolution = simplex_resolution(model.n_states, grid)
    solution = solve_k_state_policy(model, TaskParams(), p_high=p_high, resolution=resolution,
                                    belief_update=belief_update)
    asks = solution.policy == RobotAction.ASK.code
    where_ask, where_auto = (mean_belief_where(solution, a) for a in (RobotAction.ASK, RobotAction.AUTO))
    payload: dict[str, Any] = {
        "n_states": model.n_states, "p_high": p_high, "belief_update": belief_update, "resolution": resolution,
        "grid_points": len(solution.beliefs), "iterations": solution.iterations,
        "ask_share": {c.value: v for c, v in ask_share(solution).items()},
        "mean_belief_where_ask": {c.value: v for c, v in where_ask.items()},
        "mean_belief_where_auto": {c.value: v for c, v in where_auto.items()}}
    if plot is not None:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot.write_bytes(to_png(policy_on_simplex(solution.beliefs, asks, [c.value for c in Complexity])))
        payload["plot"] = str(plot)

    def human() -> None:
        typer.echo(f"Trust-aware policy of {model.n_states} trust states ({belief_update} belief update, "
                   f"p_high={p_high}, {len(solution.beliefs)} belief grid points, step 1/{resolution}, "
                   f"{solution.iterations} value-iteration sweeps)")
        for line in describe(solution):
            typer.echo(f"  {line}")
        if plot is not None:
            typer.echo(f"  plot written to {plot}")
    _emit(as_json, payload, human)


@user_errors
def agnostic(
    trials_csv: Annotated[Path,
                          typer.Argument(help="trials.csv (SPEC §9 columns); practice and excluded rows are ignored.")],
    as_json: JsonOpt = False,
) -> None:
    """The trust-agnostic policy from observed intervention rates."""
    _, sequences = read_sequences(trials_csv)
    rates = intervention_rates(sequences)
    if (reason := rates.missing_reason()) is not None:
        refuse(f"{trials_csv}: {reason}")
    baseline = trust_agnostic_policy(rates.rates, TaskParams())
    payload = rates.to_dict() | baseline.to_dict()

    def human() -> None:
        for c in Complexity:
            typer.echo(f"{c.value:>4}: P(intervene | auto) = {rates.rates[c]:.4f}  E[R | auto] = "
                       f"{baseline.expected_reward_auto[c]:.3f}  E[R | ask] = {baseline.expected_reward_ask[c]:.3f}"
                       f"  -> {baseline.action[c]}")
    _emit(as_json, payload, human)


@user_errors
def fit(
    trials_csv: Annotated[Path,
                          typer.Argument(help="trials.csv (SPEC §9 columns); practice and excluded rows are ignored.")],
    out: Annotated[Path, typer.Option(help="Where to write the fitted model JSON.")],
    restarts: Annotated[int, typer.Option(min=1, max=10_000, help="Random restarts of EM.")] = 20,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the random restarts (and of the folds).")] = 0,
    states: Annotated[str | None, typer.Option(
        help=f"Numbers of trust states, {STATES_MIN}…{STATES_MAX}, e.g. 2,3,4: several are compared by "
             "cross-validation and the chosen one is written; one is fitted as it is. Without it: the paper's "
             "two-state model.")] = None,
    cv: Annotated[int, typer.Option(min=2, max=100, help="Cross-validation folds of whole participants when "
                                    "--states names several numbers.")] = SELECTION_FOLDS,
    with_ratings: Annotated[bool, typer.Option(
        "--with-ratings", help="Use the shelf trust ratings as a second observation of the trust state (from "
        "surveys.csv beside trials.csv, or --surveys), and compare with the fit without them on held-out "
        "reliance.")] = False,
    surveys: Annotated[Path | None, typer.Option(help="surveys.csv of the same export (with --with-ratings); "
                                                 "default: beside trials.csv.")] = None,
    rating_scale: Annotated[str, typer.Option(help="The trust rating's scale as MIN,MAX in whole points (with "
                                              "--with-ratings; the paper's shelf question: 0,10).")] =
        f"{SHELF_SCALE_MIN},{SHELF_SCALE_MAX}",
    as_json: JsonOpt = False,
) -> None:
    """Fit the trust IOHMM by Baum–Welch with restarts; write the model JSON with standard errors.

    With --states 2,3,4 the numbers of trust states are compared first (held-out log-likelihood per trial,
    BIC, ICL) and the fewest states within two standard errors of the best is written.
    """
    if with_ratings:
        participants, sequences, ratings = read_rated_sequences(
            trials_csv, surveys or trials_csv.parent / "surveys.csv", _scale(rating_scale))
        _fit_with_ratings(trials_csv, out, participants, sequences, ratings,
                          _state_counts(states) if states is not None else [2], restarts, seed, cv, as_json)
        return
    if surveys is not None:
        raise ValueError("--surveys is read only with --with-ratings")
    participants, sequences = read_sequences(trials_csv)
    if states is not None:
        _fit_states(trials_csv, out, participants, sequences, _state_counts(states), restarts, seed, cv, as_json)
        return
    result = fit_iohmm(sequences, restarts=restarts, seed=seed,
                       progress=None if as_json else labelled_progress("EM iterations"))
    document = result.to_document(fitted_on={"source": str(trials_csv), "participants": participants})
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_jsonable(document), indent=2) + "\n", encoding="utf-8")

    def human() -> None:
        typer.echo(f"Fitted {result.n_sequences} participants, {result.n_trials} trials; log-likelihood "
                   f"{result.loglik:.4f} (best of {restarts} restarts). Model written to {out}")
        typer.echo(f"  content hash {content_hash(_jsonable(document))} (the model_hash of trials run under it)")
        from experiment.iohmm import PARAMETER_NAMES
        for name, value, se, status in zip(PARAMETER_NAMES, result.params.to_vector(), result.stderr, result.status,
                                           strict=True):
            shown = "   —  " if math.isnan(value) else f"{value:6.3f}"
            se_shown = f"± {se:.3f}" if not math.isnan(se) else ""
            typer.echo(f"  {name:<45} {shown} {se_shown:<8} {status}")
    _emit(as_json, document, human)


def _scale(text: str) -> tuple[int, int]:
    try:
        low, high = (int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"--rating-scale takes MIN,MAX in whole points (e.g. 0,10), got {text!r}") from None
    if not 0 < high - low <= RATING_MAX_LEVELS:
        raise ValueError(f"--rating-scale: MAX must exceed MIN by 1…{RATING_MAX_LEVELS} points, got {text!r}")
    return low, high


def _state_counts(text: str) -> list[int]:
    try:
        counts = sorted({int(part) for part in text.split(",") if part.strip()})
    except ValueError:
        raise ValueError(f"--states takes numbers of trust states separated by commas (e.g. 2,3,4), got {text!r}") \
            from None
    if not counts or not all(STATES_MIN <= k <= STATES_MAX for k in counts):
        raise ValueError(f"--states: every number of trust states must be {STATES_MIN}…{STATES_MAX}, got {text!r}")
    return counts


def _fit_states(trials_csv: Path, out: Path, participants: list[str], sequences: list[Sequence], counts: list[int],
                restarts: int, seed: int, folds: int, as_json: bool) -> None:
    selection = None
    if len(counts) > 1:
        bar = progress_bar()
        selection = select_states(sequences, counts, folds=folds, seed=seed, settings=EMSettings(restarts=restarts),
                                  progress=None if as_json else lambda label, done, total: bar(
                                      f"Comparing {label:<28}", done, total))
    chosen = counts[0] if selection is None else selection.chosen
    document = model_document(sequences, chosen, restarts=restarts, seed=seed, selection=selection,
                              fitted_on={"source": str(trials_csv), "participants": participants},
                              progress=None if as_json else labelled_progress(f"EM iterations, {chosen} states"))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_jsonable(document), indent=2) + "\n", encoding="utf-8")

    def human() -> None:
        if selection is not None:
            typer.echo(f"Compared {', '.join(map(str, counts))} trust states on {selection.n_participants} "
                       f"participants ({selection.n_trials} trials), {folds}-fold cross-validation by participant "
                       f"(seed {seed}):")
            typer.echo(f"  {'states':>6} {'log-lik':>11} {'params':>6} {'BIC':>10} {'ICL':>10}  held-out per trial")
            for c in selection.candidates:
                mark = "  <- chosen" if c.n_states == chosen else ""
                typer.echo(f"  {c.n_states:>6} {c.loglik:>11.2f} {c.fit.n_free:>6} {c.bic:>10.1f} {c.icl:>10.1f}  "
                           f"{c.held_out:.4f} ± {c.held_out_se:.4f}{mark}")
            typer.echo(f"  BIC counts trials as its sample size. Chosen: {selection.reason}")
        typer.echo(f"Fitted {chosen} trust states: log-likelihood {document['loglik']:.4f}. Model written to {out}")
        typer.echo(f"  content hash {content_hash(_jsonable(document))} (the model_hash of trials run under it)")
    _emit(as_json, document, human)  # as without --states: the model JSON (the comparison in "selection")


def _fit_with_ratings(trials_csv: Path, out: Path, participants: list[str], sequences: list[Sequence],
                      ratings: Ratings, counts: list[int], restarts: int, seed: int, folds: int,
                      as_json: bool) -> None:
    bar = progress_bar()
    fitted = fit_with_ratings(sequences, ratings, counts, restarts=restarts, seed=seed, folds=folds,
                              fitted_on={"source": str(trials_csv), "participants": participants},
                              progress=None if as_json else lambda label, done, total: bar(
                                  f"Comparing {label:<45}", done, total))
    document, rated, comparison = fitted.document, fitted.selection, fitted.comparison
    chosen = rated.chosen
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_jsonable(document), indent=2) + "\n", encoding="utf-8")

    def human() -> None:
        typer.echo(f"{rated.n_participants} participants, {rated.n_trials} trials, {ratings.count} trust ratings; "
                   f"{folds}-fold cross-validation by participant (seed {seed}), scored on held-out reliance:")
        if len(rated.candidates) > 1:
            for c in rated.candidates:
                mark = "  <- chosen" if c.n_states == chosen else ""
                typer.echo(f"  {c.n_states} states with ratings: {c.held_out:.4f} ± {c.held_out_se:.4f} per "
                           f"held-out trial{mark}")
            typer.echo(f"  Chosen: {rated.reason}")
        with_, without = comparison.with_ratings, comparison.without_ratings
        typer.echo(f"  {chosen} states with ratings {with_.held_out:.4f} ± {with_.held_out_se:.4f}, without "
                   f"{without.held_out:.4f} ± {without.held_out_se:.4f}: {comparison.verdict}")
        means = ", ".join(f"{m:.1f}" for m in document["ratings"]["mean_rating"])
        typer.echo(f"  Mean trust rating by state (lowest reliance first): {means} of "
                   f"{ratings.minimum}…{ratings.maximum}")
        typer.echo(f"Fitted {chosen} trust states with ratings: log-likelihood {document['loglik']:.4f} (reliance "
                   f"and ratings). Model written to {out}")
        typer.echo(f"  content hash {content_hash(_jsonable(document))} (the model_hash of trials run under it)")
    _emit(as_json, document, human)


def _design(name_or_path: str) -> StudyConfig:
    if name_or_path in TEMPLATES:
        return template(name_or_path)
    path = Path(name_or_path)
    if not path.exists():
        raise ValueError(f"unknown design {name_or_path!r}: not a built-in ({', '.join(TEMPLATES)}) and no such file")
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a JSON document: {exc}") from None
    config, problems = check_document(document)  # checked as the designer checks it
    if config is None:
        raise ValueError(f"{path}: invalid study config ({len(problems)} problem(s)): "
                         + "; ".join(map(str, problems[:10])))
    return config


@user_errors
def simulate(
    model_json: Annotated[str, typer.Argument(
        help="Model the simulated humans follow (a model JSON of 2 to 4 trust states, or 'paper').")],
    design: Annotated[str, typer.Option(help=f"Built-in design ({', '.join(TEMPLATES)}) or a study config JSON file.")],
    participants: Annotated[int | None,
                            typer.Option(min=1, max=100_000, help="Participants per simulated study.")] = None,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the simulation.")] = 0,
    replications: Annotated[int,
                            typer.Option(min=1, max=100_000, help="Simulated studies (power analysis when > 1).")] = 1,
    sweep: Annotated[str | None, typer.Option(help="Power analysis at each of these numbers of participants, e.g. "
                                              "10,20,40 (instead of --participants; needs --replications ≥ 2).")
                     ] = None,
    out: Annotated[Path | None,
                   typer.Option(help="Directory to write trials.csv of the (first) simulated study (and surveys.csv "
                                     "with the trust ratings, for a model fitted with ratings).")] = None,
    recover: Annotated[bool, typer.Option(
        "--recover", help="Parameter recovery: refit each of --replications simulated studies of --participants and "
                          "report per parameter the bias, RMSE and coverage of the 95 % intervals.")] = False,
    as_json: JsonOpt = False,
) -> None:
    """Simulate participants drawn from a model running through a study design (a power sweep with --sweep,
    parameter recovery with --recover)."""
    config = _design(design)
    model_document_ = load_trust_model_document(model_json)
    human_model = trust_model_from_document(model_document_)
    ratings = rating_emission_from_document(
        model_document_, 2 if isinstance(human_model, IOHMMParams) else human_model.n_states)
    if recover:
        if participants is None or sweep is not None or out is not None or replications < 2:
            refuse("--recover takes --participants N and --replications R ≥ 2 (not --sweep or --out)")
        _simulate_recovery(config, human_model, design, participants, replications, seed, as_json, ratings)
        return
    if sweep is not None:
        if participants is not None or out is not None:
            refuse("--sweep runs power analyses only: give it without --participants and --out")
        _simulate_sweep(config, human_model, design, _sizes(sweep), replications, seed, as_json)
        return
    if participants is None:
        refuse("give --participants N (or --sweep N1,N2,... for a power analysis at several N)")
    sim = simulate_study(config, human_model, participants, seed=seed, ratings=ratings)
    blocks = [b.name for b in config.blocks]
    payload: dict[str, Any] = {"design": design, "participants": participants, "seed": seed,
                               "blocks": {b: reward_summary(sim.rewards(b)) for b in blocks}}
    if len(blocks) == 2 and participants > 1:
        try:
            payload["test"] = asdict(compare_blocks(sim, *blocks).test)
        except ValueError as exc:  # no variation in either block: the t-test is undefined
            payload["test"] = {"t": None, "df": None, "p": None, "undefined": str(exc)}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        with (out / "trials.csv").open("w", encoding="utf-8", newline="") as handle:
            payload["trials_written"] = write_trials_csv(sim.records(), handle)
        if ratings is not None:
            with (out / "surveys.csv").open("w", encoding="utf-8", newline="") as handle:
                payload["ratings_written"] = write_survey_rows(sim.survey_rows(), handle)
    if replications > 1 and len(blocks) == 2:
        power = power_analysis(config, human_model, participants, replications, block_a=blocks[0], block_b=blocks[1],
                               seed=seed, progress=labelled_progress("replications") if not as_json else None)
        payload["power"] = {"replications": replications, "alpha": power.alpha, "power": power.power,
                            "mean_difference": power.mean_difference, "effect_size": power.effect_size}

    def human() -> None:
        typer.echo(f"{participants} simulated participants, design {design!r}, seed {seed}")
        for name, s in payload["blocks"].items():
            typer.echo(f"  {name:<16} cumulative reward: mean {s['mean']:.2f}, median {s['median']:.1f}, sd "
                       f"{s['sd']:.2f}")
        if payload.get("test", {}).get("p") is not None:
            t = payload["test"]
            typer.echo(f"  ttest2 {blocks[0]} vs {blocks[1]}: t = {t['t']:.3f}, df = {t['df']:.0f}, p = {t['p']:.4g}")
        if "power" in payload:
            pw = payload["power"]
            typer.echo(f"  power at alpha {pw['alpha']}: {pw['power']:.3f} over {replications} replications "
                       f"(mean difference {pw['mean_difference']:.2f}, effect size d = {pw['effect_size']:.3f})")
        if out is not None:
            typer.echo(f"  wrote {payload['trials_written']} trials to {out / 'trials.csv'}")
        if out is not None and "ratings_written" in payload:
            typer.echo(f"  wrote {payload['ratings_written']} trust ratings to {out / 'surveys.csv'}")
    _emit(as_json, payload, human)


def _simulate_recovery(config: StudyConfig, truth: TrustModel, design: str, participants: int, replications: int,
                       seed: int, as_json: bool, ratings: RatingEmission | None) -> None:
    result = recover(config, truth, participants, replications, seed=seed, ratings=ratings,
                     progress=None if as_json else labelled_progress("simulated studies refitted"))
    payload = {"design": design} | result.to_dict()

    def human() -> None:
        typer.echo(f"Parameter recovery: design {design!r}")
        for line in result.lines():
            typer.echo(line)
    _emit(as_json, payload, human)


def _sizes(sweep: str) -> list[int]:
    try:
        sizes = [int(part) for part in sweep.split(",") if part.strip()]
    except ValueError:
        raise ValueError(f"--sweep must be whole numbers separated by commas, e.g. 10,20,40; got {sweep!r}") from None
    if not sizes or min(sizes) < 2 or max(sizes) > 100_000:
        raise ValueError(f"--sweep numbers of participants must be between 2 and 100000, got {sweep!r}")
    return sorted(set(sizes))


def _simulate_sweep(config: StudyConfig, human_model: TrustModel, design: str, sizes: list[int], replications: int,
                    seed: int, as_json: bool) -> None:
    """Power at each N, the smallest N reaching 80 % power, and what the model predicts next to the paper."""
    blocks = [b.name for b in config.blocks]
    if len(blocks) != 2:
        refuse(f"a power analysis compares two blocks; design {design!r} has {len(blocks)}")
    if replications < 2:
        refuse("--sweep needs --replications R ≥ 2: power is the fraction of R simulated studies with p < 0.05")
    bar = None if as_json else progress_bar()
    result = power_sweep(config, human_model, sizes, replications, block_a=blocks[0], block_b=blocks[1], seed=seed,
                         progress=None if bar is None else lambda n, done, total: bar(f"N = {n}", done, total))
    payload = {"design": design, "seed": seed, "replications": replications} | sweep_document(result, blocks) | {
        "paper": paper_comparison(config, result.results[-1])}
    _emit(as_json, payload, lambda: _print_sweep(payload))


def _print_sweep(payload: dict[str, Any]) -> None:
    blocks, rows, target = payload["compared"], payload["sweep"], payload["target_power"]
    typer.echo(f"Power of {blocks[0]} > {blocks[1]} (ttest2 on cumulative reward per block, alpha {payload['alpha']}), "
               f"{payload['replications']} simulated studies per N, design {payload['design']!r}, seed "
               f"{payload['seed']}")
    typer.echo(f"  {'N':>6}  {'power':>6}  {'d':>7}  {'mean diff':>9}  {'95% of diffs':>17}  "
               + "  ".join(f"{b + ' mean (sd)':>24}" for b in blocks))
    for row in rows:
        low, high = row["difference_95"]
        rewards = "  ".join(f"{row['rewards'][b]['mean']:>15.2f} ({row['rewards'][b]['sd']:6.2f})" for b in blocks)
        typer.echo(f"  {row['participants']:>6}  {row['power']:>6.3f}  {row['effect_size']:>7.3f}  "
                   f"{row['mean_difference']:>9.2f}  [{low:>7.2f}, {high:>7.2f}]  {rewards}")
    if payload["participants_needed"] is None:
        typer.echo(f"  No N tried reached {target:.0%} power (largest: {rows[-1]['participants']}, power "
                   f"{rows[-1]['power']:.3f}); try larger numbers.")
    else:
        typer.echo(f"  Smallest N tried with at least {target:.0%} power: {payload['participants_needed']}.")
    if payload["paper"] is not None:
        typer.echo("  " + payload["paper"]["message"])

