"""Detection scales of the modified batch CI (MBCI, the paper's Theorem and Lemma).

Node i detects with probability p_i; over a missed detection its covariance grows by the
paper's factor chi_i^-1 >= 1 (`growth`; `chi` in (0, 1] is its inverse: give one of the
two). The expected information of the paper's mixed game scales each Y_i by

    s_i = p_i + (1 - p_i) chi_i prod_{j != i} t_j,   t_j = p_j + (1 - p_j) chi_j,   0 < s_i <= 1,

and MBCI is CI/BCI on Yhat_i = s_i Y_i (Phat_i = P_i / s_i >= P_i, so it stays consistent).
The core applies the scales to the covariances as s_i = q_i 2^E_i (q_i in [1, 2), E_i an
integer; `detection_split`), so that chi = 1 gives s = 1 exactly (p + (1 - p) is 1.0 in
floating point for every p) and MBCI equals BCI bit for bit. Where the product underflows
(p = 0, chi = 1e-200, N = 3 gives 1e-600) the split comes from log2 s instead.
"""

from __future__ import annotations

import numbers

import numpy as np

from .results import FusionInputError
from .validation import check_detection, finite_array

_LOG2E = 1.0 / np.log(2.0)


def detection_scales(p_detect, chi=None, n_nodes: int | None = None, *,
                     growth=None) -> np.ndarray:
    """MBCI's detection scales s (..., N), by which each node's information is multiplied:

        s_i = p_i + (1 - p_i) chi_i prod_{j != i} (p_j + (1 - p_j) chi_j),   0 < s_i <= 1,

    for p_detect in [0, 1] and exactly one of chi in (0, 1] or growth = 1 / chi >= 1 (the
    paper's chi^-1), each a scalar, (N,) or (..., N); n_nodes gives N when both are
    scalars. Refused when a scale underflows float64 (fo.mbci itself fuses such nodes).
    """
    q, E = detection_split(p_detect, chi, n_nodes, growth=growth)
    if (E < -1022).any():
        raise FusionInputError(
            f"detection scales underflow float64 (smallest 2^{E.min()}); fo.mbci fuses "
            "such nodes exactly")
    return np.ldexp(q, E)


def detection_split(p_detect, chi=None, n_nodes: int | None = None, *, growth=None):
    """(q, E), each (..., N), with s = q 2^E exactly, q in [1, 2), E int64, for p_detect and
    chi (or growth = 1 / chi), each a scalar, (N,) or (..., N) with leading batch axes;
    n_nodes fixes N when both are scalars (default 1)."""
    p, c = _checked(p_detect, chi, n_nodes, growth)
    t = p + (1.0 - p) * c  # each node's expected factor, > 0 since chi > 0
    # Product over j != i without dividing by t_i: exclusive prefix times exclusive suffix.
    ones = np.ones((*t.shape[:-1], 1))
    before = np.cumprod(np.concatenate((ones, t[..., :-1]), axis=-1), axis=-1)
    after = np.cumprod(np.concatenate((ones, t[..., :0:-1]), axis=-1), axis=-1)[..., ::-1]
    s = p + (1.0 - p) * c * before * after
    mant, ex = np.frexp(s)
    q, E = 2.0 * mant, ex.astype(np.int64) - 1
    low = s < 2.0**-1000  # the product may have underflowed: take the split from logs
    if low.any():
        log2_s = _log2_scales(p, c)
        E_log = np.floor(log2_s).astype(np.int64)
        q = np.where(low, np.exp2(log2_s - E_log), q)
        E = np.where(low, E_log, E)
    return q, E


def _checked(p_detect, chi, n_nodes, growth) -> tuple[np.ndarray, np.ndarray]:
    """(p, chi) checked and broadcast to (..., N)."""
    chi = _chi(chi, growth)
    if n_nodes is None:
        shapes = [np.shape(x) for x in (p_detect, chi) if np.ndim(x)]
        n_nodes = shapes[0][-1] if shapes else 1
    n_nodes = _node_count(n_nodes)
    return check_detection(p_detect, chi, n_nodes, "growth" if growth is not None else "chi")


def _log2_scales(p, c) -> np.ndarray:
    """log2 s (..., N) for checked p and chi (..., N), from logs: no product underflows."""
    with np.errstate(divide="ignore"):  # log(0) = -inf for p = 0 or 1 - p = 0: exact
        log_p, log_q, log_c = np.log(p), np.log1p(-p), np.log(c)
        log_t = np.logaddexp(log_p, log_q + log_c)
        others = log_t.sum(-1, keepdims=True) - log_t  # sum over j != i
        return np.logaddexp(log_p, log_q + log_c + others) * _LOG2E


def _chi(chi, growth):
    """chi from exactly one of chi and growth (the paper's chi^-1 >= 1)."""
    if (chi is None) == (growth is None):
        raise FusionInputError("give exactly one of chi (in (0, 1]) and growth (the paper's "
                               "chi^-1 >= 1)")
    if chi is not None:
        return chi
    g = finite_array(growth, "growth")
    bad = ~(g >= 1.0)
    if bad.any():
        raise FusionInputError(f"growth must be >= 1 (the covariance grows over a miss), got "
                               f"{g[bad].ravel()[0]}")
    return 1.0 / g


def _node_count(n_nodes) -> int:
    if isinstance(n_nodes, bool) or not isinstance(n_nodes, numbers.Integral) or n_nodes < 1:
        raise FusionInputError(f"n_nodes must be an integer >= 1, got {n_nodes!r}")
    if n_nodes > 10**7:
        raise FusionInputError(f"n_nodes = {n_nodes} is more nodes than a fusion can hold")
    return int(n_nodes)
