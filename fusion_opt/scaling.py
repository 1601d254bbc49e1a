"""Congruence scaling that hands a conic solver a well-conditioned CI weight problem.

With Ybar = mean_i Y_i = Rb^T Rb (from the QR of the stacked factors F_i / sqrt(N), so
Ybar is never formed), put Y'_i = Rb^-T Y_i Rb^-1 = G_i^T G_i, G_i = F_i Rb^-1. Then
Y'(uniform) = I, P(w) = Rb^-1 P'(w) Rb^-T and

    trace:   tr P(w)       = c tr(M P'(w)),  M = Rb^-T Rb^-1 / c,  c = |Rb^-1|_F^2
    logdet:  -log det Y(w) = -log det Y'(w) + const

so the weights are unchanged, the trace objective is 1 at uniform weights, and the data
reach the solver as matrices of order one. Compiled; B problems at once: F (B, N, n, n).
"""

from __future__ import annotations

import numpy as np

from .factored import work
from .linalg import gram, jit, matmul, qr, upper_inverse


@jit
def conic_data(F, Ys, M):
    """Ys (B, N, n, n) scaled informations and M (B, n, n) unit-trace trace weights, into
    the caller's arrays."""
    B, N, n = F.shape[0], F.shape[1], F.shape[2]
    ws = work(N, n)
    for b in range(B):
        for i in range(N):
            for r in range(n):
                for c in range(n):
                    ws.At[c, i * n + r] = F[b, i, r, c] / np.sqrt(N)
        qr(ws.At, n, N * n, ws.Vt, ws.R)
        upper_inverse(ws.R, ws.Ri)  # Rb^-1
        for i in range(N):
            matmul(F[b, i], ws.Ri, ws.B)
            gram(ws.B, Ys[b, i])
        gram(ws.Ri, M[b])  # Rb^-T Rb^-1
        M[b] /= np.trace(M[b])


def conic_problem(covs):
    """(Ys (N, n, n), M (n, n)): the congruence-scaled problem a conic backend receives for
    covariances covs (N, n, n), checked and prescaled as `fuse` does (for benchmarks and
    tests that call a backend of `backends.REGISTRY` directly)."""
    from . import core

    means, covs = core.arrays(np.zeros(np.shape(covs)[:-1]), covs, False)
    B, N, n = means.shape
    a = core._Arrays(B, N, n)
    core._prepare(means, covs, *core._unit_scales(B, N), a, core._NAMES, False)
    Ys, M = np.empty((B, N, n, n)), np.empty((B, n, n))
    conic_data(a.F, Ys, M)
    return Ys[0], M[0]
