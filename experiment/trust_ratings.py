"""Self-reported trust as a second observation of the trust state (issue 40): an ordinal emission at rated trials.

After each shelf the study asks "To what extent do you trust the robot?" on a 0…10 scale (paper §4.4; the
``trust`` item of the shelf questionnaire, ``surveys.csv`` context ``shelf:B:S``). A rating is placed at the last
scored trial of its shelf and modelled as emitted by the trust state at that trial:

    P(rating = m + r | state j) = BetaBinomial(r; n = levels, α_j, β_j),   r = 0 … levels,

an ordinal emission (higher α_j / (α_j + β_j): higher ratings) whose spread is the state's own: people use a
rating scale differently, and a binomial (no extra spread) would let the ratings overrule the reliance sequence.
Its maximisation step has no closed form: ``beta_binomial_update`` takes vectorised Newton steps in (log α, log β)
with step halving, so every EM iteration still never lowers the likelihood (a generalised EM).
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import betaln, digamma, gammaln, polygamma

from experiment import defaults
from experiment.config import StudyConfig
from experiment.records import DataError, grouped_sequences, read_model_trials
from experiment.sequences import Sequence

#: No rating at this trial (``Ratings.levels``' code).
NO_RATING = -1


@dataclass(frozen=True)
class RatingEmission:
    """Beta-binomial rating emission of K states: ``alpha``, ``beta`` (K,) on the scale ``minimum`` … ``maximum``."""

    alpha: np.ndarray
    beta: np.ndarray
    minimum: int = defaults.SHELF_SCALE_MIN
    maximum: int = defaults.SHELF_SCALE_MAX

    @property
    def levels(self) -> int:
        return self.maximum - self.minimum

    def pmf(self) -> np.ndarray:
        """(levels + 1, K) P(rating = minimum + r | state j)."""
        return np.exp(log_pmf(self.alpha[None], self.beta[None], self.levels)[0]).T

    def mean_rating(self) -> np.ndarray:
        """(K,) the expected rating of each state, on the scale."""
        return self.minimum + self.levels * self.alpha / (self.alpha + self.beta)

    def sd_rating(self) -> np.ndarray:
        """(K,) the standard deviation of a state's ratings (beta-binomial: n μ (1 − μ) (α + β + n) / (α + β + 1))."""
        total = self.alpha + self.beta
        mean = self.alpha / total
        return np.sqrt(self.levels * mean * (1 - mean) * (total + self.levels) / (total + 1))

    def permuted(self, order: np.ndarray) -> RatingEmission:
        return RatingEmission(self.alpha[order], self.beta[order], self.minimum, self.maximum)

    def to_document(self) -> dict[str, Any]:
        """The model JSON's ``"ratings"`` section (states in the model's order)."""
        return {"emission": "beta-binomial", "item": defaults.RATING_ITEM, "scale": [self.minimum, self.maximum],
                "alpha": self.alpha.tolist(), "beta": self.beta.tolist(), "mean_rating": self.mean_rating().tolist(),
                "sd_rating": self.sd_rating().tolist()}


def rating_emission_from_document(document: Any, n_states: int) -> RatingEmission | None:
    """The ``"ratings"`` section of a model JSON (written by ``trustlab fit --with-ratings``), or None if it has
    none; a malformed one is a ``DataError`` naming what is wrong."""
    section = document.get("ratings") if isinstance(document, dict) else None
    if section is None:
        return None
    try:
        alpha, beta = (np.array(section[name], dtype=float) for name in ("alpha", "beta"))
        minimum, maximum = (int(x) for x in section["scale"])
    except (KeyError, TypeError, ValueError):
        raise DataError("the model's \"ratings\" needs \"alpha\" and \"beta\" (a number per state) and "
                        "\"scale\" ([minimum, maximum])") from None
    if alpha.shape != (n_states,) or beta.shape != (n_states,):
        raise DataError(f"the model's \"ratings\" must give alpha and beta for each of its {n_states} states")
    if not (np.isfinite(alpha).all() and np.isfinite(beta).all() and (alpha > 0).all() and (beta > 0).all()):
        raise DataError("the model's rating alpha and beta must be positive numbers")
    if not 0 < maximum - minimum <= defaults.RATING_MAX_LEVELS:
        raise DataError(f"the model's rating scale must span 1…{defaults.RATING_MAX_LEVELS} points, got "
                        f"{minimum}…{maximum}")
    return RatingEmission(alpha, beta, minimum, maximum)


def log_pmf(alpha: np.ndarray, beta: np.ndarray, levels: int) -> np.ndarray:
    """(..., K, levels + 1) log BetaBinomial(r; levels, α, β) for α, β (..., K)."""
    r = np.arange(levels + 1)
    a, b = alpha[..., None], beta[..., None]
    choose = gammaln(levels + 1) - gammaln(r + 1) - gammaln(levels - r + 1)
    return choose + betaln(r + a, levels - r + b) - betaln(a, b)


def _objective(counts: np.ndarray, alpha: np.ndarray, beta: np.ndarray, levels: int) -> np.ndarray:
    """(..., K) Σ_r counts[r] log P(r | α, β); counts (..., levels + 1, K)."""
    return (np.swapaxes(counts, -1, -2) * log_pmf(alpha, beta, levels)).sum(axis=-1)


def beta_binomial_update(counts: np.ndarray, alpha: np.ndarray, beta: np.ndarray, levels: int,
                         steps: int = defaults.RATING_NEWTON_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """α, β (..., K) raised towards the maximum of Σ_r counts[r] log P(r | α, β) (counts (..., levels + 1, K)).

    Newton in u = log α, v = log β (gradient ascent where the Hessian is not negative definite), each step
    halved until the objective does not fall, and kept within ``defaults.RATING_CONCENTRATION_RANGE``. States
    with no expected ratings keep their values.
    """
    low, high = (np.log(x) for x in defaults.RATING_CONCENTRATION_RANGE)
    u, v = np.log(alpha), np.log(beta)
    n = np.swapaxes(counts, -1, -2)  # (..., K, L)
    total = n.sum(axis=-1)
    r = np.arange(levels + 1)
    current = _objective(counts, alpha, beta, levels)
    for _ in range(steps):
        a, b = np.exp(u), np.exp(v)
        ab = a + b
        common = digamma(ab) - digamma(levels + ab)
        ga = (n * digamma(r + a[..., None])).sum(-1) - total * digamma(a) + total * common
        gb = (n * digamma(levels - r + b[..., None])).sum(-1) - total * digamma(b) + total * common
        common2 = polygamma(1, ab) - polygamma(1, levels + ab)
        haa = (n * polygamma(1, r + a[..., None])).sum(-1) - total * polygamma(1, a) + total * common2
        hbb = (n * polygamma(1, levels - r + b[..., None])).sum(-1) - total * polygamma(1, b) + total * common2
        hab = total * common2
        # chain rule to (u, v): g_u = a g_a, H_uu = a² h_aa + a g_a, H_uv = a b h_ab
        gu, gv = a * ga, b * gb
        huu, hvv, huv = a * a * haa + gu, b * b * hbb + gv, a * b * hab
        det = huu * hvv - huv * huv
        concave = (huu < 0) & (det > 0)
        safe = np.where(concave, det, 1.0)
        du = np.where(concave, -(hvv * gu - huv * gv) / safe, 0.1 * np.sign(gu))
        dv = np.where(concave, -(huu * gv - huv * gu) / safe, 0.1 * np.sign(gv))
        scale = np.ones_like(u)
        improved = np.zeros(u.shape, dtype=bool)
        for _ in range(12):  # step halving: keep the largest step that does not lower the objective
            nu = np.clip(u + scale * du, low, high)
            nv = np.clip(v + scale * dv, low, high)
            value = _objective(counts, np.exp(nu), np.exp(nv), levels)
            accept = ~improved & (value >= current)
            u, v = np.where(accept, nu, u), np.where(accept, nv, v)
            current = np.where(accept, value, current)
            improved |= accept
            scale = np.where(improved, scale, scale / 2.0)
            if improved.all():
                break
    rated = total > 0
    return np.where(rated, np.exp(u), alpha), np.where(rated, np.exp(v), beta)


# -- data -------------------------------------------------------------------------

@dataclass(frozen=True)
class Ratings:
    """Per participant (in the order of the sequences), the rating level (0 … levels) at each trial, or -1."""

    levels_by_participant: tuple[np.ndarray, ...]
    minimum: int = defaults.SHELF_SCALE_MIN
    maximum: int = defaults.SHELF_SCALE_MAX

    @property
    def levels(self) -> int:
        return self.maximum - self.minimum

    @property
    def count(self) -> int:
        return int(sum((x >= 0).sum() for x in self.levels_by_participant))


def rating_scale_of(config: StudyConfig) -> tuple[int, int] | None:
    """The (minimum, maximum) on which a study asks the trust rating (its shelf questionnaire's rating item
    ``defaults.RATING_ITEM``), or None when it asks none."""
    if not config.shelf_questionnaire:
        return None
    questionnaire = config.questionnaire(config.shelf_questionnaire)
    if not any(item.id == defaults.RATING_ITEM and item.kind == "rating" for item in questionnaire.items):
        return None
    scale = questionnaire.scale
    if scale is None or scale.step != 1 or scale.min != int(scale.min) or scale.max != int(scale.max):
        return None  # not whole points: no ordinal emission of its levels
    return int(scale.min), int(scale.max)


def ratings_at_shelf_ends(participants: list[str], shelves: dict[str, list[tuple[int, int]]],
                          answers: Iterable[dict[str, str]], *, where: str = "", item: str = defaults.RATING_ITEM,
                          minimum: int = defaults.SHELF_SCALE_MIN, maximum: int = defaults.SHELF_SCALE_MAX) -> Ratings:
    """Ratings placed at the last scored trial of their shelf.

    ``shelves[participant]``: the (block, shelf) of each of the participant's model trials, in sequence order.
    ``answers``: ``surveys.csv`` rows; those of ``item`` in a ``shelf:B:S`` context are used, others ignored. A
    rating of a participant or shelf without scored trials (excluded, practice) is left out; a value off the
    scale's whole points is an error.
    """
    placed = {pid: np.full(len(shelves[pid]), NO_RATING, dtype=np.int64) for pid in participants}
    last_index = {pid: {key: i for i, key in enumerate(shelves[pid])} for pid in participants}
    for line, row in enumerate(answers, start=2):
        context = row.get("context") or ""
        if row.get("item") != item or not context.startswith("shelf:"):
            continue
        pid = row.get("participant_id", "")
        if pid not in placed:
            continue
        try:
            _, block, shelf = context.split(":")
            key = (int(block), int(shelf))
            value = float(row.get("value") or "nan")
        except ValueError:
            raise DataError(f"{where}:{line}: a shelf context is shelf:B:S with a rating value, got context "
                            f"{context!r} and value {row.get('value')!r}") from None
        if not (minimum <= value <= maximum and value == int(value)):
            raise DataError(f"{where}:{line}: a {item!r} rating must be a whole number {minimum}…{maximum}, "
                            f"got {row.get('value')!r}")
        index = last_index[pid].get(key)
        if index is not None:
            placed[pid][index] = int(value) - minimum
    return Ratings(tuple(placed[pid] for pid in participants), minimum, maximum)


def read_rated_sequences(trials_csv: str | Path, surveys_csv: str | Path,
                         scale: tuple[int, int] = (defaults.SHELF_SCALE_MIN, defaults.SHELF_SCALE_MAX),
                         ) -> tuple[list[str], list[Sequence], Ratings]:
    """Participants, their model sequences (as ``records.read_sequences``) and their trust ratings on ``scale``,
    from an export's ``trials.csv`` (whose ``shelf`` column places each trial) and ``surveys.csv``."""
    grouped = read_model_trials(trials_csv)
    participants, sequences = grouped_sequences(grouped, trials_csv)
    shelves = {}
    for pid, rows in grouped.items():
        try:
            shelves[pid] = [(int(row["block"]), int(row["shelf"])) for row in rows]
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{trials_csv}: ratings are placed by each trial's block and shelf, but participant "
                            f"{pid!r} has a trial without a whole-number shelf (the export's shelf column)") from None
    return participants, sequences, read_ratings(trials_csv, surveys_csv, participants, shelves, scale)


def read_ratings(trials_csv: str | Path, surveys_csv: str | Path, participants: list[str],
                 shelves: dict[str, list[tuple[int, int]]],
                 scale: tuple[int, int] = (defaults.SHELF_SCALE_MIN, defaults.SHELF_SCALE_MAX)) -> Ratings:
    """``ratings_at_shelf_ends`` of a ``surveys.csv`` file (the export's)."""
    path = Path(surveys_csv)
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            missing = {"participant_id", "context", "item", "value"} - set(reader.fieldnames or [])
            if missing:
                raise DataError(f"{path}: missing column(s) {', '.join(sorted(missing))}")
            return ratings_at_shelf_ends(participants, shelves, reader, where=str(path), minimum=scale[0],
                                         maximum=scale[1])
    except OSError as error:
        raise DataError(f"cannot read the ratings beside {trials_csv}: {error}") from None


def sample_ratings(emission: RatingEmission, states: list[np.ndarray], every: int,
                   rng: np.random.Generator) -> Ratings:
    """Simulated ratings: one every ``every`` trials (the end of a shelf) and at the last trial, from the state."""
    pmf = emission.pmf()
    out = []
    for path in states:
        levels = np.full(len(path), NO_RATING, dtype=np.int64)
        rated = np.unique(np.r_[np.arange(every - 1, len(path), every), len(path) - 1])
        for t in rated:
            levels[t] = rng.choice(emission.levels + 1, p=pmf[:, path[t]])
        out.append(levels)
    return Ratings(tuple(out), emission.minimum, emission.maximum)
