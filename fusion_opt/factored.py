"""The CI weight problem in square-root form: objective, gradient, certificate and the
SQP model from factors, never from informations. Compiled.

Node i enters as F_i (n, n) with Y_i = P_i^-1 = F_i^T F_i (F_i = C_i^-1, P_i = C_i C_i^T).
At weights w the fused information is Y(w) = A^T A with A = [sqrt(w_i) F_i] (stacked over
the nodes with w_i > 0), so one QR, A = Q R, gives

    P(w) = R^-1 R^-T,    trace:  f = |R^-1|_F^2,    logdet:  f = -log det Y = -2 sum log |R_kk|,
    m(w) = argmin_m |A m - b|,  b = [sqrt(w_i) F_i m_i]   (= R^-1 Q^T b),

and with P = P(w) the gradient (DESIGN §1) is

    trace:  g_i = -tr(P Y_i P) = -|F_i P|_F^2,     logdet:  g_i = -tr(P Y_i) = -|F_i R^-1|_F^2.

Nothing inverts a covariance or forms Y(w): at condition 1e12 an inverted information
loses eps * cond = 1e-4 of its small eigenvalues, which carry the large covariances that
the trace is made of; the factors lose about eps * sqrt(cond) (measured against exact
rational arithmetic: 6.5e-12 relative where the information route lost 9e-6).

`objective_error` bounds the rounding error of f: the QR is backward stable in A, which
costs eps kappa(A), and the Cholesky factors of the inputs are exact for covariances
perturbed by eps |P_i|, which moves f by at most

    trace:   |df| / f <= c n eps (kappa(A) + sum_i w_i |P_i|_F |Y_i P|_F^2 / f)
    logdet:  |df|     <= c n eps (kappa(A) + sum_i w_i |P_i|_F |Y_i R^-1|_F^2)

The SQP model (backends/newton.py) whitens the nodes at w: with B_i = F_i R^-1,
X_i = B_i^T B_i (so sum_i w_i X_i = I), the Hessian is a Gram matrix, H_ij = z_i . z_j, and
g_i = -zeta . z_i, with

    logdet:  z_i = vec(X_i),                zeta = vec(I),               z(w) = zeta
    trace:   z_i = sqrt(2) vec(R^-1 X_i),   zeta = vec(R^-1) / sqrt(2),  z(w) = 2 zeta

(the SQP takes the "logdet" model in svec form, n (n + 1) / 2 coordinates: `model_view`)

(for "trace", H_ij = 2 tr(P Y_i P Y_j P) = 2 tr(X_i D X_j) with D = R^-T R^-1, and the
factor R^-T of D gives the Gram form without an eigendecomposition).

`improvement(F, w, j, ...)` computes the difference f(w) - f(e_j) in node j's whitened
coordinates with its own, much smaller, rounding bound (assemble.py's best-vertex rule
derives it).

Every routine works in buffers made once per batch (`work(N, n)`, a `Work`). The kernels
of each SQP step (`factor`, `value`, `evaluate_at`, `gradient_at`, `model_at`) take them as
separate arrays: a compiled call that is passed the whole `Work` tuple increfs and decrefs
each of its arrays, about 0.2 µs a call, as much as the QR itself at n = 4 (passing it
made `fuse_batch` 2.5 times slower at N = 3). The forms taking a `Work` (`factor_at`,
`objective`, `evaluate`, `gradient`, `model`) are for tests and calls once per problem.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from .linalg import (
    SMALL,
    cholesky,
    copy,
    gram,
    inline,
    jit,
    lower_inverse,
    matmul,
    matmul_t,
    node_mul,
    node_tmul,
    qr,
    small_gram,
    small_mul,
    small_mul_t,
    upper_inverse,
)
from .prepare import scaled

_SQRT2 = np.sqrt(2.0)
_EPS = np.finfo(np.float64).eps
_ERR_C = 8.0

# What a solver leaves in the buffers of a Work at the weights it returns (a state):
# FACTORED, the QR of `factor` (At, Vt, R, Ri); GRADED, also the gradient of `gradient_at`
# in g; 0, neither.
FACTORED, GRADED = 1, 2

Work = namedtuple("Work", [
    "At", "Vt", "R", "Ri", "P", "B", "X", "S", "lam", "U",  # QR (transposed) and n x n
    "zeta", "g", "Et",                                        # the SQP model
    "x", "z", "mask", "r", "cols", "Elt", "Vlt", "Rls", "qe", # the nearest point
    "w_try", "best_w", "rhs", "abc",                          # steps, means, pairs
])


@jit
def work(N: int, n: int) -> Work:
    """The buffers of one problem of N nodes in dimension n (stacks transposed: At holds
    A^T, Et the columns d_i of the nearest-point problem as rows). Buffers of one shape
    are rows of one allocation: an index view costs nothing, an allocation about 25 ns
    (13 allocations instead of 26: 0.51-0.70 against 0.66-0.86 us a call, of a pair's
    7 us compiled call at n = 4)."""
    m = n * n
    K = min(N, m + 1)
    stacks, squares = np.empty((2, n, N * n)), np.empty((7, n, n))
    nodes, coords, lsq = np.empty((5, N)), np.empty((2, m + 1)), np.empty((2, K, m + 1))
    Et = np.empty((N, m + 1))
    Et[:, m] = 1.0  # the simplex row of E: model() writes the entries before it
    return Work(stacks[0], stacks[1], squares[0], squares[1], squares[2], squares[3],
                squares[4], squares[5], np.empty(n), squares[6],
                np.empty(m), nodes[0], Et,
                nodes[1], nodes[2], np.zeros(N, dtype=np.bool_), coords[0],
                np.empty(N, dtype=np.int64), lsq[0], lsq[1],
                np.empty((K, K)), coords[1], nodes[3], nodes[4], np.empty(N * n),
                np.empty((3, n)))


@jit
def factor(F, w, At, Vt, R, Ri):
    """QR of A = [sqrt(w_i) F_i]: R, R^-1 in Ri, reflectors in Vt (At is overwritten);
    returns the number of rows of A and whether Y(w) is positive definite to rounding."""
    N, n = F.shape[0], F.shape[1]
    rows = 0
    for i in range(N):
        if w[i] > 0.0:
            r = np.sqrt(w[i])
            for a in range(n):
                for b in range(n):
                    At[b, rows + a] = r * F[i, a, b]
            rows += n
    qr(At, n, rows, Vt, R)
    for k in range(n):
        if not R[k, k] != 0.0 or not np.isfinite(R[k, k]):
            return rows, False
    upper_inverse(R, Ri)
    return rows, True


@jit
def value(R, Ri, trace: bool) -> float:
    """f at a point factored into R and Ri = R^-1."""
    n = R.shape[0]
    f = 0.0
    if trace:
        for i in range(n):
            for j in range(n):
                f += Ri[i, j] * Ri[i, j]
        return f
    for k in range(n):
        f -= 2.0 * np.log(abs(R[k, k]))
    return f


@jit
def evaluate_at(F, w, At, Vt, R, Ri, trace: bool):
    """(f, ok) at w, factored into the buffers; f = inf when Y(w) is not positive definite
    (a trial point a line search must reject)."""
    _, ok = factor(F, w, At, Vt, R, Ri)
    return (value(R, Ri, trace), True) if ok else (np.inf, False)


@jit
def gradient_at(F, Ri, G, B, g, trace: bool):
    """g = the gradient at the point factored into Ri (module docstring); G and B are
    n x n scratch."""
    small = F.shape[1] <= SMALL
    if trace:
        if small:
            small_mul_t(Ri, Ri, G)  # P = R^-1 R^-T
        else:
            matmul_t(Ri, Ri, G)
    else:
        copy(G, Ri)
    for i in range(F.shape[0]):
        if small:
            node_mul(F, i, G, B, not trace)  # G = R^-1 for "logdet"
        else:
            matmul(F[i], G, B)
        g[i] = -sumsq(B)


@jit
def factor_at(F, w, ws: Work):
    """`factor` into ws."""
    return factor(F, w, ws.At, ws.Vt, ws.R, ws.Ri)


@jit
def objective(ws: Work, trace: bool) -> float:
    """f at the point factored in ws."""
    return value(ws.R, ws.Ri, trace)


@jit
def evaluate(F, w, ws: Work, trace: bool):
    """`evaluate_at` into ws."""
    return evaluate_at(F, w, ws.At, ws.Vt, ws.R, ws.Ri, trace)


@jit
def gradient(F, ws: Work, trace: bool):
    """ws.g = the gradient at the point factored in ws."""
    gradient_at(F, ws.Ri, ws.P, ws.B, ws.g, trace)


@jit
def gap(g, w) -> float:
    """The certificate g.w - min_i g_i >= f(w) - f* (DESIGN §1), clipped at 0."""
    gw, low = 0.0, np.inf
    for i in range(g.size):
        gw += g[i] * w[i]
        low = min(low, g[i])
    return max(gw - low, 0.0)


@inline
def objective_error(F, w, R, Ri, G, B, X, pnorm, f, trace: bool) -> float:
    """The bound of the module docstring on the rounding error of f at the point factored
    into R, Ri (relative for "trace", absolute for "logdet"); pnorm (N,) holds |P_i|_F;
    G, B, X are n x n scratch."""
    n = F.shape[1]
    kappa = np.sqrt(sumsq(R) * sumsq(Ri))
    small = n <= SMALL
    if trace:
        if small:
            small_mul_t(Ri, Ri, G)
        else:
            matmul_t(Ri, Ri, G)
    else:
        copy(G, Ri)
    s = 0.0
    for i in range(F.shape[0]):
        if w[i] > 0.0:
            if small:
                node_mul(F, i, G, B, not trace)  # F_i G
                node_tmul(F, i, B, X)    # Y_i P, resp. Y_i R^-1
            else:
                matmul(F[i], G, B)
                matmul(F[i].T, B, X)
            s += w[i] * pnorm[i] * sumsq(X)
    return _ERR_C * n * _EPS * (kappa + (s / abs(f) if trace else s))


@inline
def vertex_error(F, pnorm, trace: bool) -> float:
    """The rounding error of a node's own objective: n eps relative for its trace (a sum),
    c n eps |P|_F |F|_F^2 absolute for its log det (a Cholesky factor)."""
    n = F.shape[0]
    if trace:
        return n * _EPS
    return _ERR_C * n * _EPS * pnorm * sumsq(F)


Verify = namedtuple("Verify", ["S", "C", "Ci", "aC", "Sig", "ESig", "B", "Eb", "L", "Li",
                               "Minv", "K", "H", "G", "T", "U", "U2", "V", "d"])


@jit
def verify_work(n: int) -> Verify:
    """The buffers of `improvement` in dimension n."""
    m = [np.empty((n, n)) for _ in range(18)]
    return Verify(m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10], m[11],
                  m[12], m[13], m[14], m[15], m[16], m[17], np.empty(n))


@inline
def improvement(F, w, j, covs, q, shift, eta, trace: bool, v: Verify):
    """(D, bound): D = f(w) - f(e_j) computed in node j's whitened coordinates, and a
    first-order bound on |D - D_exact|, D_exact that difference for the covariances covs
    (N, n, n) as given, divided by the detection scales q 2^shift (in scaled units; eta (N,)
    bounds each scale's relative error). assemble.py's docstring derives both. D = inf when
    the whitened problem cannot be formed (then nothing is verified)."""
    N, n = F.shape[0], F.shape[1]
    eps = _EPS
    C = v.C
    scaled(covs[j], q[j], shift[j], v.S)
    if not cholesky(v.S, C):
        return np.inf, np.inf
    for a in range(n):
        for b in range(n):
            v.aC[a, b] = abs(C[a, b])
            v.Sig[a, b] = 0.0
            v.ESig[a, b] = 0.0
    # Sigma = sum_{i != j} w_i (X_i - I) + (sum_i w_i - 1) I, X_i = B_i^T B_i, B_i = F_i C,
    # and ESig, a componentwise bound on its rounding
    for i in range(N):
        if i == j or not w[i] > 0.0:
            continue
        matmul(F[i], C, v.B)
        _absmul(F[i], v.aC, v.Eb)  # |F_i| |C| bounds the rounding of B_i / (n eps)
        for a in range(n):
            for b in range(a, n):
                x, e = 0.0, 0.0
                for r in range(n):
                    x += v.B[r, a] * v.B[r, b]
                    e += abs(v.B[r, a]) * v.Eb[r, b] + abs(v.B[r, b]) * v.Eb[r, a]
                if a == b:
                    x -= 1.0
                    e += 1.0
                sx = w[i] * x
                ex = w[i] * ((2 * n + 2) * eps * e + (N + 2) * eps * abs(x))
                v.Sig[a, b] += sx
                v.ESig[a, b] += ex
                if a != b:
                    v.Sig[b, a] += sx
                    v.ESig[b, a] += ex
    s1 = _sum_minus_one(w)
    for a in range(n):
        v.Sig[a, a] += s1
        v.ESig[a, a] += 2.0 * eps * abs(s1) + N * N * eps * eps
    if not _sigma_cholesky(v):
        return np.inf, np.inf
    lower_inverse(v.L, v.Li)
    gram(v.Li, v.Minv)  # M^-1 = L^-T L^-1, for the bounds
    if trace:
        D, err = _trace_difference(F[j], C, w[j], v)
        matmul_t(v.Minv, C, v.U)  # M^-1 C^T: F_i P = B_i U
        matmul(C, v.U, v.U2)      # P
    else:
        D, err = _logdet_difference(F[j], w[j], v)
        copy(v.U, v.Li.T)         # L^-T: Y_i P Y_i = (F_i^T B_i U)(...)^T
        matmul_t(v.Li, C, v.U2)   # L^-1 C^T: Y_i P = F_i^T B_i U U2
    # node j: C C^T = S_j + dS_j, |dS_j| <= (n + 3) eps |C| |C|^T (Cholesky, and forming S_j)
    err += _inner_abs_cct(C, v.G) * ((n + 3) * eps + eta[j]) + (n + 3) * 5e-324 * _sum_abs(v.G)
    for i in range(N):  # node i: the same for C_i, and F_i = C_i^-1 (I + R_i),
        if i == j or not w[i] > 0.0:  # |R_i| <= n eps |C_i| |F_i| (forward substitution)
            continue
        scaled(covs[i], q[i], shift[i], v.S)
        if not cholesky(v.S, v.Ci):
            return np.inf, np.inf
        matmul(F[i], C, v.B)
        matmul(v.B, v.U, v.V)     # F_i P, resp. F_i C L^-T
        _tmul(F[i], v.V, v.H)     # Y_i P, resp. F_i^T F_i C L^-T
        matmul_t(v.H, v.H, v.K)   # dD/dP_i / w_i: Y_i P^2 Y_i, resp. Y_i P Y_i
        matmul(v.H, v.U2, v.T)    # dD/dY_i... with R_i: Y_i P^2, resp. Y_i P
        _absmul(v.Ci, F[i], v.Eb)
        err += w[i] * (_inner_abs_cct(v.Ci, _abs_into(v.K)) * ((n + 3) * eps + eta[i])
                       + 2 * n * eps * _inner_abs(v.Eb, v.T))
    return D, 2.0 * err


@inline
def vertex_gap(F, j, covs, q, shift, eta, g, pnorm, trace: bool) -> float:
    """An upper bound, at first order, on the certificate at the vertex e_j for the
    covariances as given (divided by the exact detection scales q 2^shift; eta (N,) bounds
    each scale's relative error), in scaled units: max(0, max_i (g_j - g_i + beta_i)) with

        logdet:  g_j - g_i = tr(Y_i D_i),        trace:  g_j - g_i = tr(Y_i D_i P_j),

    D_i = P_j - P_i formed from the inputs, whose rounding is relative to D_i itself (a
    difference is correctly rounded), and Y_i from node i's factor F_i. The certificate
    from the factors (`gap`) holds for covariances within their Cholesky's backward error,
    which at condition 1e10 moved a log det by more than two nodes 1e-7 apart differ:
    the worse node came back with a gap of 0, 4e-7 nats short (fuzz Q1). Here F_i's error
    multiplies D_i: beta_i counts the rounding of D_i; the detection scales' errors, each
    a factor (1 + eta_i) on a whole covariance, which moves g_j - g_i by at most
    (eta_i + eta_j) |tr(Y_i P_j)| (log det), (eta_i + 2 eta_j) |tr(P_j Y_i P_j)| +
    eta_j tr(P_j) (trace); F_i as the inverse Cholesky factor of P_i (C_i C_i^T = P_i +
    E_i, |E_i| <= (n + 3) eps |C_i| |C_i|^T, F_i = C_i^-1 (I + R_i), |R_i| <= n eps |C_i|
    |F_i|: dY_i = -Y_i E_i Y_i + R_i^T Y_i + Y_i R_i); and the products; doubled, as
    `improvement`'s bound. P_i is the covariance as fused, sym(P_i) / q_i 2^shift_i as
    rounded (exact for a symmetric input without a detection scale): charged entry by
    entry, that rounding (eps |P_i|, first order like the Cholesky's) would cost eps cond
    in log det, and marked 75-80 % of MBCI results at condition >= 1e4 inaccurate whose
    exact certificate was below 1e-12 (fuzz R). A node that the factors' own gradient g
    (N,) at e_j already shows no better (`_settled`, from pnorm (N,), the covariances'
    Frobenius norms) is not formed: most nodes of most vertex results, which then allocate
    nothing. inf when a Cholesky factor cannot be formed."""
    for i in range(F.shape[0]):
        if i != j and not _settled(F, g, pnorm, eta, i, j):
            return _formed_gap(F, j, i, covs, q, shift, eta, g, pnorm, trace,
                               verify_work(F.shape[1]))
    return 0.0


@inline
def _formed_gap(F, j, first, covs, q, shift, eta, g, pnorm, trace: bool, v: Verify) -> float:
    """`vertex_gap` over the nodes not `_settled`, the first of them `first`, in the
    buffers v. Per node the smaller of two upper bounds: g_j - g_i formed from
    D_i = P_j - P_i (tight where P_i is near P_j), and its two terms apart,
    tr(P_j Y_i P_j) - tr(P_j) ("trace") or tr(Y_i P_j) - n ("logdet"), each with its own
    rounding (tight where P_i is far above P_j: at n = 64, condition 6.4e11 and nodes 1e22
    to 1e101 times the best one's scale, the first's bound was 0.02-0.66 of f(e_j) where
    the exact certificate is 0, a fuzz of 2026-11-28)."""
    N, n = F.shape[0], F.shape[1]
    u = _EPS
    Sj, S, D, Ci = v.U2, v.S, v.Sig, v.Ci
    scaled(covs[j], q[j], shift[j], Sj)
    own = np.trace(Sj) if trace else float(n)  # -g_j's exact value: tr(P_j) or n
    top = 0.0
    for i in range(first, N):
        if i == j or (i > first and _settled(F, g, pnorm, eta, i, j)):
            continue
        scaled(covs[i], q[i], shift[i], S)
        if not cholesky(S, Ci):
            return np.inf
        for a in range(n):
            for b in range(n):
                D[a, b] = Sj[a, b] - S[a, b]
        _tmul(F[i], F[i], v.G)        # Y_i
        _absmul(Ci, F[i], v.Eb)       # |C_i| |F_i|, bounds |R_i| / (n eps)
        if trace:
            matmul(v.G, Sj, v.V)      # Y_i P_j, also for `_product_bound`
            err = u * _inner_abs(D, v.V)                                   # D_i
        else:
            err = u * _inner_abs(D, v.G)                                   # D_i
        delta, e = _product_bound(F[i], Ci, D, Sj, trace, v)
        formed = delta + 2.0 * (err + e + _scales_bound(delta + own, own, eta, i, j, trace))
        t, e = _product_bound(F[i], Ci, Sj, Sj, trace, v)
        apart = t - own + 2.0 * (e + (n + 1) * u * (abs(t) + own)          # t - own
                                 + _scales_bound(t, own, eta, i, j, trace))
        if np.isfinite(formed) and np.isfinite(apart):
            formed = min(formed, apart)
        elif np.isfinite(apart):
            formed = apart
        bound = formed + (n + 3) * 5e-324 * n * n
        if not np.isfinite(bound):
            return np.inf
        top = max(top, bound)
    return top


@inline
def _scales_bound(t, own, eta, i: int, j: int, trace: bool) -> float:
    """How far the detection scales' errors (a factor 1 + eta_k on each whole covariance)
    move g_j - g_i, given t = tr(P_j Y_i P_j) ("trace") or tr(Y_i P_j) ("logdet") and own =
    tr(P_j) (`vertex_gap`'s docstring)."""
    if trace:
        return (eta[i] + 2.0 * eta[j]) * abs(t) + eta[j] * abs(own)
    return (eta[i] + eta[j]) * abs(t)


@inline
def _product_bound(Fi, Ci, X, Sj, trace: bool, v: Verify):
    """(t, err): t = tr(Y_i X P_j) ("trace") or tr(Y_i X) ("logdet") from node i's factor
    F_i (Y_i = F_i^T F_i in v.G, |C_i| |F_i| in v.Eb, and for "trace" Y_i P_j in v.V) for
    an X (n, n) taken as exact, and a first-order bound on its error from F_i's (E_i, R_i:
    `vertex_gap`'s docstring) and the products' rounding, not doubled. Overwrites v.H,
    v.K, v.T and v.U."""
    n = Fi.shape[0]
    u = _EPS
    matmul(v.G, X, v.H)           # Y_i X
    if trace:
        matmul(v.H, Sj, v.K)      # Y_i X P_j
        t = np.trace(v.K)
        matmul(v.K, v.G, v.T)     # Y_i X P_j Y_i
        err = (n + 3) * u * _inner_abs_cct(Ci, _abs_into(v.T))       # E_i
        matmul(v.V, X, v.T)       # Y_i P_j X
        err += n * u * (_inner_abs(v.Eb, v.K) + _inner_abs(v.Eb, v.T))  # R_i
        _absmul(Fi, X, v.T)
        _absmul(v.T, Sj, v.U)
        err += (n * n + 3 * n) * u * _inner_abs(v.U, Fi)             # products
        return t, err
    t = np.trace(v.H)
    matmul(v.H, v.G, v.T)         # Y_i X Y_i
    err = (n + 3) * u * _inner_abs_cct(Ci, _abs_into(v.T))           # E_i
    err += 2 * n * u * _inner_abs(v.Eb, v.H)                           # R_i
    _absmul(Fi, X, v.T)
    err += (n * n + 2 * n) * u * _inner_abs(v.T, Fi)                 # products
    return t, err


@jit
def _settled(F, g, pnorm, eta, i: int, j: int) -> bool:
    """Whether node i is verifiably no better than node j at the vertex e_j by the
    factors' gradient g alone: g_j - g_i + beta < 0, beta a first-order bound on the error
    of that difference for the covariances as fused. The factors are exact for covariances
    within E (Cholesky, |E| <= (n + 3) eps |C| |C|^T) and R (inversion, n eps |C| |F|),
    the QR of F_j is exact for F_j + dA (|dA| <= c n^2 eps |F_j|), the triangular inverse
    and the products round by c n eps componentwise; each moves g_i by at most
    c n^2 eps kappa |g_i| ("logdet": g_i = -tr(Y_i P_j), e.g. |tr(Y_i E_i Y_i P_j)| <=
    |E_i| |Y_i| |g_i|; "trace": g_i = -tr(P_j Y_i P_j) in the same way, P_j twice) and
    g_j by as much of |g_j|, with kappa = sqrt(n) (|P_i|_F |F_i|_F^2 + |P_j|_F |F_j|_F^2)
    >= cond(P_i) + cond(P_j); each scale's error eta moves them by at most 2 eta
    (|g_i| + |g_j|). beta = (16 (n + 3)^2 eps kappa + 4 (eta_i + eta_j)) (|g_i| + |g_j|),
    several times the sum of those terms. Only where first order holds (16 (n + 3)^2 eps
    kappa <= 1e-2) and nothing is near underflow (|F|_F^2 <= 1e280, so that an absolute
    rounding of 1e-323 is negligible beside the covariances' least eigenvalue; |g| >=
    1e-280); else False (`vertex_gap` forms the difference)."""
    n = F.shape[1]
    fi, fj = sumsq(F[i]), sumsq(F[j])
    rel = 16.0 * (n + 3) ** 2 * _EPS * np.sqrt(n) * (pnorm[i] * fi + pnorm[j] * fj)
    gi, gj = abs(g[i]), abs(g[j])
    if not (rel <= 1e-2 and fi <= 1e280 and fj <= 1e280 and min(gi, gj) >= 1e-280):
        return False
    return g[j] - g[i] + (rel + 4.0 * (eta[i] + eta[j])) * (gi + gj) < 0.0


@inline
def _trace_difference(Fj, C, wj, v: Verify):
    """D = -tr(K M^-1 Sigma), K = C^T C, and the bound on the rounding from Sigma on (before
    the factor 2 of `improvement`); leaves in v.G the sensitivity to node j's covariance,
    F_j^T (w_j H - K) F_j (H = M^-1 K M^-1), enlarged by its own rounding."""
    n = C.shape[0]
    eps = _EPS
    copy(v.V, v.Sig)  # Z = M^-1 Sigma by substitution with L and L^T, column by column
    for c in range(n):
        for a in range(n):
            t = v.V[a, c]
            for p in range(a):
                t -= v.L[a, p] * v.V[p, c]
            v.V[a, c] = t / v.L[a, a]
        for a in range(n - 1, -1, -1):
            t = v.V[a, c]
            for p in range(a + 1, n):
                t -= v.L[p, a] * v.V[p, c]
            v.V[a, c] = t / v.L[a, a]
    _tmul(C, C, v.K)
    D = 0.0
    for a in range(n):
        for b in range(n):
            D -= v.V[a, b] * v.K[a, b]
    _abs_gram(C, v.G)  # |C|^T |C| bounds |K| and its rounding
    err = (n * n + n) * eps * _inner_abs(v.V, v.G)
    matmul(v.Minv, v.K, v.B)   # M^-1 K
    matmul(v.B, v.Minv, v.H)   # H = M^-1 K M^-1
    err += _inner_abs(v.ESig, v.H)
    _abs_gram(v.L.T, v.T)  # the solves are exact for M + dM_c, |dM_c| <= (3n+1) eps |L||L^T|
    _absmul(v.T, v.V, v.Eb)
    err += (3 * n + 1) * eps * _inner_abs(v.Eb, v.B)
    for a in range(n):
        for b in range(n):
            v.T[a, b] = wj * v.H[a, b] - v.K[a, b]
            v.Eb[a, b] = wj * abs(v.H[a, b]) + v.G[a, b]
    _sensitivity(Fj, v)
    return D, err


@inline
def _logdet_difference(Fj, wj, v: Verify):
    """D = -log det(I + Sigma) = -sum_k log1p(d_k) from the Cholesky factor of I + Sigma
    with its pivots 1 + d_k, and the bound on the rounding from Sigma on; leaves in v.G the
    sensitivity to node j's covariance, F_j^T (w_j M^-1 - I) F_j."""
    n = Fj.shape[0]
    eps = _EPS
    D, logs = 0.0, 0.0
    for k in range(n):
        t = np.log1p(v.d[k])
        D -= t
        logs += abs(t)
    err = _inner_abs(v.ESig, v.Minv) + (n + 2) * eps * (_inner_abs(v.T, v.Minv) + logs)
    for a in range(n):
        for b in range(n):
            v.T[a, b] = wj * v.Minv[a, b] - (1.0 if a == b else 0.0)
            v.Eb[a, b] = wj * abs(v.Minv[a, b]) + (1.0 if a == b else 0.0)
    _sensitivity(Fj, v)
    return D, err


@jit
def _sensitivity(Fj, v: Verify):
    """v.G = |F_j^T T F_j| + (2n + 2) eps |F_j|^T Eb |F_j| for T = v.T, Eb = v.Eb."""
    n = Fj.shape[0]
    matmul(v.T, Fj, v.K)
    _tmul(Fj, v.K, v.G)
    _absmul(v.Eb, Fj, v.V)
    for a in range(n):
        for b in range(n):
            t = 0.0
            for p in range(n):
                t += abs(Fj[p, a]) * v.V[p, b]
            v.G[a, b] = abs(v.G[a, b]) + (2 * n + 2) * _EPS * t


@inline
def _sigma_cholesky(v: Verify) -> bool:
    """Cholesky factor v.L of M = I + Sigma with pivots L_kk^2 = 1 + d_k, d_k kept apart
    (v.d), so that log det M = sum log1p(d_k) keeps the digits of a small Sigma; v.T bounds
    its backward error: L' L'^T = M + dM, L' = L with the diagonal sqrt(1 + d_k) exactly,
    |dM| <= (n + 2) eps T. False if M is not positive definite."""
    n = v.L.shape[0]
    L, T, S = v.L, v.T, v.Sig
    for k in range(n):
        d, t = S[k, k], abs(S[k, k])
        for p in range(k):
            d -= L[k, p] * L[k, p]
            t += L[k, p] * L[k, p]
        if not 1.0 + d > 0.0 or not np.isfinite(d):
            return False
        v.d[k] = d
        lkk = np.sqrt(1.0 + d)
        L[k, k] = lkk
        T[k, k] = t
        for i in range(k):
            L[i, k] = 0.0
        for i in range(k + 1, n):
            s, t = S[i, k], abs(S[i, k])
            for p in range(k):
                s -= L[i, p] * L[k, p]
                t += abs(L[i, p] * L[k, p])
            L[i, k] = s / lkk
            T[i, k] = T[k, i] = t + abs(L[i, k]) * lkk
    return True


@inline
def _sum_minus_one(w) -> float:
    """sum_i w_i - 1, compensated (Neumaier): the weights sum to 1 within a few ulps, and
    that difference enters D as it is."""
    s, c = -1.0, 0.0
    for i in range(w.size):
        t = s + w[i]
        if abs(s) >= abs(w[i]):
            c += (s - t) + w[i]
        else:
            c += (w[i] - t) + s
        s = t
    return s + c


@jit
def _absmul(A, B, out):
    """out = |A| |B|."""
    for a in range(A.shape[0]):
        for b in range(B.shape[1]):
            t = 0.0
            for p in range(A.shape[1]):
                t += abs(A[a, p]) * abs(B[p, b])
            out[a, b] = t


@jit
def _abs_gram(A, out):
    """out = |A|^T |A|."""
    n = A.shape[1]
    for a in range(n):
        for b in range(n):
            t = 0.0
            for p in range(A.shape[0]):
                t += abs(A[p, a]) * abs(A[p, b])
            out[a, b] = t


@jit
def _tmul(A, B, out):
    """out = A^T B."""
    for a in range(A.shape[1]):
        for b in range(B.shape[1]):
            t = 0.0
            for p in range(A.shape[0]):
                t += A[p, a] * B[p, b]
            out[a, b] = t


@jit
def _inner_abs(A, B) -> float:
    """sum_ab |A_ab| |B_ab|."""
    t = 0.0
    for a in range(A.shape[0]):
        for b in range(A.shape[1]):
            t += abs(A[a, b]) * abs(B[a, b])
    return t


@jit
def _inner_abs_cct(C, G) -> float:
    """sum_ab (|C| |C|^T)_ab G_ab."""
    n = C.shape[0]
    t = 0.0
    for a in range(n):
        for b in range(n):
            s = 0.0
            for p in range(n):
                s += abs(C[a, p]) * abs(C[b, p])
            t += s * G[a, b]
    return t


@jit
def _abs_into(A):
    """A <- |A|, returned."""
    for a in range(A.shape[0]):
        for b in range(A.shape[1]):
            A[a, b] = abs(A[a, b])
    return A


@inline
def _sum_abs(A) -> float:
    t = 0.0
    for a in range(A.shape[0]):
        for b in range(A.shape[1]):
            t += abs(A[a, b])
    return t


@jit
def model_at(F, Ri, zeta, Et, g, B, X, S, trace: bool, rho: float):
    """The SQP model at the point factored into Ri: g the gradient, and the columns
    d_i = W z_i - (rho c + 1/rho) zeta of the nearest-point problem in Et[i, :m]
    (W = I - (1 - rho) u u^T, u = zeta / |zeta|; backends/newton.py), Et[i, m] = 1; B, X, S
    are n x n scratch. m = Et.shape[1] - 1 is n^2 (z_i as in the module docstring) or, for
    "logdet" only, n (n + 1) / 2 (`model_view`): X_i is symmetric, and z_i = svec(X_i)
    (`svec.py`'s coordinates, the diagonal first; the order does not matter here),
    has the same Gram matrix in fewer coordinates (at (n, N) = (6, 16) the nearest point
    in 22 instead of 37 dimensions)."""
    N, n = F.shape[0], F.shape[1]
    m = Et.shape[1] - 1
    c = 2.0 if trace else 1.0
    small = n <= SMALL
    if not trace and m < n * n:
        for i in range(N):
            _whitened(F, i, Ri, B, X, small)
            gi = 0.0
            for a in range(n):
                gi -= X[a, a]
            g[i] = gi
            # zeta = svec(I): |zeta|^2 = n; as below
            shift = (1.0 - rho) / n * gi - (rho * c + 1.0 / rho)
            for a in range(n):
                Et[i, a] = X[a, a] + shift
            p = n
            for a in range(n):
                for b in range(a + 1, n):
                    Et[i, p] = _SQRT2 * X[a, b]
                    p += 1
            Et[i, m] = 1.0
        return
    zz = 0.0
    for a in range(n):
        for b in range(n):
            z = Ri[a, b] / _SQRT2 if trace else (1.0 if a == b else 0.0)
            zeta[a * n + b] = z
            zz += z * z
    for i in range(N):
        _whitened(F, i, Ri, B, X, small)
        Z = X
        if trace:
            if small:
                small_mul(Ri, X, S, True)
            else:
                matmul(Ri, X, S)
            Z = S
        scale = _SQRT2 if trace else 1.0
        gi = 0.0
        for a in range(n):
            for b in range(n):
                z = scale * Z[a, b]
                Et[i, a * n + b] = z
                gi -= zeta[a * n + b] * z
        g[i] = gi
        # W z_i = z_i - (1 - rho)(u . z_i) u, u . z_i = -g_i / |zeta|; minus the target
        shift = (1.0 - rho) / zz * gi - (rho * c + 1.0 / rho)
        for p in range(m):
            Et[i, p] += zeta[p] * shift
        Et[i, m] = 1.0


@inline
def model_view(Et, N: int, n: int, trace: bool):
    """The rows of the nearest-point problem that `model_at` fills: Et (N, n^2 + 1) itself
    for "trace", for "logdet" its first N (n (n + 1) / 2 + 1) entries as an (N, n (n + 1) /
    2 + 1) array (svec; a view, contiguous, so the same compiled kernels)."""
    if trace:
        return Et
    ms = n * (n + 1) // 2
    return Et.reshape(Et.size)[:N * (ms + 1)].reshape((N, ms + 1))


@jit
def _whitened(F, i, Ri, B, X, small: bool):
    """X = B^T B, B = F_i R^-1: node i whitened at the point factored into Ri."""
    if small:
        node_mul(F, i, Ri, B, True)
        small_gram(B, X)
    else:
        matmul(F[i], Ri, B)
        gram(B, X)


@jit
def model(F, ws: Work, trace: bool, rho: float):
    """`model_at` into ws (ws.g, ws.Et)."""
    model_at(F, ws.Ri, ws.zeta, ws.Et, ws.g, ws.B, ws.X, ws.S, trace, rho)


@jit
def sumsq(X) -> float:
    """The sum of the squares of the entries of X (2-D)."""
    t = 0.0
    for i in range(X.shape[0]):
        for j in range(X.shape[1]):
            t += X[i, j] * X[i, j]
    return t
