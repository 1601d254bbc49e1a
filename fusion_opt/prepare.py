"""Checks, exact prescaling and square-root factors of a batch of fusion problems, compiled.

`prepare(means (B, N, n), covs (B, N, n, n), q (B, N), E (B, N))` checks every value (means
and covariances finite, covariances symmetric within SYMMETRY_RTOL of their largest entry
and positive definite), and returns the factors of `factored.py` of the covariances that
are fused,

    Phat_i = P_i / s_i,   s_i = q_i 2^E_i  (q_i in [1, 2), E_i integer; s = 1 for CI and
                                            the detection scales of MBCI, kept in logs),

each multiplied by 2^-k_b, one exact power of two per problem that puts the geometric
middle of its nodes' scales (largest diagonal entries) at 1. So covariances from 1e-310
(denormal) to 1e300, and nodes of one problem 1e16 apart, reach the solvers as numbers of
order one without a rounding error; results are scaled back by 2^k_b. A problem whose
nodes span more than 2^1900 cannot be brought into range and is refused.

The first failing check is reported as a code and its position (problem, node); the caller
turns it into a FusionInputError naming the argument.
"""

from __future__ import annotations

import math

import numpy as np

from .linalg import cholesky, inline, jit, lower_inverse, pow2

SYMMETRY_RTOL = 1e-8
MAX_SPREAD_BITS = 1900
# A covariance whose condition estimate |P|_F tr(P^-1) = |P|_F |C^-1|_F^2 (C C^T = P; at
# least its condition, at most n^1.5 times it) is above this is refused as numerically
# singular: a rank-deficient covariance passes a Cholesky with pivots of rounding size, 1
# to 100 eps of its diagonal, and such a node made the rules' inverses fail and the fused
# covariance singular.
MAX_CONDITION = 2.0**46  # 7.0e13; condition 1e12 passes up to n = 16 at worst, any n typically

OK, MEANS_NONFINITE, COVS_NONFINITE, ASYMMETRIC, NOT_PD, SPREAD = range(6)


@jit
def prepare(means, covs, q, E, F, k, vertex, pnorm, where) -> int:
    """Check and factor B problems into the caller's arrays; returns a code (OK = 0).

    F (B, N, n, n) the factors; k (B,) the exponents; vertex[b, i] = (tr, log det) of the
    scaled Phat_i (the objective at the vertex e_i, in scaled units); pnorm[b, i] its
    Frobenius norm (the scale of its rounding, for the error bounds of `assemble.py`);
    where = (problem, node, index) of the first failure.
    """
    B, N, n = means.shape
    S, C = np.empty((n, n)), np.empty((n, n))
    for b in range(B):
        code = _check_values(means[b], covs[b], where)
        if code != OK:
            where[0] = b
            return code
        lo, hi = np.inf, -np.inf
        for i in range(N):
            top = 0.0
            for j in range(n):
                top = max(top, covs[b, i, j, j])
            if not top > 0.0:
                where[0], where[1] = b, i
                return NOT_PD
            bits = np.log2(top) - np.log2(q[b, i]) - E[b, i]
            lo, hi = min(lo, bits), max(hi, bits)
        if hi - lo > MAX_SPREAD_BITS:
            where[0] = b
            return SPREAD
        k[b] = int(np.round(0.5 * (lo + hi)))
        for i in range(N):
            pnorm[b, i] = _factor(covs[b, i], q[b, i], E[b, i] + k[b], S, C, F[b, i],
                                  vertex[b, i])
            if not pnorm[b, i] > 0.0:
                where[0], where[1] = b, i
                return NOT_PD
    return OK


@inline
def _check_values(means, covs, where) -> int:
    """Finite means and covariances, symmetric covariances; where[1:] = (node, index)."""
    N, n = means.shape
    for i in range(N):
        for j in range(n):
            if not np.isfinite(means[i, j]):
                where[1], where[2] = i, j
                return MEANS_NONFINITE
    for i in range(N):
        for j in range(n):
            for l in range(n):
                if not np.isfinite(covs[i, j, l]):
                    where[1], where[2] = i, j * n + l
                    return COVS_NONFINITE
        if asymmetric(covs[i]):
            where[1] = i
            return ASYMMETRIC
    return OK


@jit
def asymmetric(P) -> bool:
    """Whether the finite P (n, n) has |P_jl - P_lj| > SYMMETRY_RTOL max |P| somewhere (the
    one symmetry test of the package's checks: also `validation.check_spd`'s)."""
    n = P.shape[0]
    top = 0.0
    for j in range(n):
        for l in range(n):
            top = max(top, abs(P[j, l]))
    for j in range(n):
        for l in range(j + 1, n):
            if abs(P[j, l] - P[l, j]) > SYMMETRY_RTOL * top:
                return True
    return False


@jit
def scaled(P, q, shift, S) -> float:
    """S = sym(P) / q * 2^-shift, the covariance a node is fused with (scaled units);
    returns |S|_F, summed again from entries scaled by a power of two near the largest
    where the squares may leave float64's normal range (entries beyond 1e-145..1e145)."""
    n = P.shape[0]
    top, norm2 = 0.0, 0.0
    factor = pow2(-shift)
    for j in range(n):
        for l in range(n):
            x = 0.5 * (P[j, l] + P[l, j])
            if not np.isfinite(x):  # the sum overflowed (entries near 1.8e308)
                x = 0.5 * P[j, l] + 0.5 * P[l, j]
            if q != 1.0:  # x / 1 is x: no division where there is no scale (BCI)
                x /= q
            S[j, l] = x * factor if factor > 0.0 else np.ldexp(x, -shift)
            top = max(top, abs(S[j, l]))
            norm2 += S[j, l] * S[j, l]
    if 1e-290 < norm2 < 1e290 or top == 0.0:  # entries within 1e-145 of the largest count
        return np.sqrt(norm2)                  # for at most 1e-290 of the sum
    if not top < np.inf:
        return top
    unit = pow2(min(max(-math.frexp(top)[1], -1022), 1022))  # top * unit in [2^-52, 4)
    norm2 = 0.0
    for j in range(n):
        for l in range(n):
            x = S[j, l] * unit
            norm2 += x * x
    return np.sqrt(norm2) / unit


@inline
def _factor(P, q, shift, S, C, F_out, vertex_out) -> float:
    """F_out = C^-1 for C C^T = S = sym(P) / q * 2^-shift; vertex_out = (tr, log det) of S;
    returns |S|_F, or 0 when S is not positive definite."""
    n = P.shape[0]
    norm = scaled(P, q, shift, S)
    if not cholesky(S, C):
        return 0.0
    lower_inverse(C, F_out)
    trace, logdet, inverse2 = 0.0, 0.0, 0.0
    for j in range(n):
        trace += S[j, j]
        logdet += 2.0 * np.log(C[j, j])
        for l in range(j + 1):
            if not np.isfinite(F_out[j, l]):
                return 0.0
            inverse2 += F_out[j, l] * F_out[j, l]  # |C^-1|_F^2 = tr(P^-1)
    if not norm * inverse2 <= MAX_CONDITION:
        return 0.0
    vertex_out[0], vertex_out[1] = trace, logdet
    return norm
