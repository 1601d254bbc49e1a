"""Summaries over Monte Carlo runs: means with 95% t-intervals and paired comparisons."""

from __future__ import annotations

import csv

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


def summarise(results: list[dict], rows, columns) -> dict:
    """{row: {column: mean_ci over runs}} for per-run results[i][row][column]."""
    return {row: {col: mean_ci([r[row][col] for r in results]) for col in columns}
            for row in rows}


def write_csv(path, summary: dict, columns, paper: dict, paper_columns) -> None:
    """One line per row: the mean, low and high of each column, then the paper's values."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["row"] + [f"{c}_{s}" for c in columns for s in ("mean", "low", "high")]
                   + list(paper_columns))
        for row, cols in summary.items():
            w.writerow([row] + [v for c in columns for v in cols[c]]
                       + list(paper.get(row, (None,) * len(paper_columns))))
