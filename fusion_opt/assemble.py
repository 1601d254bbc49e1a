"""The fused estimate of each problem of a batch from its weights, compiled.

With the factors of `prepare.py` (scaled units, Y_i = F_i^T F_i) and weights w on the
simplex, `factored.py` gives P(w) = R^-1 R^-T and the mean as the least-squares solution of
[sqrt(w_i) F_i] m = [sqrt(w_i) F_i m_i]; the certificate is gap = g.w - min g. Results are
scaled back by 2^k (covariance, trace objective and its gap; log det gains n k log 2).

The best-vertex rule. A single node's objective comes straight from its input (its
trace; the log det of its Cholesky factor), a fused one with the rounding error bounded
by `factored.objective_error`. So a fused objective is reported only if it beats the best
node by more than the two errors together; when it does not, the result is that node
itself (weight 1, its own mean and covariance exactly, its own objective) with the
certificate computed there, which says how much better the optimum might be. A result
never claims to improve on the best node by less than it can verify. A vertex (weight 1
on one node) always returns that node's input unchanged.
"""

from __future__ import annotations

import numpy as np

from .factored import (evaluate, factor_at, gap, gradient, objective, objective_error,
                       vertex_error, work)
from .linalg import apply_qt, copy, fill, jit, matmul, matmul_t

_LN2 = np.log(2.0)


@jit
def assemble(F, means, covs, q, E, k, vertex, pnorm, W, trace: bool, mean, cov, stats):
    """Fused estimates of B problems into the caller's arrays: W (B, N) weights, replaced
    by the node's one-hot weights where the best-vertex rule applies; mean (B, n),
    cov (B, n, n); stats (B, 3) = objective and gap in the original units, and the
    relative certificate (gap / |f| for "trace"). Returns False if a result is not
    finite (it overflows float64 in the original units)."""
    B, N, n = means.shape
    ws = work(N, n)
    col = 0 if trace else 1
    finite = True
    for b in range(B):
        j = _vertex_or_interior(F[b], W[b], vertex[b, :, col], pnorm[b], ws, trace)
        if j >= 0:
            fill(W[b], 0.0)
            W[b, j] = 1.0
            _vertex(F[b], means[b, j], covs[b, j], q[b, j], E[b, j], k[b], vertex[b, j],
                    W[b], ws, trace, mean[b], cov[b], stats[b])
        else:
            _interior(F[b], means[b], k[b], W[b], ws, trace, mean[b], cov[b], stats[b])
        finite &= np.isfinite(stats[b, 0]) and np.isfinite(cov[b]).all() and \
            np.isfinite(mean[b]).all()
    return finite


@jit
def _vertex_or_interior(F, w, fv, pnorm, ws, trace: bool) -> int:
    """The node whose input is the result (best-vertex rule), or -1 for a fused one."""
    support, single = 0, -1
    for i in range(w.size):
        if w[i] > 0.0:
            support += 1
            single = i
    if support == 1:
        return single
    best = int(np.argmin(fv))
    f, ok = evaluate(F, w, ws, trace)
    if not ok:
        return best
    err = objective_error(F, w, ws, pnorm, f, trace)
    err_v = vertex_error(F[best], pnorm[best], trace)
    if trace:
        verified = f * (1.0 + err) < fv[best] * (1.0 - err_v)
    else:
        verified = f + err < fv[best] - err_v
    return -1 if verified else best


@jit
def _vertex(F, m_j, P_j, q_j, E_j, k, vertex_j, w, ws, trace, mean, cov, stats):
    """Node j's own estimate (mean, its modified covariance as given) and the certificate
    at e_j."""
    n = m_j.size
    copy(mean, m_j)
    for r in range(n):
        for c in range(n):
            cov[r, c] = np.ldexp(0.5 * (P_j[r, c] + P_j[c, r]) / q_j, -E_j)
    f, _ = evaluate(F, w, ws, trace)
    gradient(F, ws, trace)
    gp = gap(ws.g, w)
    if trace:
        stats[0] = np.trace(cov)
        stats[1], stats[2] = np.ldexp(gp, k), gp / abs(vertex_j[0])
    else:
        stats[0] = vertex_j[1] + n * k * _LN2
        stats[1], stats[2] = gp, gp


@jit
def _interior(F, means, k, w, ws, trace, mean, cov, stats):
    n = F.shape[1]
    rows, _ = factor_at(F, w, ws)
    r = 0
    for i in range(w.size):  # [sqrt(w_i) F_i m_i] in the row order of A
        if w[i] > 0.0:
            root = np.sqrt(w[i])
            for a in range(n):
                t = 0.0
                for c in range(a + 1):
                    t += F[i, a, c] * means[i, c]
                ws.rhs[r + a] = root * t
            r += n
    apply_qt(ws.Vt, n, rows, ws.rhs)
    for a in range(n):  # mean = R^-1 (Q^T b)[:n]
        t = 0.0
        for c in range(a, n):
            t += ws.Ri[a, c] * ws.rhs[c]
        mean[a] = t
    matmul_t(ws.Ri, ws.Ri, ws.P)
    for a in range(n):
        for c in range(n):
            cov[a, c] = np.ldexp(0.5 * (ws.P[a, c] + ws.P[c, a]), k)
    f = objective(ws, trace)
    gradient(F, ws, trace)
    gp = gap(ws.g, w)
    if trace:
        stats[0], stats[1], stats[2] = np.ldexp(f, k), np.ldexp(gp, k), gp / abs(f)
    else:
        stats[0], stats[1], stats[2] = f + n * k * _LN2, gp, gp
