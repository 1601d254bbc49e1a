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

(for "trace", H_ij = 2 tr(P Y_i P Y_j P) = 2 tr(X_i D X_j) with D = R^-T R^-1, and the
factor R^-T of D gives the Gram form without an eigendecomposition).

Every routine works in a `Work` of buffers made once per problem (`work(N, n)`).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from .linalg import copy, gram, householder, jit, matmul, matmul_t, upper_inverse

_SQRT2 = np.sqrt(2.0)
_EPS = np.finfo(np.float64).eps
_ERR_C = 8.0

Work = namedtuple("Work", [
    "At", "Vt", "R", "Ri", "P", "B", "X", "S", "lam", "U",  # QR (transposed) and n x n
    "zeta", "g", "Et",                                        # the SQP model
    "x", "z", "mask", "r", "cols", "Elt", "Vlt", "Rls",       # the nearest point
    "w_try", "best_w", "rhs",                                 # steps, means
])


@jit
def work(N: int, n: int) -> Work:
    """The buffers of one problem of N nodes in dimension n (stacks transposed: At holds
    A^T, Et the columns d_i of the nearest-point problem as rows)."""
    m = n * n
    K = min(N, m + 1)
    Et = np.empty((N, m + 1))
    Et[:, m] = 1.0  # the simplex row of E: model() writes the entries before it
    return Work(np.empty((n, N * n)), np.empty((n, N * n)), np.empty((n, n)),
                np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)),
                np.empty((n, n)), np.empty(n), np.empty((n, n)),
                np.empty(m), np.empty(N), Et,
                np.empty(N), np.empty(N), np.zeros(N, dtype=np.bool_), np.empty(m + 1),
                np.empty(N, dtype=np.int64), np.empty((K, m + 1)), np.empty((K, m + 1)),
                np.empty((K, K)), np.empty(N), np.empty(N), np.empty(N * n))


@jit
def factor_at(F, w, ws: Work):
    """QR of A = [sqrt(w_i) F_i] into ws (R, R^-1 in Ri, reflectors in Vt); returns the
    number of rows of A and whether Y(w) is positive definite to rounding."""
    N, n = F.shape[0], F.shape[1]
    rows = 0
    for i in range(N):
        if w[i] > 0.0:
            r = np.sqrt(w[i])
            for a in range(n):
                for b in range(n):
                    ws.At[b, rows + a] = r * F[i, a, b]
            rows += n
    householder(ws.At, n, rows, ws.Vt, ws.R)
    for k in range(n):
        if not ws.R[k, k] != 0.0 or not np.isfinite(ws.R[k, k]):
            return rows, False
    upper_inverse(ws.R, ws.Ri)
    return rows, True


@jit
def objective(ws: Work, trace: bool) -> float:
    """f at the point factored in ws."""
    n = ws.R.shape[0]
    f = 0.0
    if trace:
        for i in range(n):
            for j in range(n):
                f += ws.Ri[i, j] * ws.Ri[i, j]
        return f
    for k in range(n):
        f -= 2.0 * np.log(abs(ws.R[k, k]))
    return f


@jit
def evaluate(F, w, ws: Work, trace: bool):
    """(f, ok) at w, factored into ws; f = inf when Y(w) is not positive definite (a trial
    point a line search must reject)."""
    _, ok = factor_at(F, w, ws)
    return (objective(ws, trace), True) if ok else (np.inf, False)


@jit
def gradient(F, ws: Work, trace: bool):
    """ws.g = the gradient at the point factored in ws (module docstring)."""
    G = ws.P
    if trace:
        matmul_t(ws.Ri, ws.Ri, G)  # P = R^-1 R^-T
    else:
        copy(G, ws.Ri)
    for i in range(F.shape[0]):
        matmul(F[i], G, ws.B)
        ws.g[i] = -_sumsq(ws.B)


@jit
def gap(g, w) -> float:
    """The certificate g.w - min_i g_i >= f(w) - f* (DESIGN §1), clipped at 0."""
    gw, low = 0.0, np.inf
    for i in range(g.size):
        gw += g[i] * w[i]
        low = min(low, g[i])
    return max(gw - low, 0.0)


@jit
def objective_error(F, w, ws: Work, pnorm, f, trace: bool) -> float:
    """The bound of the module docstring on the rounding error of f at the point factored
    in ws (relative for "trace", absolute for "logdet"); pnorm (N,) holds |P_i|_F."""
    n = F.shape[1]
    kappa = np.sqrt(_sumsq(ws.R) * _sumsq(ws.Ri))
    G = ws.P
    if trace:
        matmul_t(ws.Ri, ws.Ri, G)
    else:
        copy(G, ws.Ri)
    s = 0.0
    for i in range(F.shape[0]):
        if w[i] > 0.0:
            matmul(F[i], G, ws.B)           # F_i G
            matmul(F[i].T, ws.B, ws.X)      # Y_i P, resp. Y_i R^-1
            s += w[i] * pnorm[i] * _sumsq(ws.X)
    return _ERR_C * n * _EPS * (kappa + (s / abs(f) if trace else s))


@jit
def vertex_error(F, pnorm, trace: bool) -> float:
    """The rounding error of a node's own objective: n eps relative for its trace (a sum),
    c n eps |P|_F |F|_F^2 absolute for its log det (a Cholesky factor)."""
    n = F.shape[0]
    if trace:
        return n * _EPS
    return _ERR_C * n * _EPS * pnorm * _sumsq(F)


@jit
def model(F, ws: Work, trace: bool, rho: float):
    """The SQP model at the point factored in ws: ws.g the gradient, and the columns
    d_i = W z_i - (rho c + 1/rho) zeta of the nearest-point problem in ws.Et[i, :n^2]
    (W = I - (1 - rho) u u^T, u = zeta / |zeta|; backends/newton.py)."""
    N, n = F.shape[0], F.shape[1]
    m = n * n
    c = 2.0 if trace else 1.0
    zz = 0.0
    for a in range(n):
        for b in range(n):
            z = ws.Ri[a, b] / _SQRT2 if trace else (1.0 if a == b else 0.0)
            ws.zeta[a * n + b] = z
            zz += z * z
    for i in range(N):
        matmul(F[i], ws.Ri, ws.B)
        gram(ws.B, ws.X)
        Z = ws.X
        if trace:
            matmul(ws.Ri, ws.X, ws.S)
            Z = ws.S
        scale = _SQRT2 if trace else 1.0
        d = ws.Et[i]
        gi = 0.0
        for a in range(n):
            for b in range(n):
                z = scale * Z[a, b]
                d[a * n + b] = z
                gi -= ws.zeta[a * n + b] * z
        ws.g[i] = gi
        # W z_i = z_i - (1 - rho)(u . z_i) u, u . z_i = -g_i / |zeta|; minus the target
        shift = (1.0 - rho) / zz * gi - (rho * c + 1.0 / rho)
        for p in range(m):
            d[p] += ws.zeta[p] * shift


@jit
def _sumsq(X) -> float:
    t = 0.0
    for i in range(X.shape[0]):
        for j in range(X.shape[1]):
            t += X[i, j] * X[i, j]
    return t
