"""The fused estimate of each problem of a batch from its weights, compiled.

With the factors of `prepare.py` (scaled units, Y_i = F_i^T F_i) and weights w on the
simplex, `factored.py` gives P(w) = R^-1 R^-T and the mean as the least-squares solution of
[sqrt(w_i) F_i] m = [sqrt(w_i) F_i m_i]; the certificate is gap = g.w - min g. Results are
scaled back by 2^k (covariance, trace objective and its gap; log det gains n k log 2).

The best-vertex rule. A fused result is reported only where it verifiably beats every
single node, in exact arithmetic on the covariances as given (divided by the exact MBCI
scales); otherwise the result is the best node itself (weight 1, its own mean and
covariance exactly, its own objective) with the certificate computed there, which says
how much better the optimum might be. A vertex (weight 1 on one node) always returns that
node's input unchanged. Two tests, the second only for the nodes the first cannot rule out:

1. f(w) from the QR of `factored.py`, with the bound of `factored.objective_error`, against
   each node's own objective (its trace; the log det of its Cholesky factor) minus
   `vertex_error`, both widened by the rounding of the detection scales. Cheap, and enough
   wherever the optimum is clearly better; but each bound is c n eps times a condition
   (3e8 at issue 9's ill-conditioned batch: 2.5e-6 in log det), far above the error made.

2. The difference D = f(w) - f(e_j), computed directly in node j's whitened coordinates,
   so that its rounding and the input's own rounding are charged to D, not to f. With
   C C^T = S_j (Cholesky of node j's scaled covariance), B_i = F_i C, X_i = B_i^T B_i (the
   nodes seen from node j; X_j = I exactly) and

       M = sum_i w_i X_i = I + Sigma,   Sigma = sum_{i != j} w_i (X_i - I) + (sum_i w_i - 1) I,

   Y(w) = C^-T M C^-1, P(w) = C M^-1 C^T, so

       logdet:  D = -log det(I + Sigma) = -sum_k log1p(d_k),   L L^T = I + Sigma, L_kk^2 = 1 + d_k
       trace:   D = tr(C (M^-1 - I) C^T) = -tr(K M^-1 Sigma),   K = C^T C,

   small numbers computed from small numbers: nodes that agree with node j contribute
   X_i - I near 0, and node j's own large covariance never cancels against itself. Its
   bound (`factored.improvement`) is first order, componentwise, and counts
   (a) the rounding of B_i, X_i and Sigma (|dB_i| <= n eps |F_i| |C|), carried to D by
       dD = -tr(M^-1 dSigma) (logdet), -tr(H dSigma), H = M^-1 K M^-1 (trace);
   (b) the Cholesky factor of I + Sigma (backward error in the pivots d_k themselves), the
       substitutions with it, log1p and the final sums;
   (c) the input: each node's Cholesky factor is exact for S_i + dS_i, |dS_i| <= (n + 3)
       eps |C_i| |C_i|^T (with forming S_i; plus eta_i |S_i| for its detection scale), and
       F_i = C_i^-1 (I + R_i), |R_i| <= n eps |C_i| |F_i|. These move D by
       tr(dS_i dD/dP_i) with dD/dP_i = w_i Y_i P^2 Y_i (trace), w_i Y_i P Y_i (logdet) for
       i != j, and for node j, which enters both f(w) and f(e_j),
           dD/dP_j = w_j Y_j P^2 Y_j - I = C^-T (w_j H - K) C^-1   (trace),
           dD/dP_j = w_j Y_j P Y_j - Y_j = C^-T (w_j M^-1 - I) C^-1   (logdet),
       which vanish as w -> e_j: node j's rounding moves f(w) and f(e_j) alike. So its
       condition no longer enters where the result is close to node j, and the other nodes'
       enters with their (small) weights.
   The bound, doubled, is checked against exact arithmetic at the optimum and at points
   near every vertex, over every kind of tests/test_campaign.py (worst |D - D_exact| /
   bound about 0.1). Verified means D + bound < 0. Issue 9's batch problems 46723 and
   57613 (improvements 4.8e-6 and 5.9e-7 in log det) get bounds of 1.3e-11 and 2.2e-11;
   near-identical nodes at condition 1e12 (trace improvements down to 3.5e-13 of f) 1e-14
   of f (3e-13 at most). What remains unverified is an improvement below the worst case of
   the input's own rounding (first order in eps), which no double-precision result can
   claim.
"""

from __future__ import annotations

import math

import numpy as np

from .factored import (
    FACTORED,
    GRADED,
    evaluate_at,
    factor,
    gap,
    gradient_at,
    improvement,
    objective_error,
    value,
    verify_work,
    vertex_error,
    vertex_gap,
    work,
)
from .linalg import SMALL, apply_qt, copy, fill, inline, jit, matmul_t, pow2, small_mul_t
from .prepare import scaled

_LN2 = np.log(2.0)
_EPS = np.finfo(np.float64).eps


@jit
def assemble(F, means, covs, q, E, k, vertex, pnorm, W, trace: bool, mean, cov, stats):
    """Fused estimates of B problems into the caller's arrays: W (B, N) weights, replaced
    by the node's one-hot weights where the best-vertex rule applies; mean (B, n),
    cov (B, n, n); stats (B, 3) = objective and gap in the original units, and the
    relative certificate (gap / |f| for "trace"). Returns False if a result is not
    finite (it overflows float64 in the original units)."""
    B, N, n = means.shape
    ws = work(N, n)
    finite = True
    for b in range(B):
        finite &= assemble_one(F[b], means[b], covs[b], q[b], E[b], k[b], vertex[b], pnorm[b],
                               W[b], trace, mean[b], cov[b], stats[b], 0, ws.At, ws.Vt, ws.R,
                               ws.Ri, ws.P, ws.B, ws.X, ws.g, ws.z, ws.rhs)
    return finite


@inline
def assemble_one(F, means, covs, q, E, k, vertex, pnorm, w, trace: bool, mean, cov, stats,
                 state, At, Vt, R, Ri, P, B, X, g, eta, rhs) -> bool:
    """`assemble` of one problem, with the buffers of `factored.Work` as arrays; state
    says what they hold at w already (`newton.solve_one`: the QR, FACTORED, and the
    gradient in g, GRADED), which is not computed again."""
    col = 0 if trace else 1
    j = _vertex_or_interior(F, w, vertex, col, pnorm, covs, q, E, k, At, Vt, R, Ri, P, B,
                            X, eta, trace, state >= FACTORED)
    if j >= 0:
        fill(w, 0.0)
        w[j] = 1.0
        _vertex(F, j, means[j], covs, q, E, k, vertex[j], pnorm, w, At, Vt, R, Ri, P, B, g,
                eta, trace, mean, cov, stats)
    else:
        _interior(F, means, k, w, Vt, R, Ri, P, B, g, rhs, trace, mean, cov, stats,
                  state == GRADED)
    return np.isfinite(stats[0]) and all_finite(cov) and all_finite(mean)


@jit
def all_finite(a) -> bool:
    for x in a.flat:
        if not np.isfinite(x):
            return False
    return True


@jit
def _vertex_or_interior(F, w, vertex, col, pnorm, covs, q, E, k, At, Vt, R, Ri, P, B, X,
                        eta, trace: bool, factored: bool) -> int:
    """The node whose input is the result (best-vertex rule), or -1 for a fused one, when
    the buffers are left factored at w (factored: they are already). eta (N,) receives
    the scales' errors. The best node is the least vertex objective fv = vertex[:, col],
    ties broken by the other criterion's (`_before`). A solver's vertex gives way to a
    better node: certified within its tolerance, it may stop at a node up to that
    tolerance worse than the best (900 ulps at n = 1, and which node depended on the
    nodes' order: fuzz P1; at n = 1 the log of variances one ulp apart ties: fuzz Q2)."""
    N, n = F.shape[0], F.shape[1]
    fv = vertex[:, col]
    support, single, best = 0, -1, 0
    for i in range(N):
        if w[i] > 0.0:
            support += 1
            single = i
        if _before(vertex, i, best, col):
            best = i
    if support == 1:
        return best if _before(vertex, best, single, col) else single
    if factored:
        f = value(R, Ri, trace)
    else:
        f, ok = evaluate_at(F, w, At, Vt, R, Ri, trace)
        if not ok:
            return best
    eta_max = 0.0
    for i in range(N):
        eta[i] = _scale_error(q[i], E[i], N)
        if w[i] > 0.0:
            eta_max = max(eta_max, eta[i])
    err = objective_error(F, w, R, Ri, P, B, X, pnorm, f, trace)
    high = f * (1.0 + err + eta_max) if trace else f + err + n * eta_max
    for i in range(N):  # every node the first test cannot rule out, by the second
        err_v = vertex_error(F[i], pnorm[i], trace)
        low = fv[i] * (1.0 - err_v - eta[i]) if trace else fv[i] - err_v - n * eta[i]
        if low <= high and not _improves_on(F, w, i, covs, q, E, k, eta, trace):
            return best
    return -1


@jit
def _before(vertex, a: int, b: int, col: int) -> bool:
    """Whether node a's vertex objectives (vertex[a, col], then the other criterion's)
    are below node b's."""
    if vertex[a, col] != vertex[b, col]:
        return vertex[a, col] < vertex[b, col]
    return vertex[a, 1 - col] < vertex[b, 1 - col]


@jit
def _scale_error(q, E, N) -> float:
    """A bound on the relative error of a node's detection scale q 2^E against the exact
    s_i (`detection.py`: a product of N terms, or from logs where it underflows); 0 when
    there is no scale (BCI, or s = 1, which `detection._split` gives only for an exact 1)."""
    if q == 1.0 and E == 0:
        return 0.0
    return (2 * N + 8 + 2 * abs(E)) * _EPS


@inline
def _improves_on(F, w, j, covs, q, E, k, eta, trace: bool) -> bool:
    """Whether f(w) < f(e_j) is verified by the difference computed in node j's whitened
    coordinates (module docstring). Allocates: it runs only where the first test fails."""
    D, bound = improvement(F, w, j, covs, q, E + k, eta, trace, verify_work(F.shape[1]))
    return D + bound < 0.0


@jit
def _vertex(F, j, m_j, covs, q, E, k, vertex_j, pnorm, w, At, Vt, R, Ri, P, B, g, eta, trace,
            mean, cov, stats):
    """Node j's own estimate (mean, its modified covariance as given) and the certificate
    at e_j: the larger of the factors' and `factored.vertex_gap`'s, which holds for the
    covariances as given."""
    N, n = F.shape[0], m_j.size
    copy(mean, m_j)
    scaled(covs[j], q[j], E[j], cov)  # sym(P_j) / s_j in the original units
    evaluate_at(F, w, At, Vt, R, Ri, trace)
    gradient_at(F, Ri, P, B, g, trace)
    for i in range(N):
        eta[i] = _scale_error(q[i], E[i], N)
    gp = max(gap(g, w), vertex_gap(F, j, covs, q, E + k, eta, g, pnorm, trace))
    if trace:
        stats[0] = np.trace(cov)
        stats[1], stats[2] = np.ldexp(gp, k), gp / abs(vertex_j[0])
    else:
        stats[0] = vertex_j[1] + n * k * _LN2
        stats[1], stats[2] = gp, gp


@jit
def _fused_mean(F, means, w, Vt, Ri, rhs, mean, e: int):
    """mean (n,) = R^-1 (Q^T b)[:n], b = [sqrt(w_i) F_i m_i 2^-e] in the row order of the QR
    the buffers hold, times 2^e."""
    n = F.shape[1]
    unit = pow2(-e)
    r = 0
    for i in range(w.size):
        if w[i] > 0.0:
            root = np.sqrt(w[i])
            for a in range(n):
                t = 0.0
                for c in range(a + 1):
                    t += F[i, a, c] * (means[i, c] * unit)
                rhs[r + a] = root * t
            r += n
    apply_qt(Vt, n, r, rhs)
    for a in range(n):
        t = 0.0
        for c in range(a, n):
            t += Ri[a, c] * rhs[c]
        mean[a] = t if e == 0 else np.ldexp(t, e)


@jit
def fuse_at(F, means, k, W, trace: bool, mean, cov, obj, shares) -> int:
    """The CI formula at fixed weights W (B, N), each >= 0 and of any sum (the rules'
    weights: naive's are all 1), without the solver's certificate or best-vertex rule, on
    the factors F (B, N, n, n) of the covariances scaled by 2^-k (B,) (`prepare`): mean
    (B, n) and cov (B, n, n) = (sum_i w_i Y_i)^-1 in the input's units, obj (B,) the
    criterion at it, and the gain shares tr(K_i) / n = w_i |F_i R^-1|_F^2 / n (B, N).
    Returns the first problem whose Y(w) is not positive definite to rounding, or -1."""
    B, N, n = means.shape
    ws = work(N, n)
    for b in range(B):
        if not factor(F[b], W[b], ws.At, ws.Vt, ws.R, ws.Ri)[1]:
            return b
        _mean_at(F[b], means[b], W[b], ws.Vt, ws.Ri, ws.rhs, mean[b])
        _covariance_at(ws.Ri, ws.P)
        scaled(ws.P, 1.0, -k[b], cov[b])  # sym(P) 2^k: back to the input's units
        f = value(ws.R, ws.Ri, trace)
        obj[b] = np.ldexp(f, k[b]) if trace else f + n * k[b] * _LN2
        gradient_at(F[b], ws.Ri, ws.P, ws.B, ws.g, False)  # g_i = -|F_i R^-1|_F^2
        for i in range(N):
            shares[b, i] = -W[b, i] * ws.g[i] / n
    return -1


@jit
def _mean_at(F, means, w, Vt, Ri, rhs, mean):
    """`_fused_mean` at w, whose QR the buffers hold; where an intermediate overflows
    (means near 1.8e308), in units of a power of two near the largest mean, exact but for
    subnormals, which then do not matter."""
    _fused_mean(F, means, w, Vt, Ri, rhs, mean, 0)
    if not all_finite(mean):
        e = 0
        for i in range(w.size):
            for a in range(F.shape[1]):
                if w[i] > 0.0 and means[i, a] != 0.0:
                    e = max(e, math.frexp(means[i, a])[1])
        _fused_mean(F, means, w, Vt, Ri, rhs, mean, min(e, 1022))


@jit
def _covariance_at(Ri, P):
    """P = R^-1 R^-T."""
    if Ri.shape[0] <= SMALL:
        small_mul_t(Ri, Ri, P)
    else:
        matmul_t(Ri, Ri, P)


@jit
def _interior(F, means, k, w, Vt, R, Ri, P, B, g, rhs, trace, mean, cov, stats,
              graded: bool):
    """The fused estimate at w, whose factors the buffers hold (`_vertex_or_interior`),
    and whose gradient g holds when graded."""
    n = F.shape[1]
    _mean_at(F, means, w, Vt, Ri, rhs, mean)
    _covariance_at(Ri, P)
    scaled(P, 1.0, -k, cov)  # sym(P) 2^k: back to the original units
    f = value(R, Ri, trace)
    if not graded:
        gradient_at(F, Ri, P, B, g, trace)
    gp = gap(g, w)
    if trace:
        stats[0], stats[1], stats[2] = np.ldexp(f, k), np.ldexp(gp, k), gp / abs(f)
    else:
        stats[0], stats[1], stats[2] = f + n * k * _LN2, gp, gp
