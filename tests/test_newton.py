"""The compiled exact solver (SQP, nearest point, pairwise 1-D method) against independent
references: the numpy criteria of criteria.py (f, g, H from inverted informations),
CVXPY/Clarabel, grids, and each other (the SQP on N = 2 against the 1-D method)."""

import itertools
import math

import cvxpy as cp
import numpy as np
import pytest
from conftest import EXTREME_KINDS, extreme_instance, instance, objective

import fusion_opt as fo
from fusion_opt import core, factored, linalg
from fusion_opt.assemble import assemble
from fusion_opt.backends import closed_form, newton
from fusion_opt.criteria import evaluate
from fusion_opt.detection import detection_split
from fusion_opt.factored import factor_at, model, work

CRITERIA = ("trace", "logdet")
KINDS = ("random", "ill-conditioned")


def _factors(covs):
    """F (N, n, n) of covs (N, n, n) as the core makes them (prescaled by 2^-k)."""
    means, covs = core.arrays(np.zeros(covs.shape[:-1]), covs, False)
    a = core._Arrays(1, *means.shape[1:])
    core._prepare(means, covs, *core._unit_scales(1, means.shape[1]), a, core._NAMES, False)
    return a.F[0], a.k[0]


def evaluate_f(F, w, criterion):
    """f at w in the factor form of factored.py."""
    return factored.evaluate(F, w, work(*F.shape[:2]), criterion == "trace")[0]


def _sqp(covs, criterion, w0=None):
    F, _ = _factors(covs)
    N, n = F.shape[:2]
    w = np.full(N, 1.0 / N) if w0 is None else np.array(w0, dtype=float)
    rel, it = newton.sqp(F, criterion == "trace", w, work(N, n), newton.TOL, 50 + 4 * N)
    return w, rel, it


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("kind", KINDS)
def test_model_has_the_gradient_and_hessian_of_criteria(kind, criterion):
    """rho = 1: the model is Newton's, so g matches and, on directions summing to 0,
    Q^T H Q = (Q^T Z)(Q^T Z)^T with rows z_i of the nearest-point matrix."""
    covs = instance(np.random.default_rng(4), 6, 3, kind)
    F, _ = _factors(covs)
    w = np.random.default_rng(5).dirichlet(np.ones(6))
    ws = work(6, 3)
    assert factor_at(F, w, ws)[1]
    model(F, ws, criterion == "trace", 1.0)
    Ys = np.einsum("iba,ibc->iac", F, F)  # F_i^T F_i
    ev = evaluate(Ys, w, criterion, hessian=True)
    assert np.allclose(ws.g, ev.g, rtol=1e-9, atol=1e-12 * np.abs(ev.g).max())
    Q = np.vstack([np.eye(5), -np.ones(5)])
    A = Q.T @ ws.Et[:, :-1]
    H = Q.T @ ev.H @ Q
    assert np.allclose(A @ A.T, H, rtol=1e-8, atol=1e-10 * np.abs(H).max())


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("rho", (0.1, 1.0))
def test_logdet_model_in_svec_form_has_the_same_gram_and_gradient(kind, rho):
    """The SQP's "logdet" model (factored.model_view: n (n + 1) / 2 coordinates) has the
    gradient and the Gram matrix of the nearest-point rows of the vec model."""
    n, N = 4, 7
    covs = instance(np.random.default_rng(8), N, n, kind)
    F, _ = _factors(covs)
    w = np.random.default_rng(9).dirichlet(np.ones(N))
    ws = work(N, n)
    assert factor_at(F, w, ws)[1]
    model(F, ws, False, rho)
    g, E = ws.g.copy(), ws.Et.copy()
    Ev = factored.model_view(ws.Et, N, n, False)
    assert Ev.shape == (N, n * (n + 1) // 2 + 1)
    factored.model_at(F, ws.Ri, ws.zeta, Ev, ws.g, ws.B, ws.X, ws.S, False, rho)
    assert np.array_equal(ws.g, g)
    assert np.all(Ev[:, -1] == 1.0)
    G, Gv = E @ E.T, Ev @ Ev.T
    assert np.allclose(Gv, G, rtol=1e-13, atol=1e-13 * np.abs(G).max())


def test_nearest_point_matches_cvxpy():
    rng = np.random.default_rng(6)
    for N, n in ((5, 1), (12, 2), (40, 3)):
        ws = work(N, n)
        m = n * n
        D = rng.standard_normal((N, m)) + 1.5  # 0 outside the hull: a boundary point
        ws.Et[:, :m] = D
        ws.mask[:] = False
        newton.nearest(ws)
        lam = ws.x.copy()
        x = cp.Variable(N, nonneg=True)
        cp.Problem(cp.Minimize(cp.sum_squares(D.T @ x)), [cp.sum(x) == 1]).solve("CLARABEL")
        assert abs(lam.sum() - 1) < 1e-14 and lam.min() >= 0
        assert np.linalg.norm(lam @ D) <= np.linalg.norm(x.value @ D) + 1e-8
        ws.mask[:] = lam > 0  # warm started on its own support: the same point
        newton.nearest(ws)
        assert np.allclose(ws.x, lam, atol=1e-12)
        for _ in range(5):  # and from any other start (the SQP's first step guesses one):
            ws.mask[:] = rng.random(N) < rng.uniform(0.1, 0.9)  # the same nearest point
            newton.nearest(ws)                                   # (at n = 1 not the same x)
            assert abs(ws.x.sum() - 1) < 1e-14 and ws.x.min() >= 0
            assert np.allclose(ws.x @ D, lam @ D, rtol=0, atol=1e-12)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_three_nodes_match_a_simplex_grid(criterion):
    covs = instance(np.random.default_rng(7), 3, 2, "random")
    w, rel, _ = _sqp(covs, criterion)
    a, b = np.meshgrid(np.linspace(0, 1, 401), np.linspace(0, 1, 401))
    keep = a + b <= 1
    grid = np.stack([a[keep], b[keep], 1 - a[keep] - b[keep]], -1)
    f_grid = objective(covs, grid, criterion)
    f = objective(covs, w, criterion)
    scale = abs(f) if criterion == "trace" else 1.0
    assert rel <= newton.TOL
    assert f <= f_grid.min() + 1e-12 * scale  # no grid point beats it
    assert f_grid.min() - f <= 1e-4 * scale  # and the grid comes close (spacing 1/400)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", [2, 4])
def test_many_nodes_match_clarabel_with_a_small_support(n, kind, criterion):
    covs = instance(np.random.default_rng(n), 64, n, kind)
    means = np.zeros((64, n))
    r = fo.bci(means, covs, criterion)
    ref = fo.bci(means, covs, criterion, "clarabel", polish=False)
    scale = abs(ref.objective) if criterion == "trace" else 1.0
    assert r.status == "optimal"
    assert r.objective <= ref.objective + 1e-9 * scale
    assert (r.weights > 0).sum() <= n * n + 1  # the nearest point's support bound


@pytest.mark.parametrize("criterion", CRITERIA)
def test_pricing_finds_support_nodes_outside_the_first_working_set(criterion):
    """N > 2 (m + 1), m = n (n + 1) / 2: the SQP works on a set of nodes priced out on all
    of them (newton._priced). On problems whose optimum uses a node outside the first set
    (the m + 1 most negative gradients at uniform weights, from inverted informations in
    numpy here), the solver (called directly: fo.bci would rescue a failure from Clarabel's
    weights) certifies its weights, which equal those of the SQP on all nodes from uniform
    weights (newton.sqp) and are no worse than Clarabel's, in objective."""
    rng, outside, trace = np.random.default_rng(12), 0, criterion == "trace"
    for t in range(40):
        n = 2 + t % 2
        m1 = n * (n + 1) // 2 + 1
        N = 3 * m1 + 5
        covs = instance(rng, N, n, KINDS[t // 2 % 2])
        Ys = np.linalg.inv(covs)
        P = np.linalg.inv(Ys.mean(0))
        g = -np.einsum("ab,ibc,ca->i", P, Ys, P) if trace else -np.einsum("ab,iba->i", P, Ys)
        F, _ = _factors(covs)
        W, rel, its = np.empty((1, N)), np.empty(1), np.empty(1, dtype=np.int64)
        newton.solve(F[None], trace, W, False, W, rel, its)
        assert rel[0] <= newton.TOL
        outside += not set(np.flatnonzero(W[0])) <= set(np.argsort(g)[:m1])
        w_all, rel_all, _ = _sqp(covs, criterion)
        ref = fo.bci(np.zeros((N, n)), covs, criterion, "clarabel", polish=False)
        # all in the factor form (numpy's inverses lose 1e-9 here)
        f, f_all, f_ref = (evaluate_f(F, w, criterion) for w in (W[0], w_all, ref.weights))
        scale = abs(f_all) if trace else 1.0
        assert rel_all <= newton.TOL and abs(f - f_all) <= 1e-12 * scale
        assert f <= f_ref + 1e-12 * scale
    assert outside >= 2  # the pricing rounds were exercised


@pytest.mark.parametrize("criterion", CRITERIA)
def test_sqp_on_pairs_equals_the_one_dimensional_method(criterion):
    """Two independent algorithms for N = 2: the SQP and the 1-D method of closed_form."""
    rng = np.random.default_rng(10)
    for k in range(30):
        covs = instance(rng, 2, (2, 4, 6)[k % 3], KINDS[k % 2])
        F, _ = _factors(covs)
        w_pair, _ = closed_form.pair_weight(F, criterion == "trace", work(2, F.shape[1]))
        w_sqp, rel, _ = _sqp(covs, criterion)
        # one evaluation for both (the double inversion of `objective` is not accurate to
        # 1e-12 on ill-conditioned pairs)
        f = [evaluate_f(F, np.array([x, 1 - x]), criterion) for x in (w_pair, w_sqp[0])]
        assert abs(f[0] - f[1]) <= 1e-13 * max(abs(f[1]), 1.0)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_pair_matches_a_grid(criterion):
    covs = instance(np.random.default_rng(7), 2, 3, "random")
    F, _ = _factors(covs)
    w, _ = closed_form.pair_weight(F, criterion == "trace", work(2, 3))
    ws = np.linspace(0, 1, 20001)
    f = objective(covs, np.stack([ws, 1 - ws], -1), criterion)
    assert abs(w - ws[np.argmin(f)]) <= 1e-4
    assert objective(covs, np.array([w, 1 - w]), criterion) <= f.min() + 1e-14 * abs(f.min())


@pytest.mark.parametrize("criterion", CRITERIA)
def test_degenerate_nodes_converge(criterion):
    """Diagonal nodes, repeated nodes and identical nodes (weights not unique, the model's
    Hessian singular): a certificate within tolerance and no worse than Clarabel."""
    rng = np.random.default_rng(8)
    diagonal = np.einsum("ij,jk->ijk", 10.0 ** rng.uniform(-3, 3, (20, 3)), np.eye(3))
    repeated = np.repeat(instance(rng, 4, 3, "random"), 3, axis=0)
    identical = np.repeat(instance(rng, 1, 3, "random"), 5, axis=0)
    for covs in (diagonal, repeated, identical):
        means = np.zeros(covs.shape[:2])
        r = fo.bci(means, covs, criterion)
        ref = fo.bci(means, covs, criterion, "clarabel", polish=False)
        assert r.status == "optimal"
        assert r.objective <= ref.objective + 1e-10 * max(abs(ref.objective), 1.0)


def test_singular_hessian_many_more_nodes_than_n_squared():
    covs = instance(np.random.default_rng(3), 12, 1, "random")  # n^2 + 1 = 2 < N = 12
    w, rel, _ = _sqp(covs, "trace")
    assert rel <= newton.TOL
    best = np.argmin(covs[:, 0, 0])  # n = 1: the smallest variance alone is optimal
    assert objective(covs, w, "trace") <= covs[best, 0, 0] * (1 + 1e-13)


def test_start_at_a_vertex_reaches_the_same_optimum():
    covs = instance(np.random.default_rng(9), 7, 3, "ill-conditioned")
    a = _sqp(covs, "trace")[0]
    b, rel, _ = _sqp(covs, "trace", w0=np.eye(7)[3])
    assert rel <= newton.TOL
    f = [objective(covs, w, "trace") for w in (a, b)]
    assert abs(f[0] - f[1]) <= 1e-12 * f[0]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("criterion", CRITERIA)
def test_design_steps_are_the_multiplicative_algorithm(kind, criterion):
    """The starts of the SQP: from uniform weights, two steps w_i <- w_i tr(P Y_i P) / tr(P)
    for "trace", one step w_i <- w_i tr(P Y_i) / n for "logdet", against the same steps
    from inverted covariances in numpy; they stay on the simplex, positive, and each
    "trace" step lowers tr P (as the algorithm does on these problems)."""
    trace = criterion == "trace"
    steps = 2 if trace else 1
    covs = instance(np.random.default_rng(12), 5, 3, kind)
    F, _ = _factors(covs)
    ws = work(5, 3)
    w = np.full(5, 0.2)
    newton._design_steps(F, w, steps, ws.At, ws.Vt, ws.R, ws.Ri, ws.P, ws.B, ws.g, trace)
    Ys = np.linalg.inv(covs)
    ref, f = np.full(5, 0.2), [objective(covs, np.full(5, 0.2), "trace")]
    for _ in range(steps):
        P = np.linalg.inv(np.einsum("i,iab->ab", ref, Ys))
        ref = ref * (np.einsum("ab,ibc,ca->i", P, Ys, P) / np.trace(P) if trace else
                     np.einsum("ab,iba->i", P, Ys) / 3)
        f.append(objective(covs, ref, "trace"))
    # (the reference inverts covariances of condition up to 3e10 here and loses eps x that:
    # 2e-12 measured, so the match is absolute)
    assert np.allclose(w, ref, rtol=0, atol=1e-14 * np.linalg.cond(covs).max())
    assert (w > 0).all() and abs(w.sum() - 1.0) <= 8 * np.finfo(float).eps
    if trace:
        assert f[2] < f[1] < f[0]


def test_an_optimum_at_a_node_is_that_node_exactly_after_design_steps():
    """Design steps never reach a zero weight; the SQP step after them does. n = 1, where
    the node of the largest information is the optimum (a fuzz case of test_fuzz.py: after
    the design steps the weights were (1.6e-17, 1.2e-30, 1.0) with a certificate of 0,
    and were returned as such, no longer the node exactly)."""
    covs = np.array([3.84004971e-16, 1.42701748e-09, 1.55231520e-24]).reshape(3, 1, 1)
    means = np.array([[1.0], [2.0], [3.0]])
    r = fo.bci(means, covs, "trace")
    assert np.array_equal(r.weights, [0.0, 0.0, 1.0])
    assert r.mean[0] == 3.0 and r.cov[0, 0] == covs[2, 0, 0]


@pytest.mark.parametrize("criterion", CRITERIA)
def test_assemble_on_the_solvers_factors_equals_assemble_on_its_own(criterion):
    """fuse_exact hands assemble the QR (and gradient) the solver leaves at its weights;
    computing them anew (newton.solve, then assemble of the batch) gives the same numbers,
    bit for bit, on every hard kind, N from 1 to 8, BCI and MBCI scales."""
    rng = np.random.default_rng(13)
    for kind in EXTREME_KINDS:
        for N, n in ((1, 3), (2, 4), (3, 4), (8, 2)):
            B = 12
            covs = np.stack([extreme_instance(rng, N, n, kind, spread=6) for _ in range(B)])
            means = rng.standard_normal((B, N, n))
            for scales in (None, np.linspace(0.5, 0.95, N)):
                q, E = (core._unit_scales(B, N) if scales is None else (core._read_only(
                    np.broadcast_to(x, (B, N)).copy()) for x in detection_split(scales, 0.9, N)))
                one, two = core._Arrays(B, N, n), core._Arrays(B, N, n)
                trace = criterion == "trace"
                assert core.fuse_exact(means, covs, q, E, trace, one.F, one.k, one.vertex,
                                       one.pnorm, one.where, one.W, one.rel, one.iters,
                                       one.mean, one.cov, one.stats) == 0
                core._prepare(means, covs, q, E, two, core._NAMES, True)
                newton.solve(two.F, trace, two.W, False, two.W, two.rel, two.iters)
                assert assemble(two.F, means, covs, q, E, two.k, two.vertex, two.pnorm, two.W,
                                trace, two.mean, two.cov, two.stats)
                for name in ("W", "mean", "cov", "stats", "iters"):
                    assert np.array_equal(getattr(one, name), getattr(two, name)), (kind, N)


def test_equal_certificates_count_as_a_stall():
    """Of equal certificates the later iterate is kept, and counted as a stall: when a tie
    reset the count, this ill-conditioned problem cycled at rounding level to the
    iteration cap (62 steps; 15 now)."""
    rng = np.random.default_rng(9)
    covs = instance(rng, 300 * 3, 4, "ill-conditioned").reshape(300, 3, 4, 4)[32]
    r = fo.bci(np.zeros((3, 4)), covs, "trace")
    assert r.status == "optimal" and r.iterations <= 20


def test_zero_failures_on_many_ill_conditioned():
    rng = np.random.default_rng(11)
    for k in range(60):
        n, N, crit = (2, 4, 6)[k % 3], (3, 7, 16)[k // 3 % 3], CRITERIA[k % 2]
        covs = instance(rng, N, n, "ill-conditioned")
        assert fo.bci(np.zeros((N, n)), covs, crit).status == "optimal", k


def test_no_progress_near_the_optimum_stops_after_a_few_steps():
    """The stall rule: at rounding level the SQP stops after a few steps without a better
    certificate instead of running to its iteration cap."""
    covs = instance(np.random.default_rng(11), 5, 2, "random")
    F, _ = _factors(covs)
    w = np.full(5, 0.2)
    rel, it = newton.sqp(F, True, w, work(5, 2), 0.0, 500)  # a tolerance never reached
    assert rel <= 1e-13 and it < 40


def test_pair_ladder_log_det_of_a_product_equals_the_sum_of_logs_to_the_last_digits():
    """closed_form._value takes one log of a product where it can: against math.fsum of
    the n logs, at factors from 1 down to 1e-320 (denormal) and at a pole (a factor 0)."""
    rng = np.random.default_rng(11)
    for n in (1, 4, 48, 200):
        for low in (0.0, -50.0, -150.0, -320.0):
            d = 10.0 ** rng.uniform(low, 0.0, n)
            abc = np.stack([np.zeros(n), d, np.ones(n)])  # d_k(w) = d_k at every w
            want = -math.fsum(np.log(d))
            got = closed_form._value(0.5, abc, False)
            assert abs(got - want) <= 8 * n * np.finfo(float).eps * max(abs(want), 1.0)
    abc = np.stack([np.zeros(3), np.array([0.5, 0.0, 0.25]), np.ones(3)])
    assert closed_form._value(0.5, abc, False) == np.inf


@pytest.mark.parametrize(("N", "n"), [(1, 1), (2, 4), (3, 2), (40, 3), (7, 12)])
def test_work_buffers_have_their_shapes_and_share_no_memory(N, n):
    """`work` carves buffers of one shape from one allocation: each has the shape its
    kernels index it by (K = min(N, n^2 + 1) columns of the nearest-point problem), no two
    overlap, Et's simplex column is 1 and the mask starts empty."""
    m, K = n * n, min(N, n * n + 1)
    want = {"At": (n, N * n), "Vt": (n, N * n), "R": (n, n), "Ri": (n, n), "P": (n, n),
            "B": (n, n), "X": (n, n), "S": (n, n), "lam": (n,), "U": (n, n), "zeta": (m,),
            "g": (N,), "Et": (N, m + 1), "x": (N,), "z": (N,), "mask": (N,), "r": (m + 1,),
            "cols": (N,), "Elt": (K, m + 1), "Vlt": (K, m + 1), "Rls": (K, K),
            "qe": (m + 1,), "w_try": (N,), "best_w": (N,), "rhs": (N * n,), "abc": (3, n)}
    ws = work(N, n)
    assert {name: a.shape for name, a in ws._asdict().items()} == want
    for a in ws:
        a[...] = 0  # every element is writable
    for (i, a), (j, b) in itertools.combinations(enumerate(ws), 2):
        assert not np.shares_memory(a, b), (ws._fields[i], ws._fields[j])
    ws = work(N, n)
    assert np.all(ws.Et[:, m] == 1.0) and not ws.mask.any()
    assert all(a.flags.c_contiguous for a in ws)


@pytest.mark.parametrize("n", [3, 17, 60])
def test_pair_products_through_blas_are_the_loops_products(n):
    """Above SMALL a pair's S = Q_a^T Q_a and B = Q_a U, X = Q_b U are BLAS products of
    copies of Q_a and Q_b (closed_form._q_blocks): the same as the loops (_q_gram,
    _q_times) to rounding, and Q_a^T Q_a + Q_b^T Q_b = I."""
    F, _ = _factors(instance(np.random.default_rng(n), 2, n, "random"))
    ws = work(2, n)
    for a in range(n):
        ws.At[:, a], ws.At[:, n + a] = F[0, a], F[1, a]
    linalg.householder(ws.At, n, 2 * n, ws.Vt, ws.R)
    linalg.thin_qt(ws.Vt, n, 2 * n, ws.At)
    Qa, Qb, S, Sb, S_loops = (np.empty((n, n)) for _ in range(5))
    closed_form._q_blocks(ws.At, Qa, Qb)
    np.testing.assert_array_equal(np.hstack([Qa.T, Qb.T]), ws.At[:, :2 * n])
    linalg.gram(Qa, S)
    linalg.gram(Qb, Sb)
    closed_form._q_gram(ws.At, S_loops)
    np.testing.assert_allclose(S, S_loops, rtol=0, atol=1e-13)
    np.testing.assert_allclose(S + Sb, np.eye(n), rtol=0, atol=1e-13)
    U = np.linalg.qr(np.random.default_rng(0).standard_normal((n, n)))[0]
    B, X, B_loops, X_loops = (np.empty((n, n)) for _ in range(4))
    linalg.matmul(Qa, U, B)
    linalg.matmul(Qb, U, X)
    closed_form._q_times(ws.At, U, B_loops, X_loops)
    np.testing.assert_allclose(B, B_loops, rtol=0, atol=1e-13)
    np.testing.assert_allclose(X, X_loops, rtol=0, atol=1e-13)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize(("N", "n"), [(2, 150), (3, 130)])
def test_large_n_is_optimal_by_the_numpy_criteria(N, n, criterion):
    """At large n (a pair's products through BLAS, the triangular inverse by rows): the
    objective and certificate of fo.bci against f and g of criteria.py from inverted
    informations at the returned weights, and for a pair against a bounded 1-D search."""
    rng = np.random.default_rng(n)
    covs, means = instance(rng, N, n, "random"), rng.standard_normal((N, n))
    r = fo.bci(means, covs, criterion)
    Ys = np.linalg.inv(covs)
    ev = evaluate(Ys, r.weights, criterion)
    scale = abs(ev.f) if criterion == "trace" else 1.0
    assert abs(r.objective - ev.f) <= 1e-10 * scale
    assert ev.g @ r.weights - ev.g.min() <= 1e-10 * scale
    np.testing.assert_allclose(r.cov, np.linalg.inv(np.tensordot(r.weights, Ys, 1)),
                               rtol=1e-9, atol=1e-12 * np.abs(r.cov).max())
    if N == 2:
        import scipy.optimize
        ref = scipy.optimize.minimize_scalar(
            lambda w: evaluate(Ys, np.array([w, 1.0 - w]), criterion).f, bounds=(0.0, 1.0),
            method="bounded", options={"xatol": 1e-10})
        assert r.objective <= ref.fun + 1e-12 * scale
