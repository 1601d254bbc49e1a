"""Pairwise CI (N = 2) as a 1-D convex problem in w, by simultaneous diagonalisation
(Reinhardt, Noack & Hanebeck 2012), compiled.

From the factors of `factored.py` (Y_a = F_a^T F_a, Y_b = F_b^T F_b): the QR of the
stacked [F_a; F_b] = [Q_a; Q_b] R gives Y_a + Y_b = R^T R and R^-T Y_a R^-1 = Q_a^T Q_a,
R^-T Y_b R^-1 = Q_b^T Q_b = I - Q_a^T Q_a. With Q_a^T Q_a = V diag(.) V^T,
nu_k = |Q_a V_k|^2 and tau_k = |Q_b V_k|^2 (nu_k + tau_k = 1; each is computed as a norm,
so neither loses digits when the other is near 1) and T = R^-1 V:

    Y(w) = R^T V diag(d) V^T R,   d_k(w) = tau_k + w (nu_k - tau_k),   P(w) = T diag(1/d) T^T,

    trace:   f = sum_k c_k / d_k  (c_k = |T_k|^2),  f' = -sum c_k a_k / d_k^2,
             f'' = 2 sum c_k a_k^2 / d_k^3
    logdet:  f = -sum_k log d_k + const,  f' = -sum a_k / d_k,  f'' = sum a_k^2 / d_k^2

(a_k = nu_k - tau_k). f is convex on [0, 1]. The search starts at the best point of a
ladder geometric towards both ends (where the poles of f lie), whose neighbours bracket the
minimiser, and takes Newton steps kept inside the shrinking bracket (bisection otherwise).
The step is -f' / (f'' - (1 - rho^2) alpha f'^2): f is homogeneous in Y (f(tY) = f / t,
resp. f - n log t), so h = -1/f (alpha = 2/f), resp. -exp(-f/n) (alpha = 1/n), is linear
along Y -> tY, where Newton's method on f crawls; rho^2 = 0.01 keeps a little of f''. Near
the optimum f' -> 0 and the step is Newton's. It stops when the certificate
max(w f', -(1 - w) f') falls to the rounding level of f, or the bracket to 4 ulps.
"""

from __future__ import annotations

import numpy as np

from ..linalg import (
    SMALL,
    eigh,
    gram,
    inline,
    jit,
    matmul,
    qr_thin,
    upper_inverse,
)

_EPS = np.finfo(np.float64).eps
_MAX_ITER = 100  # a guard: the bracket halves at least every other step
_LADDER = np.array([0.0, 1e-12, 1e-8, 1e-4, 0.1, 0.5, 0.9, 1 - 1e-4, 1 - 1e-8, 1 - 1e-12, 1.0])
_RHO2 = 0.01
_TOL = 1e-15


@jit
def pair_weight(F, trace: bool, ws):
    """The optimal weight w of node 0 (node 1 takes 1 - w) for factors F (2, n, n), and
    the iteration count; ws a `factored.Work` of this size."""
    return pair_weight_at(F, trace, ws.At, ws.Vt, ws.R, ws.Ri, ws.P, ws.B, ws.X, ws.S, ws.U,
                          ws.lam, ws.abc)


@jit
def pair_weight_at(F, trace: bool, At, Vt, R, Ri, P, B, X, S, U, lam, abc):
    """`pair_weight` with the buffers of `factored.Work` as arrays (factored.py's
    docstring says why)."""
    diagonalise(F, trace, At, Vt, R, Ri, P, B, X, S, U, lam, abc)
    return solve_weight(abc, trace)


@inline
def diagonalise(F, trace: bool, At, Vt, R, Ri, P, B, X, S, U, lam, abc):
    """abc (3, n) = a, b, c of the module docstring: d_k(w) = b_k + w a_k and the trace
    weights; the other arrays are scratch (At (n, >= 2n), n x n, lam (n,))."""
    n = F.shape[1]
    for a in range(n):  # [F_a; F_b]^T in the first 2n columns of At
        for b in range(n):
            At[b, a], At[b, n + a] = F[0, a, b], F[1, a, b]
    qr_thin(At, n, 2 * n, Vt, R)  # At now holds Q^T = [Q_a^T, Q_b^T]
    if n > SMALL:  # through BLAS, from copies of Q_a and Q_b in Ri and P (free until below)
        _q_blocks(At, Ri, P)
        gram(Ri, S)
    else:
        _q_gram(At, S)
    eigh(S, lam, U)
    if n > SMALL:
        matmul(Ri, U, B)
        matmul(P, U, X)
    else:
        _q_times(At, U, B, X)
    for k in range(n):
        nu, tau = _column_sumsq(B, k), _column_sumsq(X, k)
        abc[0, k], abc[1, k], abc[2, k] = nu - tau, tau, 1.0
    if trace:
        upper_inverse(R, Ri)
        matmul(Ri, U, P)  # T = R^-1 V
        for k in range(n):
            abc[2, k] = _column_sumsq(P, k)


@inline
def _q_gram(Qt, S):
    """S = Q_a^T Q_a from Qt = [Q_a^T, Q_b^T] (n, >= 2n), by loops (n <= SMALL)."""
    n = S.shape[0]
    for a in range(n):
        for b in range(a, n):
            t = 0.0
            for r in range(n):
                t += Qt[a, r] * Qt[b, r]
            S[a, b] = S[b, a] = t


@inline
def _q_times(Qt, U, B, X):
    """B = Q_a U and X = Q_b U from Qt = [Q_a^T, Q_b^T], by loops (n <= SMALL)."""
    n = U.shape[0]
    for r in range(n):
        for k in range(n):
            ta = tb = 0.0
            for a in range(n):
                ta += Qt[a, r] * U[a, k]
                tb += Qt[a, n + r] * U[a, k]
            B[r, k], X[r, k] = ta, tb


@jit
def _q_blocks(Qt, Qa, Qb):
    """Qa = Q_a and Qb = Q_b, C-contiguous, from Qt = [Q_a^T, Q_b^T]: BLAS on them instead
    of `_q_gram` and `_q_times`, whose strides took 7.0 of a pair's 9.8 s at n = 800."""
    n = Qa.shape[0]
    for r in range(n):
        for a in range(n):
            Qa[r, a], Qb[r, a] = Qt[a, r], Qt[a, n + r]


@jit
def _column_sumsq(X, k) -> float:
    t = 0.0
    for i in range(X.shape[0]):
        t += X[i, k] * X[i, k]
    return t


@inline
def _value(w, abc, trace: bool) -> float:
    """f at w ("logdet" up to its constant): for "logdet" -log of the product of the d_k,
    kept in range (d_k <= 1), one log for many factors instead of one each."""
    n = abc.shape[1]
    f, m = 0.0, 1.0
    for k in range(n):
        d = abc[1, k] + w * abc[0, k]
        if trace:
            f += abc[2, k] / d
        elif d < 1e-100:  # a factor that could take the product below the normal range
            f -= np.log(d)
        else:
            m *= d
            if m < 1e-200:
                f -= np.log(m)
                m = 1.0
    return f if trace else f - np.log(m)


@inline
def _derivatives(w, abc, trace: bool):
    """f, f' and the damped curvature of the module docstring at w; f only for "trace"
    (the curvature's and the stopping test's scale: "logdet" needs f only in the ladder,
    `_value`), 0 for "logdet"."""
    f = fp = fpp = 0.0
    n = abc.shape[1]
    for k in range(n):
        d = abc[1, k] + w * abc[0, k]
        r = abc[0, k] / d
        q = abc[2, k] / d if trace else 1.0
        if trace:
            f += q
        fp -= q * r
        fpp += q * r * r
    if trace:
        return f, fp, 2.0 * fpp - (1.0 - _RHO2) * 2.0 / f * fp * fp
    return f, fp, fpp - (1.0 - _RHO2) / n * fp * fp


@inline
def solve_weight(abc, trace: bool):
    """argmin over w in [0, 1] of the 1-D problem; (w, iterations)."""
    k_best, f_best = 0, np.inf
    for k in range(_LADDER.size):
        f = _value(_LADDER[k], abc, trace)
        if f < f_best:
            k_best, f_best = k, f
    w = _LADDER[k_best]
    lo = _LADDER[max(k_best - 1, 0)]
    hi = _LADDER[min(k_best + 1, _LADDER.size - 1)]
    it = 0
    for it in range(1, _MAX_ITER + 1):  # noqa: B007 (the count is reported)
        f, fp, curv = _derivatives(w, abc, trace)
        if fp < 0.0:
            lo = w
        elif fp > 0.0:
            hi = w
        step = w - fp / curv if curv > 0.0 else np.nan
        scale = abs(f) if trace else 1.0
        if max(w * fp, (w - 1.0) * fp) <= _TOL * scale or hi - lo <= 4 * _EPS or step == w:
            break
        w = step if lo < step < hi else 0.5 * (lo + hi)
    return w, it
