"""Detection scales of the modified batch CI (MBCI, the paper's Theorem and Lemma).

Node i detects with probability p_i; over a missed detection its covariance grows by the
paper's factor chi_i^-1 >= 1 (`growth`; `chi` in (0, 1] is its inverse: give one of the
two). The expected information of the paper's mixed game scales each Y_i by

    s_i = p_i + (1 - p_i) chi_i prod_{j != i} t_j,   t_j = p_j + (1 - p_j) chi_j,   0 < s_i <= 1,

and MBCI is CI/BCI on Yhat_i = s_i Y_i (Phat_i = P_i / s_i >= P_i, so it stays consistent).
The core applies the scales to the covariances as s_i = q_i 2^E_i (q_i in [1, 2), E_i an
integer; `detection_split`), so that chi = 1 gives s = 1 exactly (p + (1 - p) is 1.0 in
floating point for every p) and MBCI equals BCI bit for bit; s is 1 only where it is
exactly 1 (an inexact scale that rounds to 1 is the double below). Where the product underflows
(p = 0, chi = 1e-200, N = 3 gives 1e-600) the split comes from log2 s instead.
"""

from __future__ import annotations

import math

import numpy as np

from .limits import fits
from .linalg import jit
from .results import FusionInputError
from .validation import check_detection, finite_array, is_integer, real_array, safe_repr

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


def detection_split(p_detect, chi=None, n_nodes: int | None = None, *, growth=None,
                    leads=None):
    """(q, E), each (..., N), with s = q 2^E exactly, q in [1, 2), E int64, for p_detect and
    chi (or growth = 1 / chi), each a scalar, (N,) or (..., N) with leading batch axes;
    n_nodes fixes N when both are scalars (default 1). leads: the leading shapes the caller
    takes (a tuple of tuples; None: any), any other refused before an array is made (fuzz
    M2: p_detect of 3e7 rows for one problem took 1.4 GB before its refusal).

    The scales are computed and checked by one compiled call (`_split`): through numpy's
    small-array calls they took 44 us at N = 3, twice a whole fusion. Wrong shapes and
    values are worded by `_checked`, which refuses what `_split` refused."""
    name, value = ("chi", chi) if growth is None else ("growth", growth)
    p = real_array(p_detect, "p_detect")
    v = real_array(value, name) if (chi is None) != (growth is None) else None
    N, lead = _layout(p, (name, v), n_nodes)
    if lead is None:
        _refuse(p_detect, chi, n_nodes, growth)
    if leads is not None and lead not in leads:
        want = ["a scalar", f"({N},)", *(str((*shape, N)) for shape in leads if shape)]
        want = f"{', '.join(want[:-1])} or {want[-1]}"
        raise FusionInputError(f"p_detect and {name} must be {want}, got {(*lead, N)}")
    # q, E and the compiled call's copies of p and v: 4 numbers a scale (fuzz M2: a
    # (1e5, 1e4) view of p_detect ran out of memory in detection_scales)
    fits(f"p_detect and {name} of shape {(*lead, N)}", 32.0 * math.prod(lead) * N)
    q, E = np.empty((*lead, N)), np.empty((*lead, N), dtype=np.int64)
    code = _split(_rows(p, lead, N), _rows(v, lead, N), name == "growth", q.reshape(-1, N),
                  E.reshape(-1, N))
    if code == _BAD:
        _refuse(p_detect, chi, n_nodes, growth)
    if code == _LOW:  # a product may have underflowed: take those splits from logs, in
        fits(f"p_detect and {name} of shape {(*lead, N)}, a scale below 2^-1000 among them",
             112.0 * math.prod(lead) * N)  # about 14 numbers a scale (fuzz O1: 2.3x a
        p, c = _checked(p_detect, chi, n_nodes, growth)  # limit that counted 4 passed)
        low = np.ldexp(q, E) < 2.0**-1000
        log2_s = _log2_scales(p, c)
        E_log = np.floor(log2_s).astype(np.int64)
        q, E = np.where(low, np.exp2(log2_s - E_log), q), np.where(low, E_log, E)
    return q, E


def _layout(p, named_v, n_nodes) -> tuple[int, tuple | None]:
    """(N, the leading shape of the broadcast) of p and v, named_v = (its name, v), each a
    scalar or (..., N); lead None when chi or growth is missing, N or a shape is wrong, or
    they do not broadcast (`_checked` says which)."""
    v = named_v[1]
    if n_nodes is None:
        n_nodes = _inferred(("p_detect", p), named_v)
    N = _node_count(n_nodes)
    if v is None or any(x.ndim and x.shape[-1] != N for x in (p, v)):
        return N, None
    a, b = p.shape[:-1], v.shape[:-1]
    if a == b or not b:
        return N, a
    if not a:
        return N, b
    try:
        return N, np.broadcast_shapes(a, b)
    except ValueError:
        return N, None


def _rows(x, lead: tuple, N: int) -> np.ndarray:
    """x, a scalar or (..., N) that broadcasts to (*lead, N), as a C-contiguous writable
    (R, C) array that `_split` broadcasts: R 1 or prod(lead), C 1 or N."""
    if x.ndim == 0:
        return np.full((1, 1), x)
    if x.ndim == 1:
        return x.reshape(1, N).copy()
    if x.shape[:-1] != lead:
        x = np.broadcast_to(x, (*lead, N))
    return x.reshape(-1, N).copy()


def _refuse(p_detect, chi, n_nodes, growth):
    """Raises `_checked`'s error for inputs `_split` or `_layout` refused."""
    _checked(p_detect, chi, n_nodes, growth)
    raise FusionInputError(f"p_detect {safe_repr(p_detect)} with chi {safe_repr(chi)} or growth "
                           f"{safe_repr(growth)} "
                           "cannot give detection scales")  # a guard: _checked refuses them


_BAD, _LOW = 1, 2
_BELOW_ONE = 1.0 - 2.0**-53  # the double below 1


@jit
def _split(p, v, growth: bool, q, E) -> int:
    """q, E (R, N): s = q 2^E (module docstring) for p (Rp, Cp) and v (Rv, Cv), chi or, when
    growth, its inverse, each broadcast (Rp, Rv in {1, R}; Cp, Cv in {1, N}). Returns _BAD
    for a p outside [0, 1] or a chi outside (0, 1] (growth below 1 or not finite), _LOW
    when a scale is below 2^-1000 (its product may have underflowed), else 0. The products
    over j != i are exclusive prefix times exclusive suffix (no division by t_i), in
    numpy's order of operations before this was compiled, so the scales are unchanged. A
    scale below 1 that rounds to 1 (p or chi within about 1e-16 of 1) is the double below
    1 instead, so that s = 1 (q = 1, E = 0) means an exact 1, which the certificate takes
    as exact (`assemble._scale_error`; fuzz of stop 35: rounded to 1.0, the gap at a
    vertex understated the exact certificate by up to 3e-16)."""
    R, N = q.shape
    pr, c, t, after = np.empty(N), np.empty(N), np.empty(N), np.empty(N)
    code = 0
    for r in range(R):
        for i in range(N):
            pr[i] = p[min(r, p.shape[0] - 1), min(i, p.shape[1] - 1)]
            vi = v[min(r, v.shape[0] - 1), min(i, v.shape[1] - 1)]
            if growth and not 1.0 <= vi < np.inf:
                return _BAD
            c[i] = 1.0 / vi if growth else vi
            if not (0.0 <= pr[i] <= 1.0 and 0.0 < c[i] <= 1.0):
                return _BAD
            t[i] = pr[i] + (1.0 - pr[i]) * c[i]  # each node's expected factor, > 0
        after[N - 1] = 1.0
        for i in range(N - 2, -1, -1):
            after[i] = after[i + 1] * t[i + 1]
        before = 1.0
        for i in range(N):
            s = pr[i] + (1.0 - pr[i]) * c[i] * before * after[i]
            before *= t[i]
            if s == 1.0 and not _exactly_one(pr, c, i):
                s = _BELOW_ONE
            if s < 2.0**-1000:
                code = _LOW
            mant, ex = math.frexp(s)
            q[r, i], E[r, i] = 2.0 * mant, ex - 1
    return code


@jit
def _exactly_one(p, c, i: int) -> bool:
    """Whether s_i = p_i + (1 - p_i) chi_i prod_{j != i} t_j is exactly 1 for the float p
    and chi (N,): p_i = 1, or chi_i = 1 and every other t_j = p_j + (1 - p_j) chi_j is 1
    (p_j = 1 or chi_j = 1). chi = 1 / growth is 1 only for growth = 1, where the rounded
    c is 1 too: 1 / (1 + 2^-52) rounds to 1 - 2^-52."""
    if p[i] == 1.0:
        return True
    if c[i] != 1.0:
        return False
    for j in range(p.size):
        if j != i and p[j] != 1.0 and c[j] != 1.0:
            return False
    return True


def _checked(p_detect, chi, n_nodes, growth) -> tuple[np.ndarray, np.ndarray]:
    """(p, chi) checked and broadcast to (..., N)."""
    chi = _chi(chi, growth)
    if n_nodes is None:
        n_nodes = _inferred(("p_detect", p_detect), ("chi" if growth is None else "growth",
                                                     chi))
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


def _inferred(*named) -> int:
    """N from the last axis of the first (name, value) that is not a scalar (1 if none
    is), refusing an empty one by its name (it was blamed on n_nodes, which the caller had
    not given: fuzz I8)."""
    for name, x in named:
        if x is not None and np.ndim(x):
            if np.shape(x)[-1] == 0:
                raise FusionInputError(f"{name} must hold one value per node, got shape "
                                       f"{np.shape(x)} (no node)")
            return np.shape(x)[-1]
    return 1


def _node_count(n_nodes) -> int:
    if not is_integer(n_nodes) or n_nodes < 1:
        raise FusionInputError(f"n_nodes must be an integer >= 1, got {safe_repr(n_nodes)}")
    if n_nodes > 10**7:
        raise FusionInputError(f"n_nodes = {safe_repr(n_nodes)} is more nodes than a fusion "
                               "can hold")
    return int(n_nodes)
