"""Active-set Newton method on the weight simplex: exact, native and batched.

Minimises a CI criterion f(w) over {w >= 0, sum w = 1} with the analytic gradient g and
Hessian H of `criteria.py`. It starts at the best single node (or a given start) and works
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

from ..criteria import evaluate, gap
from ..simplex import to_simplex

TOL = 1e-13
_PINV_RTOL = 1e-11
_ARMIJO = 1e-4
_GROW_RATIO = 0.1
# A predicted decrease below this times |f| is under the rounding of f: Armijo cannot see it.
_FLAT = 1e3 * np.finfo(float).eps
_START_RIDGE = 1e-8


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


def solve_one(Ys, M, criterion, tol=TOL, max_iter=None) -> NewtonSolution:
    """The same method for one problem, Ys (N, n, n) and M (n, n), with few numpy calls.

    A batch of one pays the masking of `solve` on every call; here f, g come from
    Yf = Ys as (N, n*n) rows (Y(w) = w @ Yf, g = -Yf vec(P M P)), the Hessian on S from one
    Kronecker product (H = 2 Yf_S (P kron PMP) Yf_S^T for "trace", Yf_S (P kron P) Yf_S^T for
    "logdet"), and f, g, P of the accepted trial point are reused. It starts at the better of
    the best vertex and the projected Newton point from uniform weights (where the scaled
    Y'(w) = I). Nodes enter S several at a time (the `n` most violating); a node at weight 0
    that the face step would push negative leaves S again before the step is taken.
    Returns arrays of batch size 1.
    """
    N, n = Ys.shape[:2]
    Yf = Ys.reshape(N, n * n)
    trace = criterion == "trace"
    w, (f, g, P, G) = _start(Ys, Yf, M, n, trace)
    S = w > 0
    fscale = abs(f) if trace else 1.0
    rel, it = np.inf, 0
    for it in range(1, (max_iter or 50 + 4 * N) + 1):
        gw = g @ w
        rel = (gw - g.min()) / fscale
        if rel <= tol:
            it -= 1
            break
        g_face = g[S].min()
        if gw - g_face <= max(tol * fscale, _GROW_RATIO * (gw - g.min())):
            out = np.flatnonzero(~S & (g < g_face))
            S[out[np.argsort(g[out])[:n]]] = True
        d = _face_step(Yf, P, G, g, w, S, trace)
        t = 1.0
        for _ in range(60):  # Armijo along the projected arc: several nodes may leave at once
            w_try = project_simplex(w + t * d)
            point = _point(Yf, M, w_try, n, trace)
            slope = g @ (w_try - w)
            # Armijo, up to the rounding of f (near the optimum the decrease is below it).
            if point[0] <= f + _ARMIJO * min(slope, 0.0) + _FLAT * max(abs(f), 1.0):
                break
            t *= 0.5
        w, (f, g, P, G) = w_try, point
        S &= w > 0
        fscale = abs(f) if trace else 1.0
    one = np.ones(1)
    return NewtonSolution(to_simplex(w)[None], rel * one, it * one.astype(int),
                          (rel <= tol) * one > 0)


def _start(Ys, Yf, M, n, trace):
    """The better (in f) of the best vertex and the projected Newton point from uniform."""
    N = len(Ys)
    if trace:
        f_vertex = np.einsum("ij,nji->n", M, np.linalg.inv(Ys))
    else:
        f_vertex = -np.linalg.slogdet(Ys)[1]
    vertex = np.zeros(N)
    vertex[np.argmin(f_vertex)] = 1.0
    u = np.full(N, 1.0 / N)
    _, g, P, G = _point(Yf, M, u, n, trace)
    d = _face_step(Yf, P, G, g, u, np.ones(N, dtype=bool), trace, ridge=_START_RIDGE)
    cand = project_simplex(u + d)
    pc = _point(Yf, M, cand, n, trace)
    if pc[0] < f_vertex.min():
        return cand, pc
    return vertex, _point(Yf, M, vertex, n, trace)


def project_simplex(v):
    """Euclidean projection of v (N,) onto the simplex (sort-based)."""
    u = np.sort(v)[::-1]
    css = np.cumsum(u) - 1.0
    k = np.flatnonzero(u * np.arange(1, len(v) + 1) > css)[-1]
    return np.maximum(v - css[k] / (k + 1), 0.0)


def _point(Yf, M, w, n, trace):
    """f, g (N,), P and G (= P M P for "trace", P for "logdet") at w."""
    Y = (w @ Yf).reshape(n, n)
    P = np.linalg.inv(Y)
    if trace:
        G = P @ M @ P
        return np.vdot(M, P), -(Yf @ G.ravel()), P, G
    return -np.linalg.slogdet(Y)[1], -(Yf @ P.ravel()), P, P


def _face_step(Yf, P, G, g, w, S, trace, ridge=0.0):
    """Newton step on the face of S (zeros off S), after removing from S the nodes at
    weight 0 that it would push negative. ridge > 0 (relative) regularises a singular H
    instead of taking the minimum-norm step (used for the heuristic start only)."""
    idx = np.flatnonzero(S)
    n = len(P)
    K = (P[:, None, :, None] * G[None, :, None, :]).reshape(n * n, n * n)  # P kron G
    H = Yf[idx] @ K @ Yf[idx].T
    if trace:
        H *= 2.0
    while True:
        dk = _reduced_newton(H, g[idx], w[idx], ridge)
        leave = (w[idx] <= 0) & (dk < 0)
        if not leave.any():
            break
        S[idx[leave]] = False  # some node of S has w > 0 and never leaves: S stays nonempty
        keep = ~leave
        idx, H = idx[keep], H[np.ix_(keep, keep)]
    d = np.zeros_like(w)
    d[idx] = dk
    return d


def _reduced_newton(H, g, w, ridge):
    """Newton step d (k,) with sum(d) = 0 for H (k, k), g (k,): d = (u, -sum u) with
    (Q^T H Q) u = -Q^T g, Q = [I; -1^T]. By Cholesky when Q^T H Q is well conditioned (or
    ridge > 0), else the minimum-norm step of `_face_newton_step`."""
    k = len(g)
    if k == 1:
        return np.zeros(1)
    Hr = H[:-1, :-1] - H[:-1, -1:] - H[-1:, :-1] + H[-1, -1]
    top = Hr.diagonal().max()
    if ridge:
        Hr = Hr + ridge * top * np.eye(k - 1)
    try:
        piv = np.linalg.cholesky(Hr).diagonal()
    except np.linalg.LinAlgError:
        piv = np.zeros(1)
    if piv.min() ** 2 > _PINV_RTOL * top:
        u = np.linalg.solve(Hr, g[-1] - g[:-1])
        return np.append(u, -u.sum())
    return _face_newton_step(H[None], g[None], np.ones((1, k), dtype=bool), w[None])[0]
