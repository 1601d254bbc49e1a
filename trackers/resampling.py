"""Log-weight normalisation, effective sample size and systematic resampling.

Weights are kept as logs and normalised with log-sum-exp: w_i = exp(l_i - logsumexp(l)).
The effective sample size is ESS = 1 / sum_i w_i^2 (between 1 and N).
Systematic resampling draws one uniform u ~ U[0, 1/N) and takes the particles whose
cumulative weight intervals contain u + j/N, j = 0..N-1 (low variance, O(N)).

``end_of_step`` is the tail every particle filter step here shares: normalise, ESS, and
resample when ESS < threshold (then the log-weights restart at -log N).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fusion_opt import FusionInputError
from fusion_opt.validation import is_real, real_array, safe_repr
from trackers import _checks


def logsumexp(a: np.ndarray, axis: int | None = None) -> np.ndarray:
    """log(sum(exp(a))) along ``axis``, stable for large |a| and exact for -inf entries;
    as scipy.special.logsumexp: -inf over no entries (an empty sum is 0), inf where an entry
    is inf, NaN where one is (the filters check their weights after each step).

    A plain-numpy version: scipy.special.logsumexp's generic array handling costs more than
    the arithmetic for the small arrays of a particle filter step (measured 60% of the
    RBPF's run time).
    """
    a = np.asarray(a, dtype=float)
    _checks.fits(f"a of shape {a.shape}", 3 * 8.0 * a.size)  # a - peak, its exp, the sum
    if a.size == 0:  # numpy's max of nothing raised a bare ValueError (fuzz N12)
        return np.full(np.sum(a, axis=axis).shape, -np.inf)[()]
    peak = a.max(axis=axis, keepdims=True)
    peak[~np.isfinite(peak)] = 0.0  # all -inf: the result is -inf
    with np.errstate(divide="ignore", over="ignore"):  # a - peak = -inf: a term of 0
        out = np.log(np.exp(a - peak).sum(axis=axis, keepdims=True)) + peak
    return out.reshape(()) if axis is None else out.squeeze(axis=axis)


def normalize_log_weights(logw: np.ndarray) -> np.ndarray:
    """Shift log-weights (N,), at least one finite, so that sum(exp(logw)) = 1.

    The peak is taken out first: l - logsumexp(l) would lose log N to rounding when every
    l_i shares an offset of 1e16 or more (a measurement far from every particle).
    Refuses an empty array, NaN, +inf, and all -inf (weights that are all 0).
    """
    logw = real_array(logw, "logw")
    if logw.ndim != 1 or logw.size == 0:
        raise FusionInputError(f"logw must be a non-empty (N,) array, got shape {logw.shape}")
    # before any temporary: a broadcast view of 10^9 weights costs 8 bytes to hold, and the
    # normalisation and resampling make about six (N,) arrays of it
    _checks.fits(f"logw of {logw.size} weights", 6 * 8.0 * logw.size)
    peak = logw.max()  # NaN if any is NaN
    if not np.isfinite(peak):
        raise FusionInputError(f"logw must be finite or -inf with at least one finite "
                               f"(no NaN, no +inf, not all weights 0), got max {peak}")
    with np.errstate(over="ignore"):  # -1e308 - 1e308 = -inf: a weight that is 0 next to
        shifted = logw - peak        # the peak's, as exp gives it
    return shifted - np.log(np.exp(shifted).sum())


def effective_sample_size(logw: np.ndarray) -> float:
    """ESS = 1 / sum w_i^2 for normalised weights w = softmax(logw)."""
    w = np.exp(normalize_log_weights(logw))
    return float(1.0 / (w @ w))


def systematic_resample(logw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices (N,) of the ancestors chosen by systematic resampling."""
    return _systematic(np.exp(normalize_log_weights(logw)), _checks.generator("rng", rng))


def _systematic(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling of normalised weights w (N,): ancestor indices (N,)."""
    N = w.shape[0]
    cdf = np.cumsum(w)
    cdf[-1] = 1.0  # guard against rounding leaving the last interval short of 1
    positions = (rng.random() + np.arange(N)) / N
    return np.searchsorted(cdf, positions, side="right")


class StepEnd(NamedTuple):
    """The end of a particle filter step.

    weights (N,): normalised weights after the step's updates (what its estimate uses);
    ess: 1 / sum weights^2; ancestors (N,) int, the resampled particles' indices, or None
    when the particles were not resampled; logw (N,): the log-weights to carry into the next
    step (log(weights), or -log N after resampling).
    """

    weights: np.ndarray
    ess: float
    ancestors: np.ndarray | None
    logw: np.ndarray


def end_of_step(logw: np.ndarray, threshold: float, rng: np.random.Generator) -> StepEnd:
    """Normalise log-weights (N,), compute the ESS and resample systematically if
    ESS < threshold (an absolute particle count). Draws from ``rng`` only when resampling."""
    if not is_real(threshold) or not threshold >= 0.0:  # also NaN
        raise FusionInputError(f"threshold must be a particle count >= 0, got "
                               f"{safe_repr(threshold)}")
    logw = normalize_log_weights(logw)
    w = np.exp(logw)
    ess = float(1.0 / (w @ w))
    if ess >= threshold:
        return StepEnd(w, ess, None, logw)
    N = w.shape[0]
    return StepEnd(w, ess, _systematic(w, _checks.generator("rng", rng)),
                   np.full(N, -np.log(N)))
