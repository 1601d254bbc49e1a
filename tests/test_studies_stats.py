"""Intervals of the study tables: a mean's bootstrap interval respects the support of a
non-negative quantity and is reproducible; a paired difference keeps a symmetric one."""

import numpy as np
import pytest
from scipy import stats as scipy_stats

from studies import stats


@pytest.mark.parametrize("seed", range(5))
def test_interval_of_a_non_negative_quantity_stays_non_negative_with_few_runs(seed):
    """Skewed MSE-like values over 3 runs: the Student-t interval goes below zero, the
    bootstrap percentile interval stays within the values' range."""
    x = np.random.default_rng(seed).lognormal(0.0, 1.5, 3)
    mean, low, high = stats.mean_ci(x)
    assert mean == pytest.approx(x.mean())
    tol = 1e-12 * x.max()  # the mean of equal values may differ from them by rounding
    assert x.min() - tol <= low <= mean <= high <= x.max() + tol


def test_the_example_of_the_issue_no_longer_goes_below_zero():
    x = [0.05, 0.10, 2.853]  # mean 1.001; the t interval is about [-2.6, 4.6]
    half = scipy_stats.t.ppf(0.975, 2) * np.std(x, ddof=1) / np.sqrt(3)
    assert np.mean(x) - half < 0
    assert stats.mean_ci(x)[1] >= 0.05


def test_interval_is_reproducible_and_covers_like_a_95_percent_interval():
    assert stats.mean_ci([1.0, 2.0, 4.0]) == stats.mean_ci([1.0, 2.0, 4.0])
    rng = np.random.default_rng(7)
    covered = [lo <= 1.0 <= hi for lo, hi in
               (stats.mean_ci(rng.exponential(1.0, 100))[1:] for _ in range(300))]
    assert 0.90 <= np.mean(covered) <= 0.98


def test_one_run_or_equal_values_give_the_point():
    assert stats.mean_ci([2.5]) == (2.5, 2.5, 2.5)
    assert stats.mean_ci([0.0, 0.0, 0.0]) == (0.0, 0.0, 0.0)


def test_paired_difference_keeps_a_symmetric_t_interval():
    a, b = np.array([1.0, 2.0, 3.5, 0.5]), np.array([1.5, 1.0, 3.0, 1.5])
    p = stats.paired(a, b)
    d = a - b
    half = scipy_stats.t.ppf(0.975, 3) * d.std(ddof=1) / 2
    assert p["mean_diff"] == pytest.approx(d.mean())
    assert (p["low"], p["high"]) == pytest.approx((d.mean() - half, d.mean() + half))
    assert p["share_better"] == 0.5 and p["runs"] == 4


def test_a_value_some_runs_do_not_define_is_summarised_over_the_others(tmp_path):
    """Fuzz F6: the ANEES of a node that matched no target is NaN in that run, and the
    network study's tables showed 'nan [nan, nan]'. The mean and interval are taken over
    the runs that define it; none: '-' in a table, an empty cell in a CSV."""
    assert stats.mean_ci([1.0, np.nan, 3.0]) == stats.mean_ci([1.0, 3.0])
    assert stats.fmt(*stats.mean_ci([np.nan, np.nan])) == "-"
    stats.write_rows(tmp_path / "t.csv", [{"a": np.nan, "b": 1.5}])
    assert (tmp_path / "t.csv").read_text().splitlines() == ["a,b", ",1.5"]
