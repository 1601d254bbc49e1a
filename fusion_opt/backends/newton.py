"""Newton methods on the weight simplex: exact and native, batched (`solve`) and for one
problem (`solve_one`, sequential quadratic programming; see its docstring).

`solve` minimises a CI criterion f(w) over {w >= 0, sum w = 1} with the analytic gradient g
and Hessian H of `criteria.py`. It starts at the best single node (or a given start) and works
on the support S (the free weights): the step is the Newton step of the face,
d = -pinv(Z H Z) Z g with Z the projector onto {d : sum d = 0, d_i = 0 off S}; the
pseudo-inverse (by eigh) keeps it exact when H is singular (N > n(n+1)/2, where the weights
are not unique and a plain Newton solve stalls). A ratio test keeps w >= 0 (a weight that
reaches 0 leaves S) and Armijo backtracking keeps the descent monotone far from the optimum.
Once S is optimal on its face, the node with the most negative reduced cost joins S.
It stops on the certificate gap(w) <= tol (relative to f for "trace"; absolute for
"logdet", where it bounds log det P(w) - log det P*), not on an iteration count.
All problems of a batch advance together with masks; H is formed on the support only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack
from scipy.optimize import nnls

from .. import svec
from ..criteria import evaluate, gap
from ..results import FusionSolverError
from ..simplex import to_simplex

TOL = 1e-13
_PINV_RTOL = 1e-11
_ARMIJO = 1e-4
_GROW_RATIO = 0.1
# A predicted decrease below this times |f| is under the rounding of f: Armijo cannot see it.
_FLAT = 1e3 * np.finfo(float).eps
# sqrt of the model's curvature along the whitened gradient, relative to f's own (1), and
# below which relative gap it is f's own again.
_RHO = 0.1
_LOCAL = 1e-4
# Steps without a better certificate in the local phase after which `solve_one` stops.
_STALL = 5
# Wolfe's optimality test of a face, relative to the largest |d_i . p|; and from how many
# nodes on the face is tried before NNLS (measured faster from 32 to 64 nodes, slower at 16).
_WOLFE_RTOL = 1e-12
_FACE_MIN_NODES = 32


@dataclass(frozen=True)
class NewtonSolution:
    """w (B, N) on the simplex, rel_gap (B,) the certificate relative as in the module
    docstring, iterations (B,), converged (B,) whether rel_gap <= tol was reached."""

    w: np.ndarray
    rel_gap: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray


def relative_gap(f, g, w, criterion):
    """gap(w), divided by |f| for "trace" (scale-free there), as is for "logdet"."""
    gp = gap(g, w)
    return gp / np.abs(f) if criterion == "trace" else gp


def best_vertex(Ys, M, criterion) -> np.ndarray:
    """One-hot weights (B, N) of the best single node: f(e_i) for every i at once."""
    nb, N = Ys.shape[:2]
    eye = np.broadcast_to(np.eye(N), (nb, N, N))
    Ms = None if M is None else np.broadcast_to(M[:, None], (nb, N, *M.shape[1:]))
    f = evaluate(Ys[:, None], eye, criterion, Ms).f  # (B, N)
    return np.eye(N)[np.argmin(f, axis=-1)]


def solve(Ys, M, criterion, w0=None, tol=TOL, max_iter=None) -> NewtonSolution:
    """Ys (B, N, n, n) and M (B, n, n) of a scaled problem; w0 (B, N) a start near the
    simplex (the best vertex if None). max_iter defaults to 50 + 4 N, a guard only."""
    nb, N = Ys.shape[:2]
    w = best_vertex(Ys, M, criterion) if w0 is None else to_simplex(w0)
    support = w > 0
    iters = np.zeros(nb, dtype=int)
    rel = np.full(nb, np.inf)
    todo = np.arange(nb)
    for _ in range(max_iter or 50 + 4 * N):
        ev = evaluate(Ys[todo], w[todo], criterion, M[todo])
        rel[todo] = relative_gap(ev.f, ev.g, w[todo], criterion)
        keep = rel[todo] > tol
        todo, ev = todo[keep], type(ev)(ev.f[keep], ev.g[keep], None)
        if todo.size == 0:
            break
        iters[todo] += 1
        _grow_support(support, todo, ev, w, criterion, tol)
        sup = support[todo]
        nodes, sub = _compress(sup)
        H = evaluate(Ys[todo], w[todo], criterion, M[todo], hessian=True, nodes=nodes).H
        d_sub = _face_newton_step(H, _at(ev.g, nodes), sub, _at(w[todo], nodes))
        d = np.zeros_like(sup, dtype=float)
        np.put_along_axis(d, nodes, d_sub, axis=-1)
        w[todo], support[todo] = _line_search(Ys[todo], M[todo], criterion, w[todo], d, ev,
                                              sup, tol)
    return NewtonSolution(w, rel, iters, rel <= tol)


def _at(a, nodes):
    return np.take_along_axis(a, nodes, axis=-1)


def _compress(sup):
    """Support indices first: nodes (b, k) for k = the largest support, sub (b, k) mask."""
    k = int(sup.sum(-1).max())
    nodes = np.argsort(~sup, axis=-1, kind="stable")[:, :k]
    return nodes, _at(sup, nodes)


def _grow_support(support, todo, ev, w, criterion, tol):
    """Where the gap on the face of S is small beside the whole gap (or within tol), the
    nodes off S dominate what is left to gain: add the one of most negative reduced cost."""
    sup = support[todo]
    gw = (ev.g * w[todo]).sum(-1)
    face_gap = gw - np.where(sup, ev.g, np.inf).min(-1)
    scale = np.abs(ev.f) if criterion == "trace" else 1.0
    grow = face_gap <= np.maximum(tol * scale, _GROW_RATIO * (gw - ev.g.min(-1)))
    j = np.argmin(ev.g, axis=-1)
    support[todo[grow], j[grow]] = True


def _face_newton_step(H, g, sup, w):
    """Minimum-norm Newton step on the face: H (b, k, k), g (b, k), sup (b, k) bool."""
    k = sup.sum(-1, keepdims=True)
    s = sup.astype(float)
    Z = np.eye(sup.shape[-1]) * s[:, None, :] - s[:, :, None] * s[:, None, :] / k[..., None]
    R = Z @ H @ Z
    lam, V = np.linalg.eigh(0.5 * (R + np.swapaxes(R, -1, -2)))
    inv = np.where(lam > _PINV_RTOL * lam[:, -1:], 1.0 / np.where(lam > 0, lam, 1.0), 0.0)
    zg = np.where(sup, (Z @ g[..., None])[..., 0], 0.0)
    d = -(V @ (inv[..., None] * (np.swapaxes(V, -1, -2) @ zg[..., None])))[..., 0]
    d = np.where(sup, d, 0.0)  # exact zeros off S, not rounding residue of Z
    d -= s * (d.sum(-1, keepdims=True) / k)  # and sum(d) = 0 on S
    # A node that just joined S at weight 0 must be able to enter: where the Newton step
    # would push it out, use the projected gradient, which moves it in.
    stuck = ((w <= 0) & sup & (d < 0)).any(-1)
    d[stuck] = -zg[stuck]
    return d


def _line_search(Ys, M, criterion, w, d, ev, sup, tol):
    """Ratio test and Armijo backtracking; returns the new weights and support."""
    neg = d < 0
    ratio = np.where(neg, w / np.where(neg, -d, 1.0), np.inf)
    t_max = np.minimum(ratio.min(-1), 1.0)
    slope = (ev.g * d).sum(-1)  # < 0 for a descent direction
    scale = np.abs(ev.f) if criterion == "trace" else 1.0
    t = t_max.copy()
    # Near the optimum the decrease is below the rounding of f: take the full step there.
    pending = -slope > tol * scale * 1e-3
    for _ in range(60):
        if not pending.any():
            break
        idx = np.flatnonzero(pending)
        w_try = np.maximum(w[idx] + t[idx, None] * d[idx], 0.0)
        f_try = evaluate(Ys[idx], w_try, criterion, M[idx]).f
        ok = f_try <= ev.f[idx] + _ARMIJO * t[idx] * slope[idx]
        pending[idx[ok]] = False
        t[idx[~ok]] *= 0.5
    w_new = w + t[:, None] * d
    blocked = (t == t_max)[:, None] & neg & (ratio <= t_max[:, None])
    w_new[blocked] = 0.0
    sup = sup & ~blocked & (w_new > 0)
    return to_simplex(w_new), sup


def solve_one(Ys, M, criterion, w0=None, tol=TOL, max_iter=None) -> NewtonSolution:
    """One problem, Ys (N, n, n) and M (n, n), by sequential quadratic programming: Newton's
    method with the simplex kept in the subproblem. Returns arrays of batch size 1.

    At w, with Y(w) = U^T U, whiten every node: z_i = svec(R^T Y_i R) * s (N, m), where
    R = U^-1 and s = 1 for "logdet", and for "trace" R = U^-1 V and s_kl = sqrt(mu_k + mu_l)
    with U^-T M U^-1 = V diag(mu) V^T. Then H_ij = z_i . z_j and g_i = -zeta . z_i
    (zeta = svec(I) for "logdet", svec(diag(sqrt(mu / 2))) for "trace"), and R^T Y(w) R = I
    puts z(w) = c zeta (c = 1, resp. 2), so the quadratic model of f about w is

        f(lam) ~ f(w) + |W (z(lam) - z(w)) - zeta / rho|^2 / 2 + const,   z(lam) = sum lam_i z_i,

    with W = I - (1 - rho) u u^T, u = zeta / |zeta|. rho = 1 would be Newton's model of f;
    f is homogeneous in Y (f(tY) = f/t, resp. f - n log t), and along u, where that
    nonlinearity lives, Newton's model is poor far from the optimum: rho = 0.1 keeps 1% of its
    curvature there (the Hessian of h = -1/f, resp. -exp(-f/n), has none). At the optimum u is
    orthogonal to the face, so the local convergence stays quadratic; below a relative gap of
    1e-4 it uses rho = 1, whose nearest-point problem is the best conditioned. The minimiser
    over the simplex is the point of the polytope conv{W z_i} nearest to c rho zeta + zeta/rho
    (`_nearest`); its support has at most m + 1 nodes whatever N. w moves towards it with
    Armijo backtracking on f. It stops on the certificate as `solve` does, or unconverged when
    5 steps in the local phase have not improved it (rounding level). Starts at w0 or uniform
    weights (where the scaled Y'(w) = I).
    """
    N, n = Ys.shape[:2]
    pb = _prepare(Ys, M, criterion)
    w = np.full(N, 1.0 / N) if w0 is None else to_simplex(w0)
    f, Ui = _value(pb, w)
    it, limit, rel, best, stalled = 0, max_iter or 50 + 4 * N, np.inf, np.inf, 0
    while True:
        # Near the optimum, Newton's own model: its nearest-point problem is the best
        # conditioned, and the damping along u no longer matters there.
        g = _model(pb, Ui, 1.0 if rel <= _LOCAL else _RHO)
        rel = max(float(g @ w - g.min()), 0.0) / (abs(f) if pb.trace else 1.0)
        # far from the optimum the certificate need not fall at every step; near it, it does
        best, stalled = (rel, 0) if rel < best else (best, stalled + (best <= _LOCAL))
        if rel <= tol or it == limit or stalled == _STALL:  # the last: at rounding level
            break
        it += 1
        w, f, Ui = _step_towards(pb, w, _nearest(pb.E, w), f, g)
    one = np.ones(1)
    return NewtonSolution(w[None], rel * one, it * one.astype(int), (rel <= tol) * one > 0)


@dataclass(frozen=True)
class _Problem:
    """One problem prepared once: Yf (N, n*n) rows vec(Y_i), YsvT (m, N) columns svec(Y_i),
    M (n, n), B (n, n) its Cholesky factor ("trace"), T the svec basis, diagonal positions,
    zeta of "logdet" (None for "trace"), and E (m + 1, N), whose first m rows each step
    overwrites with the d_i of `_nearest` and whose last row is ones."""

    Yf: np.ndarray
    YsvT: np.ndarray
    M: np.ndarray
    B: np.ndarray | None
    T: np.ndarray
    diag: np.ndarray
    zeta: np.ndarray | None
    E: np.ndarray

    @property
    def trace(self) -> bool:
        return self.zeta is None


def _prepare(Ys, M, criterion) -> _Problem:
    N, n = Ys.shape[:2]
    i, j = svec.upper(n)
    diag = np.flatnonzero(i == j)
    trace = criterion == "trace"
    zeta = None
    if not trace:
        zeta = np.zeros(len(i))
        zeta[diag] = 1.0  # svec(I)
    E = np.ones((len(i) + 1, N))
    return _Problem(Ys.reshape(N, n * n), np.ascontiguousarray((Ys[:, i, j] * svec.scale(n)).T),
                    M, lapack.dpotrf(M, lower=1)[0] if trace else None, svec.basis(n), diag,
                    zeta, E)


def _value(pb, w):
    """f(w) and U^-1 (Y(w) = U^T U); f = inf where Y(w) is not positive definite to
    rounding (a trial point the line search must reject)."""
    n = len(pb.M)
    U, info = lapack.dpotrf((w @ pb.Yf).reshape(n, n))
    if info:
        return np.inf, None
    Ui = lapack.dtrtri(U)[0]
    if pb.trace:
        C = pb.B.T @ Ui
        return float(np.vdot(C, C)), Ui  # tr(M P) = |B^T U^-1|_F^2
    return -2.0 * float(np.log(U.diagonal()).sum()), Ui


def _model(pb, Ui, rho):
    """g (N,); writes the rows d_i = W z_i - zhat' of `_nearest` (the docstring of
    `solve_one`) into the first m rows of pb.E, as columns."""
    if pb.trace:
        mu, V = lapack.dsyevd(Ui.T @ pb.M @ Ui)[:2]
        R = Ui @ V
        i, j = svec.upper(len(mu))
        s = np.sqrt(mu[i] + mu[j])[:, None]
        zeta = np.zeros(len(i))
        zeta[pb.diag] = np.sqrt(0.5 * mu)
        c = 2.0  # z(w) = svec(I) * s = 2 zeta, since R^T Y(w) R = I
    else:
        R, s, zeta, c = Ui, 1.0, pb.zeta, 1.0  # z(w) = svec(I) = zeta
    # svec(R^T X R) = T^T (R^T kron R^T) T svec(X)
    Rt = R.T
    C = pb.T.T @ (Rt[:, None, :, None] * Rt[None, :, None, :]).reshape(len(pb.T), -1) @ pb.T
    Zt = (s * C) @ pb.YsvT  # columns z_i
    g = -(zeta @ Zt)
    # W z_i = z_i - (1 - rho) (u . z_i) u with u = zeta / |zeta| and u . z_i = -g_i / |zeta|
    shift = (1.0 - rho) / (zeta @ zeta) * g - (rho * c + 1.0 / rho)
    np.add(Zt, zeta[:, None] * shift, out=pb.E[:-1])
    return g


def _nearest(E, w):
    """Weights lam (N,) of the point of conv{d_i} nearest 0, for E (m + 1, N) with columns
    (d_i, 1). NNLS solves min |E u - e| over u >= 0 with e = (0, 1); then lam = u / sum(u)
    (Lawson & Hanson 1974, ch. 23). NNLS builds its active set from empty, at a cost that
    grows with N: for many nodes the face of the support of w is tried first."""
    N = E.shape[1]
    lam = _nearest_on_face(E[:-1].T, np.flatnonzero(w)) if N >= _FACE_MIN_NODES else None
    if lam is not None:
        return lam
    e = np.zeros(len(E))
    e[-1] = 1.0
    try:
        u = nnls(E, e, maxiter=20 * N)[0]
    except RuntimeError as exc:  # its iteration limit (finite termination is proven)
        raise FusionSolverError("newton", "qp_iteration_limit", str(exc)) from None
    return u / u.sum()


def _nearest_on_face(D, S):
    """The nearest point restricted to the nodes S, if it has positive weights there and no
    node off S would bring the model lower (Wolfe's test d_i . p >= |p|^2); else None.
    With the last node of S eliminated: min |d_k + A u| over u, A = (d_i - d_k), by QR."""
    if S.size < 2 or S.size > D.shape[1] + 1:
        return None
    Ds = D[S]
    A = (Ds[:-1] - Ds[-1]).T
    lqr, u, info = lapack.dgels(A, -Ds[-1])
    r = np.abs(lqr.diagonal())
    if info or r.min() <= _PINV_RTOL * r.max():
        return None
    lam_s = np.append(u[:S.size - 1], 1.0 - u[:S.size - 1].sum())
    p = lam_s @ Ds
    Dp = D @ p
    if lam_s.min() <= 0.0 or Dp.min() < p @ p - _WOLFE_RTOL * np.abs(Dp).max():
        return None
    lam = np.zeros(len(D))
    lam[S] = lam_s
    return lam


def _step_towards(pb, w, lam, f, g):
    """Armijo backtracking from lam towards w; returns the new w, f and U^-1."""
    d = lam - w
    slope = float(g @ d)  # < 0: lam minimises a convex model that agrees with f to first order
    t = 1.0
    for _ in range(60):
        w_try = lam if t == 1.0 else w + t * d
        f_try, Ui = _value(pb, w_try)
        # Armijo, up to the rounding of f (near the optimum the decrease is below it).
        if f_try <= f + _ARMIJO * t * min(slope, 0.0) + _FLAT * max(abs(f), 1.0):
            break
        t *= 0.5
    return w_try, f_try, Ui
