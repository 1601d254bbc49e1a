"""Estimation-error metrics for single- and multi-target tracking.

Single target, over T steps with estimates m_k, covariances P_k and truth x_k:

    MSE   = (1/T) sum_k ||m_k - x_k||^2         (the paper's MSE: sum over the components
                                                 given, mean over time)
    RMSE  = sqrt(MSE)
    MNCM  = (1/T) sum_k ||P_k||_2               (mean spectral norm of the covariance)
    NEES_k = (m_k - x_k)^T P_k^-1 (m_k - x_k),   ANEES = mean of NEES over the samples.

For a consistent filter NEES_k ~ chi2(n); the mean of M such independent values lies in
[chi2.ppf(0.025, M n) / M, chi2.ppf(0.975, M n) / M] with probability 0.95.

Multi-target, for point sets X (m, d) and Y (k, d), with d_c(x, y) = min(c, ||x - y||):

    OSPA (Schuhmacher et al. 2008), m <= k:
        ( (1/k) (min_pi sum_{i<=m} d_c(x_i, y_pi(i))^p + c^p (k - m)) )^(1/p)
    GOSPA (Rahmathullah et al. 2017), m <= k:
        ( min_pi sum_{i<=m} d_c(x_i, y_pi(i))^p + (c^p / alpha) (k - m) )^(1/p)
    (with alpha = 2 this is the assignment distance with a cost c^p / 2 per missed or false
    target). The optimal assignment uses scipy.optimize.linear_sum_assignment.

Track identity: `match` pairs estimates with targets (the optimal assignment on d_c, which
is OSPA's of order 1; pairs closer than c) and `id_switches` counts, per target, how often
the id matched to it changes. `set_errors` gives OSPA, GOSPA and the match of one step at
once.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from fusion_opt import FusionInputError
from fusion_opt.linalg import row_norms
from fusion_opt.validation import cholesky_ok, is_sequence, safe_repr, symmetrised
from trackers import _checks


def _indices(components, n: int) -> np.ndarray:
    """``components`` as integer state indices in [0, n)."""
    a = np.asarray(None if isinstance(components, str | bytes) else components)
    if a.dtype.kind not in "iu" or a.size == 0 or np.any(a < 0) or np.any(a >= n):
        raise FusionInputError(f"components must be integer indices in [0, {n}), got "
                               f"{safe_repr(components)}")
    a = a.reshape(-1)
    if np.unique(a).size != a.size:  # a repeated index would count its error twice
        raise FusionInputError(f"components must be distinct indices, got {safe_repr(components)}")
    return a


def _components(arr: np.ndarray, components) -> np.ndarray:
    if components is None:
        return arr
    return arr[..., _indices(components, arr.shape[-1])]


def _pair(estimates, truth):
    m = _checks.finite_array("estimates", estimates, ndim=2)
    x = _checks.finite_array("truth", truth, ndim=2)
    if m.shape != x.shape:
        raise FusionInputError(f"estimates {m.shape} and truth {x.shape} must have the same shape")
    if m.shape[1] == 0:
        raise FusionInputError(f"estimates must be (T, n) with n >= 1 state components, got "
                               f"{m.shape}")
    return m, x


def _errors(estimates, truth, components) -> np.ndarray:
    """The errors (T, k) of the components, T >= 1, refused if a difference overflows."""
    m, x = _pair(estimates, truth)
    if m.shape[0] == 0:
        raise FusionInputError("estimates and truth must hold at least one step, got none")
    with np.errstate(over="ignore"):
        e = _components(m - x, components)
    if not np.isfinite(e).all():
        raise FusionInputError("estimates - truth overflows float64")
    return e


def mse(estimates, truth, components=None) -> float:
    """Mean over time of the squared error norm. estimates, truth (T, n); ``components``
    selects distinct state indices (e.g. models.POSITION), default the full state. Refused if it
    overflows float64 (`rmse` does not)."""
    e = _errors(estimates, truth, components)
    with np.errstate(over="ignore"):
        value = float(np.mean(np.sum(e * e, axis=-1)))
    if not np.isfinite(value):
        raise FusionInputError(f"the MSE overflows float64 (errors up to {np.abs(e).max():.3g})")
    return value


def rmse(estimates, truth, components=None) -> float:
    """sqrt(mse): root mean (over time) squared error norm, computed on errors scaled by
    their largest (exactly, by a power of two) when their squares would leave float64;
    refused if the RMSE itself overflows (errors near 1e308 in several components)."""
    e = _errors(estimates, truth, components)
    top = np.abs(e).max()
    if 1e-150 < top < 1e150 or top == 0.0:
        return float(np.sqrt(np.mean(np.sum(e * e, axis=-1))))
    shift = int(np.frexp(top)[1])  # 2^shift itself is inf at top >= 2^1023 (fuzz U1)
    e = np.ldexp(e, -shift)
    with np.errstate(over="ignore"):
        value = float(np.ldexp(np.sqrt(np.mean(np.sum(e * e, axis=-1))), shift))
    if not np.isfinite(value):
        raise FusionInputError(f"the RMSE overflows float64 (errors up to {top:.3g})")
    return value


def _cov_block(covs, components):
    """The (T, k, k) blocks of symmetric positive semidefinite covariances (T, n, n)."""
    P = _checks.finite_array("covs", covs, ndim=3)
    if P.shape[1] != P.shape[2] or P.shape[1] == 0:
        raise FusionInputError(f"covs must be (T, n, n) with n >= 1, got {P.shape}")
    if components is not None:
        idx = _indices(components, P.shape[1])
        P = P[:, idx[:, None], idx[None, :]]
    top = np.abs(P).max(axis=(1, 2))
    asym = np.abs(P - P.swapaxes(1, 2)).max(axis=(1, 2)) > 1e-8 * top
    low = np.linalg.eigvalsh(symmetrised(P))[:, 0] < -1e-10 * top
    if asym.any() or low.any():
        k = int(np.flatnonzero(asym | low)[0])
        what = "symmetric" if asym[k] else "positive semidefinite"
        raise FusionInputError(f"covs[{k}] is not {what}")
    return P


def spectral_norms(covs, components=None) -> np.ndarray:
    """(T,) spectral norms ||P_k||_2 of covariances (T, n, n), in one batched call;
    ``components`` takes the block of those state indices (e.g. models.POSITION)."""
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(_cov_block(covs, components), ord=2, axis=(1, 2))
    if not np.isfinite(norms).all():  # fuzz N4: inf, and a NaN MNCM, at 1e308 entries
        k = int(np.flatnonzero(~np.isfinite(norms))[0])
        raise FusionInputError(f"the spectral norm of covs[{k}] overflows float64")
    return norms


def mncm(covs, components=None) -> float:
    """Mean over time of `spectral_norms`."""
    return _mean(spectral_norms(covs, components))


def _mean(values: np.ndarray) -> float:
    """The mean of finite values (T,) >= 0, T >= 1, taken over values scaled by their
    largest when their sum would overflow."""
    if values.size == 0:
        raise FusionInputError("a mean over no step is undefined: give at least one step")
    with np.errstate(over="ignore"):
        value = float(np.mean(values))
    if np.isfinite(value):
        return value
    top = values.max()
    return float(np.mean(values / top) * top)


def nees(estimates, truth, covs, components=None) -> np.ndarray:
    """(T,) normalised estimation error squared e_k^T P_k^-1 e_k."""
    m, x = _pair(estimates, truth)
    P = _cov_block(covs, components)
    if P.shape[0] != m.shape[0]:
        raise FusionInputError(f"covs has {P.shape[0]} steps, estimates {m.shape[0]}")
    e = _components(m - x, components)
    if e.shape[1] != P.shape[1]:
        raise FusionInputError(f"covs blocks are {P.shape[1:]}, errors have {e.shape[1]} "
                               "components")
    singular = ~cholesky_ok(P)
    if singular.any():
        raise FusionInputError(f"covs[{int(np.flatnonzero(singular)[0])}] is not positive "
                               "definite: its NEES is undefined")
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.einsum("ti,ti->t", e, np.linalg.solve(P, e[..., None])[..., 0])
    if not np.isfinite(out).all():
        raise FusionInputError(f"the NEES of step {int(np.flatnonzero(~np.isfinite(out))[0])} "
                               "overflows float64 (an error far beyond its covariance)")
    return out


def anees(estimates, truth, covs, components=None) -> float:
    """Mean NEES over the steps."""
    return _mean(nees(estimates, truth, covs, components))


def anees_bounds(dim: int, count: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` interval of the mean of ``count`` independent chi2(dim) values:
    chi2.ppf((1 -+ level) / 2, count dim) / count."""
    dim = _checks.positive_int("dim", dim)
    count = _checks.positive_int("count", count)
    level = _checks.probability("level", level)
    if not 0.0 < level < 1.0:  # 1 gives (0, inf), 0 an interval of width 0
        raise FusionInputError(f"level must lie strictly between 0 and 1, got {safe_repr(level)}")
    if count * dim >= 10**300:
        raise FusionInputError("count x dim must be below 1e300")
    df = float(count * dim)  # a Python int above 2^63 would reach scipy as an object
    a = (1.0 - level) / 2.0  # the upper tail by isf: 1 - a rounds to 1 below a = 2^-54,
    return float(chi2.ppf(a, df) / count), float(chi2.isf(a, df) / count)  # ppf's inf (fuzz U2)


def nees_bounds(dim: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` interval of one NEES value, chi2(dim)."""
    return anees_bounds(dim, 1, level)


def _point_sets(X, Y):
    X = _checks.finite_array("X", X)
    Y = _checks.finite_array("Y", Y)
    for name, S in (("X", X), ("Y", Y)):
        if S.ndim != 2:
            raise FusionInputError(f"{name} must be a (m, d) array of points, got shape {S.shape}")
    if X.shape[0] and Y.shape[0] and X.shape[1] != Y.shape[1]:
        raise FusionInputError(f"X and Y points differ in dimension: {X.shape[1]} vs {Y.shape[1]}")
    return X, Y


def _assignment_cost(D, c, p) -> tuple[float, float]:
    """(u, S) for the distances d_c (m, k) of two point sets, m, k >= 1 (`_distances`): S = min
    over assignments of sum (d_c(x, y) / u)^p over the min(m, k) assigned pairs, in units
    u chosen so that no c, p or distance reaches beyond float64: u = c when the sets differ
    in size (a term of 1 per unassigned point then dominates), else the largest distance
    of the optimal assignment, so that its largest term is 1 and none that matters
    underflows ((d / c)^p underflowed to 0 for c = 1e300, fuzz I5; with u the largest of
    all distances, every assigned term did at p = 400 and OSPA was 0, fuzz N2). u = 0
    where every distance is."""
    m, k = D.shape
    if m != k:
        (r, s), C = _assigned(D, c, p, k)
        return c, float(C[r, s].sum())
    u = float(D.max())
    for _ in range(_REFINE):
        if u == 0.0:
            return u, 0.0
        (r, s), C = _assigned(D, u, p, k)
        top = float(D[r, s].max())
        if top >= u:
            break
        u = top  # its terms underflowed in units of u: again in units of its largest
    return u, float(C[r, s].sum())


# Units `_assignment_cost` tries at most: each try divides u by the largest ratio of the
# distances whose p-th powers vanish beside 1 (at least 2^(1074 / p)); one or two suffice.
_REFINE = 64


def _assigned(D, u, p, k):
    """The optimal assignment (rows, columns) of the costs C = (D / u)^p and C, whose
    entries above 2 k are cut to 2 k: an assignment of entries <= 1 costs at most k, so no
    entry above that is in an optimal one where such an assignment exists (in units of a
    distance of one, it does), and none overflows."""
    with np.errstate(over="ignore"):
        C = np.minimum((D / u) ** p, 2.0 * k)
    return linear_sum_assignment(C), C


def _distances(X, Y, c) -> np.ndarray | None:
    """(m, k) distances cut at c, d_c = min(c, ||x - y||), the only ones the metrics use:
    Euclidean without squares that over- or underflow (`fusion_opt.linalg.row_norms`; a
    difference that overflows is beyond any cut-off). None when a set is empty."""
    if X.shape[0] == 0 or Y.shape[0] == 0:
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        return np.minimum(row_norms(X[:, None, :] - Y[None, :, :]), c)


def _order(c, p) -> tuple[float, float]:
    """The cut-off c > 0 and the order p >= 1, checked by name."""
    c = _checks.positive("c", c)
    p = _checks.positive("p", p)
    if p < 1:
        raise FusionInputError(f"p must be >= 1, got {p}")
    return c, p


def _alpha(alpha) -> float:
    alpha = _checks.positive("alpha", alpha)
    if alpha > 2:
        raise FusionInputError(f"alpha must be in (0, 2], got {alpha}")
    return alpha


def ospa(X, Y, c: float, p: float) -> float:
    """OSPA distance between point sets X (m, d) and Y (k, d) with cut-off c > 0, order p >= 1.

    0 if both sets are empty; c if exactly one is.
    """
    X, Y = _point_sets(X, Y)
    c, p = _order(c, p)
    return _ospa(_cost(_distances(X, Y, c), c, p), _sizes(X, Y), p)


def gospa(X, Y, c: float, p: float, alpha: float = 2.0) -> float:
    """GOSPA distance between X (m, d) and Y (k, d): cut-off c > 0, order p >= 1,
    alpha in (0, 2] (alpha = 2: the cost c^p / 2 per missed or false target)."""
    X, Y = _point_sets(X, Y)
    c, p = _order(c, p)
    alpha = _alpha(alpha)
    return _gospa(_cost(_distances(X, Y, c), c, p), _sizes(X, Y), p, alpha, c)


def match(X, Y, c: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of the optimal assignment of estimates X (m, d) to targets Y (k, d) with
    cost d_c = min(c, ||x - y||) (OSPA's assignment of order p = 1) that are closer than
    c: (rows of X (K,), rows of Y (K,)), K <= min(m, k)."""
    X, Y = _point_sets(X, Y)
    c = _checks.positive("c", c)
    return _match(_distances(X, Y, c), c)


class SetErrors(NamedTuple):
    """What `set_errors` gives: `ospa` and `gospa` of two point sets, and the pairs of
    `match`, rows of X (K,) and of Y (K,)."""

    ospa: float
    gospa: float
    rows: np.ndarray
    cols: np.ndarray


def set_errors(X, Y, c: float, p: float, alpha: float = 2.0) -> SetErrors:
    """`ospa`, `gospa` and `match` of estimates X (m, d) and targets Y (k, d) at once, each
    the value it gives alone: the checks and the distances once, and one assignment for
    OSPA and GOSPA (the same problem; match's, of order 1, is its own). A study scoring
    every step with the three apart (Table 2: 13 estimate series x 500 steps a run) spent
    a fifth of its run on them."""
    X, Y = _point_sets(X, Y)
    c, p = _order(c, p)
    alpha = _alpha(alpha)
    D, sizes = _distances(X, Y, c), _sizes(X, Y)
    cost = _cost(D, c, p)
    return SetErrors(_ospa(cost, sizes, p), _gospa(cost, sizes, p, alpha, c), *_match(D, c))


def _sizes(X, Y) -> tuple[int, int]:
    """The sizes of two point sets, the smaller first: (m, k), m <= k."""
    m, k = sorted((X.shape[0], Y.shape[0]))
    return m, k


def _cost(D, c, p) -> tuple[float, float]:
    """`_assignment_cost` of the cut distances D, or (c, 0) where a set is empty (D None)."""
    return (c, 0.0) if D is None else _assignment_cost(D, c, p)


def _ospa(cost, sizes, p) -> float:
    """OSPA from `_cost`'s (u, S) and the sets' `_sizes`."""
    (u, S), (m, k) = cost, sizes  # u = c where k > m
    if k == 0:
        return 0.0
    return float(u * ((S + (k - m)) / k) ** (1.0 / p))


def _gospa(cost, sizes, p, alpha, c) -> float:
    """GOSPA from `_cost`'s (u, S) and the sets' `_sizes`."""
    (u, S), (m, k) = cost, sizes  # u = c where k > m
    with np.errstate(over="ignore"):
        total = S + (k - m) / alpha
        # (k - m) / alpha past float64 (alpha = 5e-324, fuzz O2): the root from logs, where
        # S <= k is below the rounding of a total past 1e308, u = c among them (its root
        # alone overflowed beside c = 5e-324 and 1e-300: fuzz T1)
        value = float(u * total ** (1.0 / p)) if np.isfinite(total) else \
            float(np.exp(np.log(u) + (np.log(k - m) - np.log(alpha)) / p))
    if not np.isfinite(value):  # fuzz N3: inf for c = 1e308 and two missed targets
        raise FusionInputError(f"GOSPA overflows float64 (c = {c:g}, alpha = {alpha:g}, "
                               f"{k - m} unassigned points)")
    return value


def _match(D, c) -> tuple[np.ndarray, np.ndarray]:
    """`match`'s pairs from the cut distances D (None: a set is empty): those of the
    assignment closer than c."""
    if D is None:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    r, s = linear_sum_assignment(D)
    keep = D[r, s] < c
    return r[keep], s[keep]


def id_switches(ids) -> np.ndarray:
    """(J,) the number of changes between consecutive entries of each target's sequence of
    matched track ids, ids[j] the ids matched to target j in step order (steps where it
    is unmatched left out, so a track that drops out and returns with its id does not
    switch)."""
    if not is_sequence(ids):
        raise FusionInputError(f"ids must be a sequence of id sequences, one per target, got "
                               f"{type(ids).__name__}")
    seqs = [_id_sequence(f"ids[{j}]", s) for j, s in enumerate(ids)]
    return np.array([np.count_nonzero(np.diff(s)) for s in seqs], dtype=np.int64)


def _id_sequence(name: str, value) -> np.ndarray:
    """Track ids (L,) as int64, exactly (as floats, ids above 2^53 would merge)."""
    a = np.asarray(value) if not isinstance(value, str | bytes) else np.asarray(None)
    if a.dtype.kind == "f" and np.isfinite(a).all() and (a == np.round(a)).all() \
            and np.abs(a).max(initial=0.0) < 2.0**53:
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu" or a.ndim != 1 \
            or (a.dtype.kind == "u" and a.max(initial=0) >= 2**63):
        raise FusionInputError(f"{name} must be a 1-D sequence of integer track ids, got "
                               f"{safe_repr(value)}")
    return a.astype(np.int64)


def cardinality_error(n_estimated, n_true) -> np.ndarray:
    """(T,) signed cardinality error (float): estimated minus true number of targets per
    step."""
    a = _checks.finite_array("n_estimated", n_estimated, ndim=1)
    b = _checks.finite_array("n_true", n_true, ndim=1)
    if a.shape != b.shape:
        raise FusionInputError(f"n_estimated {a.shape} and n_true {b.shape} must be equal 1-D "
                               "shapes")
    for name, x in (("n_estimated", a), ("n_true", b)):  # fuzz N5: 1.5 targets passed
        bad = (x < 0) | (x != np.round(x)) | (x >= 2.0**53)
        if bad.any():
            raise FusionInputError(f"{name} must be counts of targets (whole numbers from 0 "
                                   f"to 2^53), got {safe_repr(x[bad][0].item())}")
    return a - b
