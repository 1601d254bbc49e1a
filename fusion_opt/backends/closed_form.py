"""Pairwise CI (N = 2) by simultaneous diagonalisation: a 1-D convex problem in w.

(Reinhardt, Noack & Hanebeck 2012.) With Y_b = L L^T and L^-1 Y_a L^-T = U diag(lam) U^T,
T = L^-T U diagonalises both informations at once (T^T Y_a T = diag(lam), T^T Y_b T = I), so

    Y(w) = w Y_a + (1 - w) Y_b = T^-T diag(d) T^-1,   d_k(w) = 1 + w a_k,  a_k = lam_k - 1,
    P(w) = T diag(1 / d) T^T,

and, with c_k = (T^T M T)_kk >= 0,

    trace:   f = sum_k c_k / d_k      f' = -sum c_k a_k / d_k^2,  f'' = 2 sum c_k a_k^2 / d_k^3
    logdet:  f = -sum_k log d_k + C   f' = -sum a_k / d_k,        f'' = sum a_k^2 / d_k^2

f is convex on [0, 1] (d_k > 0 there, since lam_k > 0). The minimiser is an end point when
f'(0) >= 0 or f'(1) <= 0, else the root of f' in (0, 1), found by Newton's method kept
inside a shrinking bracket (a step leaving the bracket is replaced by bisection). It stops
when the certificate of DESIGN §1, which for N = 2 is gap = max(w f', -(1 - w) f'), falls
to rounding level of f, or the bracket to one ulp. Everything broadcasts over leading
batch axes; there is no loop over problems.

The same 1-D problem arises from the covariances directly: if P_b = T T^T and
T^-1 P_a T^-T = diag(mu), then lam = 1 / mu. `diagonalise_covariances` uses that form, so a
batch of pairs needs no inverse of the inputs (see `batch.py`).
"""

from __future__ import annotations

import time

import numpy as np

from ..results import FusionInputError
from . import WeightSolution

_EPS = np.finfo(float).eps
_MAX_ITER = 100  # a guard: the bracket halves at least every other step, so <= ~110 is exact


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
    L = np.linalg.cholesky(A + B)
    Linv = np.linalg.inv(L)
    nu, U = np.linalg.eigh(Linv @ A @ np.swapaxes(Linv, -1, -2))
    nu = np.clip(nu, _EPS, 1.0 - _EPS)
    return nu, (np.swapaxes(Linv, -1, -2) if inverse else L) @ U


def _derivatives(w, a, c, criterion):
    """f' and f'' of the module docstring at w (...), a and c (..., n)."""
    r = a / (1.0 + w[..., None] * a)
    if criterion == "trace":
        cr = c * r / (1.0 + w[..., None] * a)
        return -cr.sum(-1), 2.0 * (cr * r).sum(-1)
    return -r.sum(-1), (r * r).sum(-1)


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
    zero = np.zeros(a.shape[:-1])
    d0, _ = _derivatives(zero, a, c, criterion)
    d1, _ = _derivatives(zero + 1.0, a, c, criterion)
    lo, hi = zero.copy(), zero + 1.0
    # Start at the root of the secant of f' between the end points (exact if f' is linear).
    interior = (d0 < 0) & (d1 > 0)
    w = np.where(interior, -d0 / np.where(interior, d1 - d0, 1.0), np.where(d0 >= 0, 0.0, 1.0))
    scale = objective(w, a, c, criterion) if criterion == "trace" else 1.0  # as newton's
    iters = 0
    for iters in range(1, _MAX_ITER + 1):  # noqa: B007 (count reported)
        fp, fpp = _derivatives(w, a, c, criterion)
        done = ~interior | (pair_gap(w, fp) <= tol * scale) | (hi - lo <= 4 * _EPS)
        if done.all():
            break
        lo = np.where(fp < 0, w, lo)
        hi = np.where(fp > 0, w, hi)
        step = w - fp / np.where(fpp > 0, fpp, 1.0)
        inside = (step > lo) & (step < hi) & (fpp > 0)
        w = np.where(done, w, np.where(inside, step, 0.5 * (lo + hi)))
    fp, _ = _derivatives(w, a, c, criterion)
    return w, fp, iters


def solve(Ys, M, criterion) -> WeightSolution:
    """Backend: Ys (2, n, n) scaled informations, M (n, n) trace weight -> weights (2,)."""
    t0 = time.perf_counter()
    if Ys.shape[0] != 2:
        raise FusionInputError(f"backend 'closed-form' fuses N = 2 nodes, got N = {len(Ys)}")
    lam, T = diagonalise_information(Ys[0], Ys[1])
    c = np.einsum("ji,jk,ki->i", T, M, T) if criterion == "trace" else lam
    w, _, iters = solve_weight(lam - 1.0, c, criterion)
    wall = time.perf_counter() - t0
    return WeightSolution(np.array([w, 1.0 - w]), "optimal", iters, wall, wall)
