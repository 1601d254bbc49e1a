"""Summaries over Monte Carlo runs: means with 95% t-intervals and paired comparisons."""

from __future__ import annotations

import numpy as np
from scipy import stats


def mean_ci(values, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high): the mean of values (R,) and its Student-t interval (NaN-free;
    with one run the interval is the point)."""
    x = np.asarray(values, dtype=float)
    m = float(x.mean())
    if x.size < 2:
        return m, m, m
    half = stats.t.ppf(0.5 + level / 2, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size)
    return m, m - half, m + half


def paired(a, b, level: float = 0.95) -> dict:
    """Paired comparison of a against b over the same runs: mean of a - b with its
    interval, and the share of runs where a < b (a better, for an error)."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    m, lo, hi = mean_ci(d, level)
    return {"mean_diff": m, "low": lo, "high": hi, "share_better": float(np.mean(d < 0)),
            "runs": int(d.size)}


def fmt(mean: float, low: float, high: float, digits: int = 4) -> str:
    """'0.1234 [0.1200, 0.1268]'."""
    return f"{mean:.{digits}g} [{low:.{digits}g}, {high:.{digits}g}]"
