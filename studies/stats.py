"""Summaries over Monte Carlo runs: means with 95% intervals and paired comparisons.

A mean's interval is the bootstrap percentile interval: the 2.5% and 97.5% quantiles of
the means of B = 2000 resamples (with replacement) of the runs, drawn from a fixed seed.
It lies within the range of the runs' values, so the interval of a non-negative quantity
(MSE, MNCM, OSPA, ...) never goes below zero, as a Student-t interval does with few runs.
A paired difference (a - b over the same runs) keeps the symmetric Student-t interval:
its sign is the question, and it has no bounded support.
"""

from __future__ import annotations

import csv
from functools import lru_cache

import numpy as np
from scipy import stats

RESAMPLES = 2000
INTERVAL_NOTE = (f"95% intervals: bootstrap percentile over the runs ({RESAMPLES} seeded "
                 "resamples), paired differences: Student t.")


@lru_cache(maxsize=16)
def _resamples(runs: int) -> np.ndarray:
    """Indices (RESAMPLES, runs) of the bootstrap resamples of `runs` runs (seeded, so
    every table gives the same interval for the same values)."""
    return np.random.default_rng(runs).integers(0, runs, (RESAMPLES, runs))


def mean_ci(values, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high): the mean of values (R,) and its bootstrap percentile interval
    (with one run, or all values equal, the interval is the point), over the runs that
    define the value (NaN: not defined in that run, as the ANEES of a node that matched no
    target); NaN for all three when no run defines it (`fmt` writes "-")."""
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    if x.size == 0:
        return np.nan, np.nan, np.nan
    m = float(x.mean())
    if x.size < 2:
        return m, m, m
    means = x[_resamples(x.size)].mean(axis=1)
    low, high = np.quantile(means, [0.5 - level / 2, 0.5 + level / 2])
    return m, float(low), float(high)


def paired(a, b, level: float = 0.95) -> dict:
    """Paired comparison of a against b over the same runs: mean of a - b with its
    Student-t interval, and the share of runs where a < b (a better, for an error), over
    the runs that define both (`mean_ci`); NaN (written "-") if none does."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d = d[~np.isnan(d)]
    if d.size == 0:
        return {"mean_diff": np.nan, "low": np.nan, "high": np.nan, "share_better": np.nan,
                "runs": 0}
    m = float(d.mean())
    half = 0.0
    if d.size >= 2:
        half = stats.t.ppf(0.5 + level / 2, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size)
    return {"mean_diff": m, "low": m - half, "high": m + half,
            "share_better": float(np.mean(d < 0)), "runs": int(d.size)}


def fmt(mean: float, low: float, high: float, digits: int = 4) -> str:
    """'0.1234 [0.1200, 0.1268]'; '-' for a value no run defines."""
    if np.isnan(mean):
        return "-"
    return f"{mean:.{digits}g} [{low:.{digits}g}, {high:.{digits}g}]"


def fmt_share(d: dict) -> str:
    """The share of runs where a paired rule is lower (`paired`), '0.55'; '-' when no run
    defines the difference."""
    return "-" if np.isnan(d["share_better"]) else f"{d['share_better']:.2f}"


def summarise(results: list[dict], rows, columns) -> dict:
    """{row: {column: mean_ci over runs}} for per-run results[i][row][column]."""
    return {row: {col: mean_ci([r[row][col] for r in results]) for col in columns}
            for row in rows}


def write_csv(path, summary: dict, columns, paper: dict, paper_columns) -> None:
    """One line per row: the mean, low and high of each column, then the paper's values."""
    write_rows(path, [{"row": row, **{f"{c}_{s}": v for c in columns
                                      for s, v in zip(("mean", "low", "high"), cols[c],
                                                      strict=True)},
                       **dict(zip(paper_columns, paper.get(row, (None,) * len(paper_columns)),
                                  strict=True))}
                      for row, cols in summary.items()])


def blank_nan(row: dict) -> dict:
    """row for a CSV: a value no run defines or that does not apply (NaN) as an empty
    cell."""
    return {k: "" if isinstance(v, float) and np.isnan(v) else v for k, v in row.items()}


def write_rows(path, rows: list[dict]) -> None:
    """A CSV of rows (dicts with the same keys, in the first row's order), NaN as an
    empty cell (`blank_nan`)."""
    rows = [blank_nan(r) for r in rows]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else [])
        w.writeheader()
        w.writerows(rows)
