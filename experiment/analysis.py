"""Statistics for the report: t-tests and the trust-vs-survey fits (paper §4.4–4.5, §5.2–5.3).

- ``ttest2``: two-sample t-test equivalent to MATLAB ``ttest2`` (cumulative
  reward per policy, §5.2; Schaefer scores after each policy, §5.3).
- ``paired_ttest``: within-participant comparison (Schaefer pre vs. post).
- ``fit_logistic``: P^T(r) = L / (1 + exp(−k (r − r0))) fitted by least squares
  to the median belief per trust answer, like MATLAB ``fit`` (§4.4).
- ``fit_linear``: ordinary least squares line with 95 % confidence intervals
  (reliance on trust, §4.5).

Inputs are 1-D array-likes of finite numbers; anything that makes a statistic
undefined raises ``ValueError`` with the reason instead of returning garbage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize, special, stats

CONFIDENCE = 0.95
#: Evaluation budget per start of the logistic fit. Logistic-shaped data converge
#: in < 30; data with no logistic shape crawl towards a bound, and stopping there
#: still gives a finite (if poor) fit.
_MAX_NFEV = 150


def _vector(name: str, values: object, min_size: int) -> np.ndarray:
    """``values`` as a float array of shape (n,), n ≥ min_size, all finite."""
    array = np.asarray(values, dtype=float)
    if array.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {array.shape}")
    if array.size < min_size:
        raise ValueError(f"{name} needs at least {min_size} values, got {array.size}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


def _same_length(x: np.ndarray, y: np.ndarray) -> None:
    if x.size != y.size:
        raise ValueError(f"x and y must have the same length, got {x.size} and {y.size}")


# --- t-tests -------------------------------------------------------------------

@dataclass(frozen=True)
class TTestResult:
    """Two-sided t-test of mean(x) = mean(y); [ci_low, ci_high] is the CI (default 95 %) of mean(x) − mean(y)."""

    t: float
    df: float
    p: float
    mean_x: float
    mean_y: float
    ci_low: float
    ci_high: float


def _t_result(diff: float, se: float, df: float, x: np.ndarray, y: np.ndarray, confidence: float) -> TTestResult:
    """t = diff / se with Student-t(df) p-value and confidence interval diff ± t_{(1+c)/2, df} · se."""
    if not se > 0:
        raise ValueError("the standard error is 0 (no variation in the data): t is undefined")
    t = diff / se
    half = float(stats.t.ppf(0.5 + confidence / 2, df)) * se
    return TTestResult(t=t, df=float(df), p=float(2 * stats.t.sf(abs(t), df)), mean_x=float(x.mean()),
                       mean_y=float(y.mean()), ci_low=diff - half, ci_high=diff + half)


def _sum_squares(x: np.ndarray) -> float:
    """Σ (x − x̄)², exactly 0 for a constant sample (no rounding residue from the mean)."""
    return 0.0 if np.ptp(x) == 0 else float(np.sum((x - x.mean()) ** 2))


def _check_confidence(confidence: float) -> None:
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")


def ttest2(x: object, y: object, *, equal_var: bool = True, confidence: float = CONFIDENCE) -> TTestResult:
    """Two-sample, two-sided t-test, as MATLAB ``ttest2(x, y)``; x: (n_x,), y: (n_y,).

    ``equal_var=True`` (MATLAB's default ``'Vartype','equal'``) pools the
    variances: s² = (SS_x + SS_y) / df, se = s·sqrt(1/n_x + 1/n_y),
    df = n_x + n_y − 2. ``equal_var=False`` (``'unequal'``) is Welch's test:
    se² = s_x²/n_x + s_y²/n_y with Welch–Satterthwaite df. Same numbers as
    ``scipy.stats.ttest_ind``, computed directly so that a constant sample
    (legitimate here) does not trip scipy's precision warning.
    """
    _check_confidence(confidence)
    x, y = _vector("x", x, 1 if equal_var else 2), _vector("y", y, 1 if equal_var else 2)
    nx, ny, diff = x.size, y.size, float(x.mean() - y.mean())
    df: float
    if equal_var:
        df = nx + ny - 2
        if df < 1:
            raise ValueError("the pooled test needs n_x + n_y ≥ 3 (at least one degree of freedom)")
        se = math.sqrt((_sum_squares(x) + _sum_squares(y)) / df * (1 / nx + 1 / ny))
        return _t_result(diff, se, df, x, y, confidence)
    vx, vy = _sum_squares(x) / (nx - 1) / nx, _sum_squares(y) / (ny - 1) / ny
    se = math.sqrt(vx + vy)
    df = (vx + vy) ** 2 / (vx**2 / (nx - 1) + vy**2 / (ny - 1)) if se > 0 else math.nan
    return _t_result(diff, se, df, x, y, confidence)


def paired_ttest(x: object, y: object, *, confidence: float = CONFIDENCE) -> TTestResult:
    """Paired, two-sided t-test of mean(x − y) = 0, as MATLAB ``ttest(x, y)``; df = n − 1.

    x, y: (n,) with x[i] and y[i] from the same participant (e.g. Schaefer
    score before and after a block). se = sd(x − y) / sqrt(n).
    """
    _check_confidence(confidence)
    x, y = _vector("x", x, 2), _vector("y", y, 2)
    _same_length(x, y)
    d = x - y
    se = math.sqrt(_sum_squares(d) / (d.size - 1) / d.size)
    return _t_result(float(d.mean()), se, d.size - 1, x, y, confidence)


# --- Logistic fit ------------------------------------------------------------------

@dataclass(frozen=True)
class LogisticFit:
    """y ≈ L / (1 + exp(−k (r − r0))) with goodness of fit as MATLAB ``fit`` reports it.

    sse = Σ residual²; rmse = sqrt(sse / dfe) with dfe = n − 3 (three
    coefficients), MATLAB's "RMSE" (the standard error of the regression), not
    sqrt(sse / n). rmse is NaN when n = 3 (no residual degrees of freedom).
    """

    L: float
    k: float
    r0: float
    sse: float
    rmse: float
    n: int

    def __call__(self, r: object) -> np.ndarray:
        return logistic(np.asarray(r, dtype=float), self.L, self.k, self.r0)


def logistic(r: np.ndarray, L: float, k: float, r0: float) -> np.ndarray:
    """L / (1 + exp(−k (r − r0))), evaluated without overflow. r: any shape."""
    return L * special.expit(k * (r - r0))


def _starts(r: np.ndarray, y: np.ndarray) -> list[tuple[float, float, float]]:
    """A few starting points (L, k, r0): scale from the data, midpoint and direction varied."""
    span = float(np.ptp(r))
    top = max(float(np.abs(y).max()), 1e-6)
    mids = np.quantile(r, [0.0, 0.5, 1.0])
    return [(top, sign * 4.0 / span, float(m)) for sign in (1.0, -1.0) for m in mids]


def fit_logistic(r: object, y: object) -> LogisticFit:
    """Least-squares fit of y = L / (1 + exp(−k (r − r0))) (paper §4.4).

    r, y: (n,), e.g. trust answers and the median belief for each. Solved with
    ``scipy.optimize.least_squares`` (trust-region reflective with bounds, the
    solver behind ``curve_fit``, called directly because ``curve_fit`` raises
    instead of returning the best point when its evaluation budget runs out)
    from several starts, keeping the lowest SSE. Bounds: 0 ≤ L ≤ 10·max|y|,
    |k| ≤ 100/range(r), r0 within 10 ranges of the data, so step-like or flat
    data give finite parameters. Raises ``ValueError`` with fewer than 3
    distinct r values (three coefficients).
    """
    r, y = _vector("r", r, 1), _vector("y", y, 1)
    _same_length(r, y)
    if np.unique(r).size < 3:
        raise ValueError(f"a 3-parameter logistic needs at least 3 distinct r values, got {np.unique(r).size}")
    span, top = float(np.ptp(r)), max(float(np.abs(y).max()), 1e-6)
    bounds = ((0.0, -100.0 / span, float(r.min()) - 10 * span), (10 * top, 100.0 / span, float(r.max()) + 10 * span))
    (L, k, r0), sse = min((_fit_from(r, y, start, bounds) for start in _starts(r, y)), key=lambda f: f[1])
    dfe = r.size - 3
    return LogisticFit(L=L, k=k, r0=r0, sse=sse, rmse=math.sqrt(sse / dfe) if dfe > 0 else math.nan, n=int(r.size))


def _jacobian(params: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(n, 3): derivatives of the logistic with respect to L, k, r0."""
    L, k, r0 = params
    s = special.expit(k * (r - r0))
    slope = L * s * (1 - s)
    return np.column_stack([s, slope * (r - r0), -slope * k])


def _fit_from(r: np.ndarray, y: np.ndarray, start: tuple[float, float, float],
              bounds: tuple[tuple[float, ...], tuple[float, ...]]) -> tuple[tuple[float, float, float], float]:
    """((L, k, r0), sse) of a bounded least-squares run from one start (best point even if not converged)."""
    x0 = [float(np.clip(s, lo, hi)) for s, lo, hi in zip(start, *bounds, strict=True)]
    def residuals(p: np.ndarray) -> np.ndarray:
        return logistic(r, *p) - y

    def jacobian(p: np.ndarray) -> np.ndarray:
        return _jacobian(p, r)

    result = optimize.least_squares(residuals, x0, jac=jacobian,
                                    bounds=bounds, method="trf", max_nfev=_MAX_NFEV)
    L, k, r0 = (float(v) for v in result.x)
    return (L, k, r0), float(np.sum((logistic(r, L, k, r0) - y) ** 2))


def median_by_answer(answers: object, beliefs: object) -> tuple[np.ndarray, np.ndarray]:
    """The distinct answers, ascending, and the median belief for each.

    answers, beliefs: (n,), e.g. each shelf's trust answer and the belief of
    high trust at the end of that shelf. Returns levels (m,), medians (m,).
    """
    answers, beliefs = _vector("answers", answers, 1), _vector("beliefs", beliefs, 1)
    _same_length(answers, beliefs)
    levels, inverse = np.unique(answers, return_inverse=True)
    medians = np.array([np.median(beliefs[inverse == i]) for i in range(levels.size)])
    return levels, medians


# --- Linear fit ------------------------------------------------------------------

@dataclass(frozen=True)
class LinearFit:
    """y ≈ slope·x + intercept by ordinary least squares, with 95 % t-intervals (df = n − 2).

    r2 = 1 − SSE/SST; NaN when y is constant (SST = 0).
    """

    slope: float
    intercept: float
    r2: float
    n: int
    slope_ci: tuple[float, float]
    intercept_ci: tuple[float, float]

    def __call__(self, x: object) -> np.ndarray:
        return self.slope * np.asarray(x, dtype=float) + self.intercept


def fit_linear(x: object, y: object, *, confidence: float = CONFIDENCE) -> LinearFit:
    """Least-squares line through (x, y) (paper §4.5: Rel(r) = 0.63 r + 3.27).

    x, y: (n,), n ≥ 3 with at least 2 distinct x. Standard errors:
    se_slope = s / sqrt(Sxx), se_intercept = s · sqrt(1/n + x̄²/Sxx), s² = SSE/(n − 2).
    """
    _check_confidence(confidence)
    x, y = _vector("x", x, 3), _vector("y", y, 3)
    _same_length(x, y)
    x_mean, y_mean = x.mean(), y.mean()
    sxx = float(np.sum((x - x_mean) ** 2))
    if sxx == 0:
        raise ValueError("x is constant: the slope is undefined")
    slope = float(np.sum((x - x_mean) * (y - y_mean)) / sxx)
    intercept = float(y_mean - slope * x_mean)
    sse = float(np.sum((y - slope * x - intercept) ** 2))
    sst = float(np.sum((y - y_mean) ** 2))
    s = math.sqrt(sse / (x.size - 2))
    half = float(stats.t.ppf(0.5 + confidence / 2, x.size - 2))
    se_slope, se_intercept = s / math.sqrt(sxx), s * math.sqrt(1 / x.size + x_mean**2 / sxx)
    return LinearFit(slope=slope, intercept=intercept, r2=1 - sse / sst if sst > 0 else math.nan, n=int(x.size),
                     slope_ci=(slope - half * se_slope, slope + half * se_slope),
                     intercept_ci=(intercept - half * se_intercept, intercept + half * se_intercept))
