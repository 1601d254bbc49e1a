"""Pairwise CI (N = 2) by simultaneous diagonalisation: a 1-D convex problem in w.

(Reinhardt, Noack & Hanebeck 2012.) With Y_b = L L^T and L^-1 Y_a L^-T = U diag(lam) U^T,
T = L^-T U diagonalises both informations at once (T^T Y_a T = diag(lam), T^T Y_b T = I), so

    Y(w) = w Y_a + (1 - w) Y_b = T^-T diag(d) T^-1,   d_k(w) = 1 + w a_k,  a_k = lam_k - 1,
    P(w) = T diag(1 / d) T^T,

and, with c_k = (T^T M T)_kk >= 0,

    trace:   f = sum_k c_k / d_k      f' = -sum c_k a_k / d_k^2,  f'' = 2 sum c_k a_k^2 / d_k^3
    logdet:  f = -sum_k log d_k + C   f' = -sum a_k / d_k,        f'' = sum a_k^2 / d_k^2

f is convex on [0, 1] (d_k > 0 there, since lam_k > 0). It starts at the best point of a
ladder geometric towards both ends (where the poles of f lie), whose neighbours there bracket
the minimiser, and takes Newton steps kept inside the shrinking bracket (a step leaving it is
replaced by bisection). The step is -f' / (f'' - (1 - rho^2) alpha f'^2): f is homogeneous in
Y (f(tY) = f/t, resp. f - n log t), so h = -1/f (alpha = 2/f), resp. h = -exp(-f/n)
(alpha = 1/n), is increasing in f and linear along Y -> tY, where Newton's method on f
crawls; h'' is proportional to f'' - alpha f'^2, and rho^2 = 0.01 keeps a little of f''.
Near the optimum f' -> 0 and the step is Newton's. It stops when the certificate of DESIGN §1,
which for N = 2 is gap = max(w f', -(1 - w) f'), falls to rounding level of f, or the bracket
to one ulp. `solve_weight` broadcasts over leading batch axes (no loop over problems);
`solve` runs the same iteration for one pair in Python floats, which beats numpy's cost per
call on n <= ~10 numbers.

The same 1-D problem arises from the covariances directly: if P_b = T T^T and
T^-1 P_a T^-T = diag(mu), then lam = 1 / mu. `diagonalise_covariances` uses that form, so a
batch of pairs needs no inverse of the inputs (see `batch.py`).
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.linalg import lapack

from ..results import FusionInputError
from . import WeightSolution

_EPS = np.finfo(float).eps
_MAX_ITER = 100  # a guard: the bracket halves at least every other step, so <= ~110 is exact
# Start points: geometric towards both ends of [0, 1].
_LADDER = np.array([0.0, 1e-12, 1e-8, 1e-4, 0.1, 0.5, 0.9, 1 - 1e-4, 1 - 1e-8, 1 - 1e-12, 1.0])
# Weight of f'' in the Newton curvature, beside that of the homogeneous form (module docstring).
_RHO2 = 0.01


def diagonalise_information(Ya, Yb):
    """Ya, Yb (..., n, n) SPD -> lam (..., n), T (..., n, n) with T^T Ya T = diag(lam),
    T^T Yb T = I."""
    nu, V = _split(Ya, Yb)
    return nu / (1.0 - nu), V / np.sqrt(1.0 - nu)[..., None, :]


def diagonalise_covariances(Pa, Pb):
    """Pa, Pb (..., n, n) SPD -> lam (..., n), T (..., n, n) with Pa = T diag(1/lam) T^T,
    Pb = T T^T, i.e. the information form of `diagonalise_information` with T^-T."""
    mu, V = _split(Pa, Pb, inverse=False)
    return (1.0 - mu) / mu, V * np.sqrt(1.0 - mu)[..., None, :]


def _split(A, B, inverse=True):
    """Diagonalise A and B against their sum S = L L^T, which is well conditioned when one
    of them is not (a Cholesky factor of B alone can lose every digit): with
    L^-1 A L^-T = U diag(nu) U^T, nu in (0, 1) and L^-1 B L^-T = U diag(1 - nu) U^T.
    Returns nu, clipped into [eps, 1 - eps] against rounding, and V = L^-T U (inverse, for
    informations: V^T A V = diag(nu)) or L U (for covariances: A = V diag(nu) V^T)."""
    if A.ndim == 2:  # one pair: LAPACK directly, numpy's wrappers cost more than the work
        L = lapack.dpotrf(A + B, lower=1)[0]
        Linv = lapack.dtrtri(L, lower=1)[0]
        nu, U = lapack.dsyevd(Linv @ A @ Linv.T)[:2]
    else:
        L = np.linalg.cholesky(A + B)
        Linv = np.linalg.inv(L)
        nu, U = np.linalg.eigh(Linv @ A @ np.swapaxes(Linv, -1, -2))
    nu = np.clip(nu, _EPS, 1.0 - _EPS)
    return nu, (np.swapaxes(Linv, -1, -2) if inverse else L) @ U


def _derivatives(w, a, c, criterion):
    """f', the curvature of the Newton step f'' - (1 - rho^2) alpha f'^2 (module docstring)
    and the certificate's scale (f for "trace", 1 for "logdet") at w (...), a, c (..., n)."""
    d = 1.0 + w[..., None] * a
    r = a / d
    if criterion == "trace":
        q = c / d
        f = q.sum(-1)
        qr = q * r
        fp = -qr.sum(-1)
        return fp, 2.0 * (qr * r).sum(-1) - (1.0 - _RHO2) * 2.0 / f * fp * fp, f
    fp = -r.sum(-1)
    return fp, (r * r).sum(-1) - (1.0 - _RHO2) / a.shape[-1] * fp * fp, 1.0


def objective(w, a, c, criterion):
    """f(w) of the module docstring without the constant of "logdet"; shape (...)."""
    d = 1.0 + w[..., None] * a
    return (c / d).sum(-1) if criterion == "trace" else -np.log(d).sum(-1)


def pair_gap(w, fprime):
    """The certificate of DESIGN §1 for weights (w, 1 - w): max(w f', -(1 - w) f')."""
    return np.maximum(w * fprime, -(1.0 - w) * fprime)


def solve_weight(a, c, criterion, tol=1e-15):
    """argmin over w in [0, 1] of the 1-D problem; a, c (..., n) (c unused for "logdet").

    Returns w (...), f'(w) (...) and the iteration count (int, over the whole batch).
    """
    w, lo, hi = _ladder_start(a, c, criterion)
    iters = 0
    for iters in range(1, _MAX_ITER + 1):  # noqa: B007 (count reported)
        fp, curv, scale = _derivatives(w, a, c, criterion)
        lo = np.where(fp < 0, w, lo)
        hi = np.where(fp > 0, w, hi)
        step = w - fp / np.where(curv > 0, curv, np.nan)  # nan: not inside, so bisect
        # done at rounding level: the gap, the bracket, or a step that leaves w unchanged
        done = (pair_gap(w, fp) <= tol * scale) | (hi - lo <= 4 * _EPS) | (step == w)
        if done.all():
            break
        inside = (step > lo) & (step < hi)
        w = np.where(done, w, np.where(inside, step, 0.5 * (lo + hi)))
    return w, _derivatives(w, a, c, criterion)[0], iters


def _ladder_start(a, c, criterion):
    """The best point of `_LADDER` and its neighbours there, which bracket the minimiser
    (f is convex); each (...)."""
    f = objective(np.broadcast_to(_LADDER, (*a.shape[:-1], len(_LADDER))),
                  a[..., None, :], c[..., None, :], criterion)
    k = np.argmin(f, axis=-1)
    return (_LADDER[k], _LADDER[np.maximum(k - 1, 0)],
            _LADDER[np.minimum(k + 1, len(_LADDER) - 1)])


def _solve_scalar(a, c, criterion, tol=1e-15):
    """`solve_weight` for one problem, a and c (n,), in Python floats; returns w and the
    iteration count."""
    w, lo, hi = (float(x) for x in _ladder_start(a, c, criterion))
    terms = list(zip(a.tolist(), c.tolist(), strict=True))
    trace = criterion == "trace"
    iters = 0
    for iters in range(1, _MAX_ITER + 1):  # noqa: B007 (count reported)
        fp, curv, scale = _scalar_derivatives(w, terms, trace)
        lo, hi = (w, hi) if fp < 0 else (lo, w) if fp > 0 else (lo, hi)
        step = w - fp / curv if curv > 0 else math.nan  # nan: not inside, so bisect
        if max(w * fp, (w - 1.0) * fp) <= tol * scale or hi - lo <= 4 * _EPS or step == w:
            break
        w = step if lo < step < hi else 0.5 * (lo + hi)
    return w, iters


def _scalar_derivatives(w, terms, trace):
    """`_derivatives` at a float w for terms [(a_k, c_k)]."""
    f = fp = fpp = 0.0
    for ak, ck in terms:
        d = 1.0 + w * ak
        r = ak / d
        q = ck / d if trace else 1.0
        f += q
        fp -= q * r
        fpp += q * r * r
    if trace:
        return fp, 2.0 * fpp - (1.0 - _RHO2) * 2.0 / f * fp * fp, f
    return fp, fpp - (1.0 - _RHO2) / len(terms) * fp * fp, 1.0


def solve(Ys, M, criterion) -> WeightSolution:
    """Backend: Ys (2, n, n) scaled informations, M (n, n) trace weight -> weights (2,)."""
    t0 = time.perf_counter()
    if Ys.shape[0] != 2:
        raise FusionInputError(f"backend 'closed-form' fuses N = 2 nodes, got N = {len(Ys)}")
    lam, T = diagonalise_information(Ys[0], Ys[1])
    c = ((M @ T) * T).sum(0) if criterion == "trace" else lam  # c_k = (T^T M T)_kk
    w, iters = _solve_scalar(lam - 1.0, c, criterion)
    wall = time.perf_counter() - t0
    return WeightSolution(np.array([w, 1.0 - w]), "optimal", iters, wall, wall)
