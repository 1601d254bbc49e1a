"""The exact native weight solver: sequential quadratic programming on the simplex,
compiled (numba, cached on disk) and looped over the problems of a batch.

`solve(F, trace, W0, use_start)` takes the square-root factors F (B, N, n, n) of a batch
(`factored.py`: Y_i = F_i^T F_i) and returns weights (B, N), the relative certificate (B,)
and the iteration counts (B,). N = 1 is weight 1; N = 2 is the 1-D problem of
`closed_form.py`; N >= 3 is the SQP below, problem by problem, so a problem gives the same
weights alone or inside any batch.

SQP (one problem). At w the model of `factored.py` whitens the nodes, z_i (m,), so that
H_ij = z_i . z_j and g_i = -zeta . z_i, with z(w) = sum w_i z_i = c zeta. The quadratic
model of f about w is then, up to a constant,

    q(lam) = |W (z(lam) - z(w)) - zeta / rho|^2 / 2,       lam on the simplex,

with W = I - (1 - rho) u u^T, u = zeta / |zeta|. rho = 1 is Newton's model; f is homogeneous
in Y (f(tY) = f / t, resp. f - n log t), along u Newton's model is poor far from the
optimum, and rho = 0.1 keeps 1% of its curvature there; below a relative certificate of
1e-4, and after a step the line search shortened (where the damped model overshot: on an
ill-conditioned problem it did so again at every step, each shortened to nothing), rho = 1.
The minimiser of q is the point of conv{d_i}, d_i = W z_i - (rho c + 1/rho)
zeta, nearest the origin, found by non-negative least squares (Lawson & Hanson 1974,
ch. 23: min |E u - e| over u >= 0 with E = [d_i; 1], e = (0, 1), lam = u / sum u, the d_i
first scaled to unit size, which does not move lam), warm started on the support of w
(at the first step from the SQP's own start, where every weight is positive, on the
nodes whose next design weight w_i (-g_i) is at least half the largest: `_likely_support`);
its support has at most m + 1 nodes whatever N. w moves towards lam with Armijo
backtracking on f (allowing the rounding of f); below a relative certificate of 1e-4,
where the decrease of f can be below f's own rounding on an ill-conditioned problem, the
whole step to lam is taken instead if its certificate is better than that of the line
search's point. It stops on the certificate (relative to f for "trace", absolute for
"logdet") or, at rounding level, after 5 steps below 1e-4 without a better one; it returns
the iterate with the best certificate. It starts from steps of the multiplicative
algorithm of optimal design (`_design_steps`) from uniform weights, two for "trace", one
for "logdet" (on a working set of many nodes, `_priced`, only for "trace"), which save
more SQP steps than they cost, and then takes at least one SQP step. For "logdet" the
model is in svec form (`factored.model_at`: m = n (n + 1) / 2 instead of n^2).

Many nodes. Some optimum needs at most n (n + 1) / 2 + 1 nodes (Caratheodory: Y(w) is
a convex combination of the Y_i in the n (n + 1) / 2-dimensional space of symmetric
matrices). Above twice that many nodes, the SQP runs on a working set of them and the
gradient on all N nodes prices the others in (`_priced`, column generation), so that a
step costs O(n^2) nodes instead of N: at (n, N) = (6, 64) the solve took 173 -> 148 us,
at (6, 256) 587 -> 289 us (one random problem each, "trace").
"""

from __future__ import annotations

import math

import numpy as np

from ..factored import (
    FACTORED,
    GRADED,
    evaluate_at,
    gap,
    gradient_at,
    model_at,
    model_view,
    sumsq,
    value,
    work,
)
from ..linalg import (
    apply_qt,
    apply_reflector,
    copy,
    fill,
    householder,
    householder_column,
    inline,
    jit,
    pow2,
)
from . import closed_form

TOL = 1e-13
_ARMIJO = 1e-4
_FLAT = 1e3 * np.finfo(np.float64).eps  # a decrease below this x |f| is under f's rounding
_RHO = 0.1
_LOCAL = 1e-4
_STALL = 5
_DESIGN_STEPS = 2
_DESIGN_LOGDET = 1
_LIKELY = 0.5
_LAST = 1e-6  # from here a Newton step likely ends below TOL (quadratic convergence)
_EPS = np.finfo(np.float64).eps


@jit
def solve(F, trace: bool, W0, use_start: bool, W, rel, iters):
    """Weights W (B, N), relative certificates rel (B,) and iterations (B,) for factors
    F (B, N, n, n); each SQP starts at W0[b] when use_start (a polish), else at uniform
    weights."""
    ws = work(F.shape[1], F.shape[2])
    for b in range(F.shape[0]):
        rel[b], iters[b], _ = solve_one(F[b], trace, W0[b], use_start, W[b], ws.At,
                                        ws.Vt, ws.R, ws.Ri, ws.P, ws.B, ws.X, ws.S, ws.U,
                                        ws.lam, ws.abc, ws.zeta, ws.g, ws.Et, ws.x, ws.z,
                                        ws.mask, ws.r, ws.cols, ws.Elt, ws.Vlt, ws.Rls,
                                        ws.qe, ws.w_try, ws.best_w)


@inline
def solve_one(F, trace: bool, w0, use_start: bool, w, At, Vt, R, Ri, P, Bm, X, S, U, lam,
              abc, zeta, g, Et, x, z, mask, r, cols, Elt, Vlt, Rls, qe, w_try, best_w):
    """`solve` of one problem, F (N, n, n), into w (N,), with the buffers of `Work` as
    arrays (numba inlines a function of at most 30 arguments); returns (rel, iterations,
    state): state FACTORED when the buffers hold the QR of the returned w (At, Vt, R, Ri:
    what `factored.evaluate_at` leaves), GRADED when g also holds `factored.gradient_at`
    there, else 0 (`assemble.py` need not compute them again)."""
    N = F.shape[0]
    if N == 1:
        w[0] = 1.0
        return 0.0, 0, 0
    if N == 2:
        w[0], it = closed_form.pair_weight_at(F, trace, At, Vt, R, Ri, P, Bm, X, S, U, lam,
                                              abc)
        w[1] = 1.0 - w[0]
        rel = _certificate(F, w, trace, At, Vt, R, Ri, P, Bm, g)[2]
        return rel, it, GRADED if rel < np.inf else 0
    if not use_start and N > _priced_above(F.shape[1]):  # a polish starts on all nodes
        return _priced(F, trace, w, At, Vt, R, Ri, P, Bm, X, S, zeta, g, Et, x, z, mask, r,
                       cols, Elt, Vlt, Rls, qe, w_try, best_w)
    designed = not use_start
    if use_start:
        copy(w, w0)
    else:
        fill(w, 1.0 / N)
        if designed:
            _design_steps(F, w, _DESIGN_STEPS if trace else _DESIGN_LOGDET, At, Vt, R, Ri, P, Bm,
                          g, trace)
    # at least one SQP step after design steps: theirs never reach a zero weight, the
    # nearest point does (an optimum at a node is returned as that node exactly)
    return _sqp(F, trace, w, TOL, 50 + 4 * N, 1 if designed else 0, not use_start, At, Vt, R,
                Ri, P, Bm, X, S, zeta, g, Et, x, z, mask, r, cols, Elt, Vlt, Rls, qe, w_try,
                best_w)


@jit
def _priced_above(n: int) -> int:
    """The number of nodes above which `_priced` solves a problem in dimension n: twice
    n (n + 1) / 2 + 1, the nodes some optimum needs at most. Below it the working set
    gains nothing (solve times against the SQP on all nodes, 16 problems each, "trace":
    (2, 7) 13.6 against 11.0 us, (4, 16) 28.6 against 27.5, (6, 32) 80.9 against 92.4)."""
    return 2 * (n * (n + 1) // 2 + 1)


@jit
def _priced(F, trace: bool, w, At, Vt, R, Ri, P, Bm, X, S, zeta, g, Et, x, z, mask, r, cols,
            Elt, Vlt, Rls, qe, w_try, best_w):
    """Many nodes (N > `_priced_above`): the SQP on a working set of nodes, priced out on
    all of them (column generation; module docstring). With m = n (n + 1) / 2, the set
    starts as the m + 1 nodes of the most negative gradient at uniform weights; the SQP
    solves the problem on the set, started as `solve_one` starts it (uniform weights on
    the set, design steps for "trace"); the gradient on all N nodes at its weights gives the
    certificate of the whole problem; while that is above TOL, the nodes off the set
    whose gradient is below g.w by more than TOL join it (up to m + 1 of them, the most
    negative first) and the SQP goes on from its weights. The set only grows, so this
    ends, at worst with all N nodes. FS, wS, idx, inS hold the set: its factors, weights,
    node indices (ascending, so that its QR is the whole problem's at the same weights)
    and mask (made here: at few nodes, where this does not run, four more buffers in
    `Work` cost 0.1 us a call). Returns as `solve_one`, the certificate that of all N
    nodes."""
    N, n = F.shape[0], F.shape[1]
    add = n * (n + 1) // 2 + 1
    FS, wS = np.empty_like(F), np.empty(N)
    idx, inS = np.empty(N, dtype=np.int64), np.zeros(N, dtype=np.bool_)
    fill(w, 1.0 / N)
    if not evaluate_at(F, w, At, Vt, R, Ri, trace)[1]:
        return np.inf, 0, 0
    gradient_at(F, Ri, P, Bm, g, trace)
    if not _join(g, w, inS, -np.inf, add):  # the first set: the `add` most negative
        return np.inf, 0, 0
    K = _gather(F, w, inS, FS, wS, idx)
    fill(wS[:K], 1.0 / K)
    if trace:
        _design_steps(FS[:K], wS[:K], _DESIGN_STEPS, At, Vt, R, Ri, P, Bm, g[:K], True)
    its, min_iter, fresh = 0, 1 if trace else 0, True
    while True:
        rel, it, state = _sqp(FS[:K], trace, wS[:K], TOL, 50 + 4 * K, min_iter, fresh, At, Vt,
                              R, Ri, P, Bm, X, S, zeta, g[:K], Et[:K], x[:K], z[:K], mask[:K],
                              r, cols[:K], Elt, Vlt, Rls, qe, w_try[:K], best_w[:K])
        its, min_iter, fresh = its + it, 0, False
        fill(w, 0.0)
        for t in range(K):
            w[idx[t]] = wS[t]
        f, ok = evaluate_at(F, w, At, Vt, R, Ri, trace) if state == 0 else \
            (value(R, Ri, trace), True)
        if not ok:
            return np.inf, its, 0
        gradient_at(F, Ri, P, Bm, g, trace)
        scale = abs(f) if trace else 1.0
        rel = gap(g, w) / scale
        if rel <= TOL or K == N or not _join(g, w, inS, TOL * scale, add):
            return rel, its, GRADED
        K = _gather(F, w, inS, FS, wS, idx)


@jit
def _join(g, w, inS, margin: float, most: int) -> bool:
    """Marks in inS up to `most` nodes off it whose g_i < g.w - margin, the most negative
    first; False if there is none."""
    gw = 0.0
    for i in range(w.size):
        gw += g[i] * w[i]
    joined = 0
    for i in np.argsort(g):
        if joined == most or not g[i] < gw - margin:
            break
        if not inS[i]:
            inS[i] = True
            joined += 1
    return joined > 0


@jit
def _gather(F, w, inS, FS, wS, idx) -> int:
    """The nodes of inS in ascending order: their indices into idx, factors into FS and
    weights into wS; returns their number."""
    K = 0
    for i in range(w.size):
        if inS[i]:
            idx[K] = i
            wS[K] = w[i]
            for a in range(F.shape[1]):
                for b in range(F.shape[2]):
                    FS[K, a, b] = F[i, a, b]
            K += 1
    return K


@jit
def _design_steps(F, w, steps: int, At, Vt, R, Ri, P, B, g, trace: bool):
    """Steps of the multiplicative algorithm of optimal design (Silvey, Titterington &
    Torsney 1978): w_i <- w_i (-g_i) / s, s = -sum_i w_i g_i, which keeps w on the simplex
    and positive ("trace": -g_i = tr(P Y_i P), s = tr(P) = f; "logdet": -g_i = tr(P Y_i),
    s = n). From uniform weights, two of them for "trace" (an evaluation and a gradient
    each, 0.7 us at (n, N) = (4, 3)) save 1.3 to 1.5 SQP steps (1.5 us each) there; for
    "logdet" one saves 0.3 to 1.6 SQP steps at (n, N) from (4, 7) to (6, 16) (solve times
    1.03 to 1.2 times shorter; a second saved fewer steps than it cost). A step whose
    numbers are not finite is not taken."""
    N = w.size
    for _ in range(steps):
        if not evaluate_at(F, w, At, Vt, R, Ri, trace)[1]:
            return
        gradient_at(F, Ri, P, B, g, trace)
        s = 0.0
        for i in range(N):
            s -= w[i] * g[i]
        if not 0.0 < s < np.inf:
            return
        for i in range(N):
            w[i] *= -g[i] / s


@jit
def certificates(F, W, trace: bool, rel):
    """rel (B,): the relative certificate of weights W (B, N) for factors F (B, N, n, n)."""
    ws = work(F.shape[1], F.shape[2])
    for b in range(F.shape[0]):
        rel[b] = _certificate(F[b], W[b], trace, ws.At, ws.Vt, ws.R, ws.Ri, ws.P, ws.B,
                              ws.g)[2]


@jit
def certificate(F, w, ws, trace: bool):
    """(gap, f, gap relative to |f| for "trace", as is for "logdet") at weights w."""
    return _certificate(F, w, trace, ws.At, ws.Vt, ws.R, ws.Ri, ws.P, ws.B, ws.g)


@jit
def _certificate(F, w, trace: bool, At, Vt, R, Ri, P, B, g):
    f, ok = evaluate_at(F, w, At, Vt, R, Ri, trace)
    if not ok:
        return np.inf, np.inf, np.inf
    gradient_at(F, Ri, P, B, g, trace)
    gp = gap(g, w)
    return gp, f, gp / abs(f) if trace else gp


@jit
def sqp(F, trace: bool, w, ws, tol: float, max_iter: int):
    """One problem (module docstring): F (N, n, n), w (N,) a start on the simplex with Y(w)
    positive definite, overwritten with the iterate of the best certificate. Returns that
    certificate (relative) and the iteration count."""
    rel, it, _ = _sqp(F, trace, w, tol, max_iter, 0, False, ws.At, ws.Vt, ws.R, ws.Ri, ws.P, ws.B,
                      ws.X, ws.S, ws.zeta, ws.g, ws.Et, ws.x, ws.z, ws.mask, ws.r, ws.cols,
                      ws.Elt, ws.Vlt, ws.Rls, ws.qe, ws.w_try, ws.best_w)
    return rel, it


@jit
def _sqp(F, trace: bool, w, tol: float, max_iter: int, min_iter: int, fresh: bool, At, Vt,
         R, Ri, P, Bm, X, S, zeta, g, Et, x, z, mask, r, cols, Elt, Vlt, Rls, qe, w_try, best_w):
    """`sqp` with the buffers of `Work` as arrays (factored.py's docstring says why), taking
    at least min_iter steps; of iterates with equal certificates the later is kept. A
    point the last certificate says is likely final (below _LAST) is certified by its
    gradient alone (`factored.gradient_at`, half the cost of the model), the model made
    only if it is not, and only once: at rounding level, where the certificate stalls
    above tol, the two gradients' rounding differ, and a gradient at every step (log det,
    n = 200: 10 steps to 17) kept resetting the stall count."""
    N = F.shape[0]
    Et = model_view(Et, N, F.shape[1], trace)
    f, _ = evaluate_at(F, w, At, Vt, R, Ri, trace)
    copy(best_w, w)
    best, rel, it, stalled, shortened, missed = np.inf, np.inf, 0, 0, False, False
    while True:
        graded = rel <= _LAST and not missed
        if graded:
            gradient_at(F, Ri, P, Bm, g, trace)
        else:
            model_at(F, Ri, zeta, Et, g, Bm, X, S, trace,
                     1.0 if rel <= _LOCAL or shortened else _RHO)
        rel = gap(g, w) / (abs(f) if trace else 1.0)
        if rel <= best:  # of equal certificates the later (which counts as a stall)
            copy(best_w, w)
        if rel < best:
            best, stalled = rel, 0
        elif rel <= _LOCAL:  # far from the optimum (also after a change of support, from
            stalled += 1     # a better point) the certificate need not fall each step
        if (best <= tol and it >= min_iter) or it >= max_iter or stalled >= _STALL:
            break
        if graded:  # not final after all
            missed = True
            model_at(F, Ri, zeta, Et, g, Bm, X, S, trace, 1.0)
        it += 1
        if it == 1 and fresh:
            _likely_support(w, g, mask)
        else:
            for i in range(N):
                mask[i] = w[i] > 0.0
        _nearest(Et, x, mask, z, r, cols, Elt, Vlt, Rls, qe)
        f = _step_towards(F, trace, w, x, g, w_try, At, Vt, R, Ri, f)
        shortened = not _equal(w, x)
        if rel <= _LOCAL and shortened:
            f = _whole_step_if_better(F, trace, w, x, g, At, Vt, R, Ri, P, Bm, f)
    if not _equal(w, best_w) or not f < np.inf:  # the buffers hold another point
        copy(w, best_w)
        return best, it, 0
    return best, it, GRADED if graded else FACTORED


@inline
def _likely_support(w, g, mask):
    """The warm start of a fresh SQP's first nearest point: the nodes whose w_i (-g_i), the
    next weight of the multiplicative algorithm of optimal design, is at least _LIKELY
    times the largest (g < 0: every node's information lowers f). Started on all nodes
    (every weight is positive there) its least squares was never positive, and the NNLS
    built the support from none, a node at a time: 9.4 nodes entered at (n, N) = (6, 16),
    3.8 from this start, whose least squares is positive on 96 % of problems ("trace";
    8.4 and 5.8 for "logdet"). A wrong guess costs one factorisation: `_nearest` then
    starts from none, as before."""
    top = 0.0
    for i in range(w.size):
        top = max(top, -w[i] * g[i])
    for i in range(w.size):
        mask[i] = -w[i] * g[i] >= _LIKELY * top


@inline
def _whole_step_if_better(F, trace: bool, w, x, g, At, Vt, R, Ri, P, B, f) -> float:
    """Near the optimum the decrease of f along a Newton step (about the certificate
    squared) can fall below the rounding of f (eps times the condition of the stacked
    factors: 1e-12 of f at condition 1e10); the line search then rejects or shortens the
    step at random and the SQP stalls above its tolerance. So when it did not take the
    whole step to x, the certificates decide, which stay accurate there: x replaces the
    line search's point w if its certificate is better. The buffers are left factored at
    the point whose f is returned."""
    gradient_at(F, Ri, P, B, g, trace)  # the buffers hold w's factors (_step_towards)
    rel_w = gap(g, w) / (abs(f) if trace else 1.0)
    f_x, ok = evaluate_at(F, x, At, Vt, R, Ri, trace)
    if ok:
        gradient_at(F, Ri, P, B, g, trace)
        if gap(g, x) / (abs(f_x) if trace else 1.0) < rel_w:
            copy(w, x)
            return f_x
    evaluate_at(F, w, At, Vt, R, Ri, trace)
    return f


@jit
def _equal(a, b) -> bool:
    for i in range(a.size):
        if a[i] != b[i]:
            return False
    return True


@inline
def _step_towards(F, trace: bool, w, x, g, w_try, At, Vt, R, Ri, f) -> float:
    """Armijo backtracking from the nearest point x towards w, allowing the rounding of f;
    w is overwritten with the accepted point, whose f is returned and whose factors are
    left in the buffers (unchanged w and f if no step is accepted)."""
    N = w.size
    slope = 0.0
    for i in range(N):
        slope += g[i] * (x[i] - w[i])
    slope = min(slope, 0.0)
    allowance = _FLAT * (abs(f) if trace else max(abs(f), 1.0))
    t = 1.0
    for _ in range(60):
        for i in range(N):
            w_try[i] = x[i] if t == 1.0 else w[i] + t * (x[i] - w[i])
        f_try, ok = evaluate_at(F, w_try, At, Vt, R, Ri, trace)
        if ok and f_try <= f + _ARMIJO * t * slope + allowance:
            copy(w, w_try)
            return f_try
        t *= 0.5
    evaluate_at(F, w, At, Vt, R, Ri, trace)  # leave w's factors in the buffers
    return f


@jit
def nearest(ws):
    """`_nearest` on the buffers of ws."""
    _nearest(ws.Et, ws.x, ws.mask, ws.z, ws.r, ws.cols, ws.Elt, ws.Vlt, ws.Rls, ws.qe)


@jit
def _nearest(Et, x, P, z, r, cols, Elt, Vlt, Rls, qe):
    """x (N,) on the simplex minimising |sum x_i d_i| for the rows (d_i, 1) of Et
    (N, m + 1): Lawson-Hanson NNLS of min |E u - e|, e = (0, ..., 0, 1), x = u / sum u,
    started on the nodes P (a mask) when the least-squares solution there is positive.
    The QR of E_P is kept as nodes enter (`linalg.householder_column`) and made anew when
    one leaves: nodes enter one at a time (at the SQP's first step on 64 nodes of n = 6,
    12 to 18 end in the support), and a new QR for each cost O(k^3): 133 us there, 72 us
    with the kept QR. z, r, cols, Elt, Vlt, Rls, qe are its scratch (`factored.Work`)."""
    N, M = Et.shape
    _normalise(Et)
    fill(x, 0.0)
    k = _factor_on(Et, P, cols, Elt, Vlt, Rls, qe)
    if 0 < k and _solve_on(k, cols, Rls, qe, z) and _positive_on(z, P):
        copy(x, z)
    else:
        fill(P, False)
        k = _factor_on(Et, P, cols, Elt, Vlt, Rls, qe)  # none: qe = e
    norm = np.sqrt(sumsq(Et) / N)
    tol = 10.0 * max(M, N) * _EPS * max(norm, 1.0)
    for _ in range(3 * N + 10):
        j = _entering(Et, x, r, P, tol)
        if j < 0:
            break
        P[j] = True
        k = _inner(j, k, Et, x, P, z, cols, Elt, Vlt, Rls, qe)
        if k < 0:
            break
    total = x.sum()
    if not total > 0.0:  # cannot happen for a nonzero e; a guard against rounding
        fill(x, 1.0 / N)
    else:
        x /= total


@inline
def _normalise(Et):
    """Scales the d_i (the rows of Et without their last entry, the simplex's 1) by a
    power of two (exactly) to a root mean square near 1. The nearest point does not depend
    on their scale, but the rank test of the least squares and the tolerance of the duals
    meet them against the simplex row of ones; for "trace" the d_i are of the size of
    sqrt(f), which the prescaling leaves anywhere from 1e-12 to 1e12 (a fused trace far
    below the nodes' middle scale), and at 1e-6 two nodes' difference fell below the rank
    test and the SQP stalled above its tolerance."""
    N, M = Et.shape
    s = 0.0
    for i in range(N):
        for p in range(M - 1):
            s += Et[i, p] * Et[i, p]
    if not 0.0 < s < np.inf:
        return
    # 2^shift is a normal number (|shift| <= 540 for a finite s > 0): exact, as ldexp
    scale = pow2(-math.frexp(np.sqrt(s / N))[1])
    for i in range(N):
        for p in range(M - 1):
            Et[i, p] *= scale


@inline
def _entering(Et, x, r, P, tol: float) -> int:
    """The node off P of the largest dual E^T (e - E x) above tol, or -1 (r: scratch)."""
    N, M = Et.shape
    fill(r, 0.0)
    r[M - 1] = 1.0
    for i in range(N):
        if x[i] != 0.0:
            for p in range(M):
                r[p] -= x[i] * Et[i, p]
    j, top = -1, tol
    for i in range(N):
        if not P[i]:
            t = 0.0
            for p in range(M):
                t += Et[i, p] * r[p]
            if t > top:
                j, top = i, t
    return j


@inline
def _inner(j, k, Et, x, P, z, cols, Elt, Vlt, Rls, qe) -> int:
    """Lawson-Hanson's inner loop after node j entered P, whose other k nodes the QR in
    cols, Elt, Vlt, Rls, qe holds; returns the number of nodes the QR then holds, or -1 if
    j cannot enter (rounding), which ends the outer loop."""
    N = x.size
    k = _append(j, k, Et, cols, Elt, Vlt, Rls, qe)
    for _ in range(3 * N + 10):
        good = k > 0 and _solve_on(k, cols, Rls, qe, z)
        if not good or (z[j] <= 0.0 and x[j] == 0.0):
            P[j] = False
            return -1
        if _positive_on(z, P):
            copy(x, z)
            return k
        alpha = 1.0
        for i in range(N):
            if P[i] and z[i] <= 0.0:
                alpha = min(alpha, x[i] / (x[i] - z[i]))
        for i in range(N):
            if P[i]:
                x[i] += alpha * (z[i] - x[i])
                if x[i] <= 0.0:
                    x[i] = 0.0
                    P[i] = False
        k = _factor_on(Et, P, cols, Elt, Vlt, Rls, qe)
    return k


@jit
def _factor_on(Et, P, cols, Elt, Vlt, Rls, qe) -> int:
    """QR of E_P, its columns in node order (cols), with qe = Q^T e; returns their number,
    or -1 when they are more than the buffers hold."""
    N, M = Et.shape
    k = 0
    for i in range(N):
        if P[i]:
            if k == Elt.shape[0]:
                return -1
            cols[k] = i
            for p in range(M):
                Elt[k, p] = Et[i, p]
            k += 1
    householder(Elt, k, M, Vlt, Rls)
    fill(qe, 0.0)
    qe[M - 1] = 1.0
    apply_qt(Vlt, k, M, qe)
    return k


@inline
def _append(j, k, Et, cols, Elt, Vlt, Rls, qe) -> int:
    """Node j's column appended to the QR of k columns (qe updated); returns k + 1, or -1
    when the buffers are full."""
    M = Et.shape[1]
    if k == Elt.shape[0]:
        return -1
    cols[k] = j
    for p in range(M):
        Elt[k, p] = Et[j, p]
    householder_column(Elt, k, M, Vlt, Rls)
    apply_reflector(Vlt, k, M, qe)  # the first k reflectors are in qe already
    return k + 1


@jit
def _solve_on(k, cols, Rls, qe, z) -> bool:
    """z (N,), zero off the k columns of the QR, minimising |E_P z_P - e| by back
    substitution; False when E_P is numerically rank deficient."""
    top, low = 0.0, np.inf
    for c in range(k):
        top, low = max(top, abs(Rls[c, c])), min(low, abs(Rls[c, c]))
    if not low > 1e3 * _EPS * top:
        return False
    fill(z, 0.0)
    for c in range(k - 1, -1, -1):
        t = qe[c]
        for d in range(c + 1, k):
            t -= Rls[c, d] * z[cols[d]]
        z[cols[c]] = t / Rls[c, c]
    return True


@jit
def _positive_on(z, P) -> bool:
    for i in range(z.size):
        if P[i] and not z[i] > 0.0:
            return False
    return True
