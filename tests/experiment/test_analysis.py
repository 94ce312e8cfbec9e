import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from experiment import defaults
from experiment.analysis import fit_linear, fit_logistic, logistic, median_by_answer, paired_ttest, ttest2

PAPER_LOGISTIC = (defaults.PAPER_LOGISTIC_L, defaults.PAPER_LOGISTIC_K, defaults.PAPER_LOGISTIC_R0)
#: Trust answers that received ratings in the paper (§4.4: none below 3).
ANSWERS = np.arange(3, defaults.SHELF_SCALE_MAX + 1, dtype=float)

samples = st.lists(st.integers(-50, 150), min_size=2, max_size=30).map(np.array)


# --- t-tests ------------------------------------------------------------------------

def pooled_by_hand(x, y):
    nx, ny = len(x), len(y)
    df = nx + ny - 2
    sp2 = ((nx - 1) * np.var(x, ddof=1) + (ny - 1) * np.var(y, ddof=1)) / df
    se = math.sqrt(sp2 * (1 / nx + 1 / ny))
    diff = np.mean(x) - np.mean(y)
    half = stats.t.ppf(0.975, df) * se
    return diff / se, df, 2 * stats.t.sf(abs(diff / se), df), diff - half, diff + half


def test_ttest2_closed_form():
    # x = [1, 2, 3], y = [2, 4, 7]: s_x² = 1, s_y² = 19/3, pooled 11/3, se = √22 / 3, t = −7/√22.
    result = ttest2([1, 2, 3], [2, 4, 7])
    assert result.t == pytest.approx(-7 / math.sqrt(22))
    assert result.df == 4
    assert (result.mean_x, result.mean_y) == pytest.approx((2, 13 / 3))
    assert result.p == pytest.approx(2 * stats.t.sf(7 / math.sqrt(22), 4))


@given(x=samples, y=samples)
def test_ttest2_matches_pooled_formula(x, y):
    if np.ptp(x) == 0 and np.ptp(y) == 0:
        with pytest.raises(ValueError, match="standard error is 0"):
            ttest2(x, y)
        return
    r = ttest2(x, y)
    assert (r.t, r.df, r.p, r.ci_low, r.ci_high) == pytest.approx(pooled_by_hand(x, y), rel=1e-9, abs=1e-12)
    assert r.ci_low <= r.mean_x - r.mean_y <= r.ci_high
    assert (r.p < 0.05) == (r.ci_low > 0 or r.ci_high < 0)  # the 95 % CI excludes 0 iff p < 0.05
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scipy warns on a constant sample; the numbers stand
        ref = stats.ttest_ind(x, y)
    ci = ref.confidence_interval()
    assert (r.t, r.df, r.p, r.ci_low, r.ci_high) == pytest.approx((ref.statistic, ref.df, ref.pvalue, ci.low, ci.high),
                                                                  rel=1e-9, abs=1e-12)


def test_welch_matches_satterthwaite_by_hand():
    x, y = np.array([69.0, 75, 81, 62, 90, 71]), np.array([84.0, 88, 79, 95, 83, 90, 86, 81])
    vx, vy = np.var(x, ddof=1) / len(x), np.var(y, ddof=1) / len(y)
    df = (vx + vy) ** 2 / (vx**2 / (len(x) - 1) + vy**2 / (len(y) - 1))
    t = (x.mean() - y.mean()) / math.sqrt(vx + vy)
    r = ttest2(x, y, equal_var=False)
    assert (r.t, r.df, r.p) == pytest.approx((t, df, 2 * stats.t.sf(abs(t), df)))
    assert r.p == pytest.approx(stats.ttest_ind(x, y, equal_var=False).pvalue)
    assert r.ci_high - r.ci_low == pytest.approx(2 * stats.t.ppf(0.975, df) * math.sqrt(vx + vy))


def test_paired_ttest_is_a_one_sample_test_of_differences():
    pre, post = np.array([60.0, 65, 70, 58, 72, 66]), np.array([68.0, 70, 71, 66, 80, 65])
    d = pre - post
    se = np.std(d, ddof=1) / math.sqrt(len(d))
    r = paired_ttest(pre, post)
    assert (r.t, r.df) == pytest.approx((d.mean() / se, len(d) - 1))
    assert r.p == pytest.approx(stats.ttest_1samp(d, 0).pvalue) == pytest.approx(stats.ttest_rel(pre, post).pvalue)
    assert (r.ci_low + r.ci_high) / 2 == pytest.approx(d.mean())


@pytest.mark.parametrize(("call", "message"), [
    (lambda: ttest2([1, 1], [2, 2]), "standard error is 0"),
    (lambda: ttest2([0.1, 0.1, 0.1], [0.1, 0.1], equal_var=False), "standard error is 0"),
    (lambda: ttest2([1], [2]), "n_x \\+ n_y ≥ 3"),
    (lambda: ttest2([1], [2, 3, 4], equal_var=False), "at least 2"),
    (lambda: ttest2([1, np.nan], [2, 3]), "NaN"),
    (lambda: ttest2([[1, 2]], [2, 3]), "one-dimensional"),
    (lambda: ttest2([1, 2], [2, 3], confidence=95), "confidence"),
    (lambda: paired_ttest([1, 2, 3], [2, 3, 4]), "standard error is 0"),
    (lambda: paired_ttest([1, 2, 3], [2, 3]), "same length"),
])
def test_undefined_tests_raise_with_a_reason(call, message):
    with pytest.raises(ValueError, match=message):
        call()


# --- logistic fit -------------------------------------------------------------------------

def test_logistic_fit_recovers_the_paper_curve():
    fit = fit_logistic(ANSWERS, logistic(ANSWERS, *PAPER_LOGISTIC))
    assert (fit.L, fit.k, fit.r0) == pytest.approx(PAPER_LOGISTIC, rel=1e-6)
    assert fit.sse < 1e-20 and fit.n == len(ANSWERS)
    assert fit(ANSWERS) == pytest.approx(logistic(ANSWERS, *PAPER_LOGISTIC))


def test_logistic_rmse_uses_residual_degrees_of_freedom():
    noise = np.random.default_rng(5).normal(0, 0.05, ANSWERS.size)
    fit = fit_logistic(ANSWERS, logistic(ANSWERS, *PAPER_LOGISTIC) + noise)
    assert fit.sse == pytest.approx(np.sum((fit(ANSWERS) - logistic(ANSWERS, *PAPER_LOGISTIC) - noise) ** 2))
    assert fit.rmse == pytest.approx(math.sqrt(fit.sse / (ANSWERS.size - 3)))  # MATLAB: dfe = n − 3
    assert fit.L == pytest.approx(defaults.PAPER_LOGISTIC_L, abs=0.15)


def test_logistic_fit_with_three_points_has_no_rmse():
    fit = fit_logistic([3, 6, 9], logistic(np.array([3.0, 6, 9]), *PAPER_LOGISTIC))
    assert fit.sse == pytest.approx(0, abs=1e-12) and math.isnan(fit.rmse)


@pytest.mark.parametrize(("r", "y"), [([3, 3, 4, 4], [0.2, 0.3, 0.5, 0.6]), ([5], [0.5]), ([], [])])
def test_logistic_fit_needs_three_distinct_points(r, y):
    with pytest.raises(ValueError, match="at least"):
        fit_logistic(r, y)


@pytest.mark.parametrize("y", [np.full(8, 0.7), np.zeros(8), np.r_[np.zeros(4), np.ones(4)], -ANSWERS])
def test_logistic_fit_survives_degenerate_data(y):
    fit = fit_logistic(ANSWERS, y)
    assert all(map(math.isfinite, (fit.L, fit.k, fit.r0, fit.sse, fit.rmse)))


@settings(max_examples=20, deadline=None)
@given(y=st.lists(st.floats(-2, 2), min_size=8, max_size=8))
def test_logistic_fit_never_crashes(y):
    fit = fit_logistic(ANSWERS, y)
    assert math.isfinite(fit.sse) and fit.L >= 0


def test_median_by_answer():
    levels, medians = median_by_answer([7, 3, 7, 7, 3, 10], [0.9, 0.2, 0.5, 0.7, 0.4, 0.95])
    assert levels.tolist() == [3, 7, 10]
    assert medians == pytest.approx([0.3, 0.7, 0.95])
    with pytest.raises(ValueError, match="same length"):
        median_by_answer([1, 2], [0.5])


# --- linear fit -------------------------------------------------------------------------------

def test_linear_fit_recovers_the_paper_line():
    slope, intercept = defaults.PAPER_RELIANCE_SLOPE, defaults.PAPER_RELIANCE_INTERCEPT
    fit = fit_linear(ANSWERS, slope * ANSWERS + intercept)
    assert (fit.slope, fit.intercept, fit.r2, fit.n) == pytest.approx((slope, intercept, 1.0, ANSWERS.size))
    assert fit.slope_ci == pytest.approx((slope, slope)) and fit.intercept_ci == pytest.approx((intercept, intercept))


def test_linear_fit_matches_scipy_with_noise():
    rng = np.random.default_rng(6)
    x = rng.integers(3, 11, 60).astype(float)
    y = defaults.PAPER_RELIANCE_SLOPE * x + defaults.PAPER_RELIANCE_INTERCEPT + rng.normal(0, 1, x.size)
    fit, ref = fit_linear(x, y), stats.linregress(x, y)
    half = stats.t.ppf(0.975, x.size - 2)
    assert (fit.slope, fit.intercept, fit.r2) == pytest.approx((ref.slope, ref.intercept, ref.rvalue**2))
    assert fit.slope_ci == pytest.approx((ref.slope - half * ref.stderr, ref.slope + half * ref.stderr))
    assert fit.intercept_ci == pytest.approx((ref.intercept - half * ref.intercept_stderr,
                                              ref.intercept + half * ref.intercept_stderr))
    assert fit.slope_ci[0] < defaults.PAPER_RELIANCE_SLOPE < fit.slope_ci[1]


def test_linear_fit_degenerate_inputs():
    with pytest.raises(ValueError, match="x is constant"):
        fit_linear([2, 2, 2], [1, 2, 3])
    with pytest.raises(ValueError, match="at least 3"):
        fit_linear([1, 2], [1, 2])
    assert math.isnan(fit_linear([1, 2, 3], [4, 4, 4]).r2)
