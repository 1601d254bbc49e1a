"""The single-problem Newton (SQP) solver and the scalar pairwise solver against independent
references: criteria.py's derivatives, grids, CVXPY, the batched solvers and Clarabel."""

import cvxpy as cp
import numpy as np
import pytest
from conftest import objective

import fusion_opt as fo
from fusion_opt.backends import REGISTRY, closed_form, newton
from fusion_opt.criteria import evaluate
from fusion_opt.fusion import information
from fusion_opt.scaling import scale
from studies.backends import instance

CRITERIA = ("trace", "logdet")
KINDS = ("random", "ill-conditioned")


def _scaled(covs, criterion):
    return scale(information(covs), criterion)


def _f(sp, w, criterion):
    return evaluate(sp.Ys, w, criterion, sp.M).f


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("kind", KINDS)
def test_whitened_model_has_the_gradient_and_hessian_of_criteria(kind, criterion):
    # rho = 1: the model is Newton's, so d_i - d_j = z_i - z_j and H_ij = z_i . z_j
    sp = _scaled(instance(np.random.default_rng(4), 6, 3, kind), criterion)
    w = np.random.default_rng(5).dirichlet(np.ones(6))
    pb = newton._prepare(sp.Ys, sp.M, criterion)
    g = newton._model(pb, newton._value(pb, w)[1], 1.0)
    D = pb.E[:-1].T
    ev = evaluate(sp.Ys, w, criterion, sp.M, hessian=True)
    assert np.allclose(g, ev.g, rtol=1e-9, atol=1e-12 * np.abs(ev.g).max())
    Q = np.vstack([np.eye(5), -np.ones(5)])  # directions with sum 0: Q^T H Q = A A^T
    A = Q.T @ D
    H = Q.T @ ev.H @ Q
    assert np.allclose(A @ A.T, H, rtol=1e-8, atol=1e-10 * np.abs(H).max())


def test_nearest_point_matches_cvxpy_and_the_face_test():
    rng = np.random.default_rng(6)
    for N, m in ((5, 2), (12, 3), (40, 6)):
        D = rng.standard_normal((N, m)) + 1.5  # 0 outside the hull: a boundary point
        lam = newton._nearest(np.vstack([D.T, np.ones(N)]), np.full(N, 1.0 / N))
        x = cp.Variable(N, nonneg=True)
        cp.Problem(cp.Minimize(cp.sum_squares(D.T @ x)), [cp.sum(x) == 1]).solve("CLARABEL")
        assert abs(lam.sum() - 1) < 1e-14 and lam.min() >= 0
        assert np.linalg.norm(lam @ D) <= np.linalg.norm(x.value @ D) + 1e-8
        S = np.flatnonzero(lam)
        assert np.allclose(newton._nearest_on_face(D, S), lam, atol=1e-12)
        # a face missing a node of the optimum fails Wolfe's test (or is too small to try)
        assert newton._nearest_on_face(D, S[1:]) is None


@pytest.mark.parametrize("criterion", CRITERIA)
def test_three_nodes_match_a_simplex_grid(criterion):
    covs = instance(np.random.default_rng(7), 3, 2, "random")
    sp = _scaled(covs, criterion)
    sol = newton.solve_one(sp.Ys, sp.M, criterion)
    a, b = np.meshgrid(np.linspace(0, 1, 401), np.linspace(0, 1, 401))
    keep = a + b <= 1
    grid = np.stack([a[keep], b[keep], 1 - a[keep] - b[keep]], -1)
    f_grid = objective(covs, grid, criterion)
    f = objective(covs, sol.w[0], criterion)
    scale_f = abs(f) if criterion == "trace" else 1.0
    assert sol.converged[0]
    assert f <= f_grid.min() + 1e-12 * scale_f  # no grid point beats it
    assert f_grid.min() - f <= 1e-4 * scale_f  # and the grid comes close (spacing 1/400)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", [2, 4])
def test_many_nodes_match_clarabel_with_a_small_support(n, kind, criterion):
    sp = _scaled(instance(np.random.default_rng(n), 64, n, kind), criterion)
    sol = newton.solve_one(sp.Ys, sp.M, criterion)
    ref = REGISTRY["clarabel-direct"](sp.Ys, sp.M, criterion).w
    f, f_ref = _f(sp, sol.w[0], criterion), _f(sp, np.maximum(ref, 0) / ref.clip(0).sum(),
                                                 criterion)
    assert sol.converged[0] and sol.rel_gap[0] <= newton.TOL
    assert f <= f_ref + 1e-9 * (abs(f_ref) if criterion == "trace" else 1.0)
    assert (sol.w[0] > 0).sum() <= n * (n + 1) // 2 + 1


@pytest.mark.parametrize("criterion", CRITERIA)
def test_degenerate_nodes_converge_like_the_batched_solver(criterion):
    rng = np.random.default_rng(8)
    diagonal = np.einsum("ij,jk->ijk", 10.0 ** rng.uniform(-3, 3, (20, 3)), np.eye(3))
    repeated = np.repeat(instance(rng, 4, 3, "random"), 3, axis=0)
    identical = np.repeat(instance(rng, 1, 3, "random"), 5, axis=0)
    for covs in (diagonal, repeated, identical):
        sp = _scaled(covs, criterion)
        sol = newton.solve_one(sp.Ys, sp.M, criterion)
        batched = newton.solve(sp.Ys[None], sp.M[None], criterion).w[0]
        assert sol.converged[0]
        assert _f(sp, sol.w[0], criterion) <= _f(sp, batched, criterion) + 1e-13


def test_start_at_a_vertex_reaches_the_same_optimum():
    sp = _scaled(instance(np.random.default_rng(9), 7, 3, "ill-conditioned"), "trace")
    a = newton.solve_one(sp.Ys, sp.M, "trace")
    b = newton.solve_one(sp.Ys, sp.M, "trace", w0=np.eye(7)[3])
    assert b.converged[0]
    assert abs(_f(sp, a.w[0], "trace") - _f(sp, b.w[0], "trace")) <= 1e-12


def test_qp_iteration_limit_is_a_solver_error(monkeypatch):
    def stuck(*args, **kwargs):
        raise RuntimeError("Maximum number of iterations reached.")

    monkeypatch.setattr(newton, "nnls", stuck)
    with pytest.raises(fo.FusionSolverError, match="newton"):
        fo.bci(np.zeros((3, 2)), instance(np.random.default_rng(1), 3, 2, "random"),
               backend="newton")


@pytest.mark.parametrize("criterion", CRITERIA)
def test_scalar_pair_solver_equals_the_vectorised_one(criterion):
    rng = np.random.default_rng(10)
    for k in range(40):
        sp = _scaled(instance(rng, 2, (2, 4, 6)[k % 3], KINDS[k % 2]), criterion)
        lam, T = closed_form.diagonalise_information(sp.Ys[0], sp.Ys[1])
        c = ((sp.M @ T) * T).sum(0) if criterion == "trace" else lam
        w_scalar, _ = closed_form._solve_scalar(lam - 1.0, c, criterion)
        w_batch, _, _ = closed_form.solve_weight((lam - 1.0)[None], c[None], criterion)
        f = [closed_form.objective(np.array(x), lam - 1.0, c, criterion)
             for x in (w_scalar, w_batch[0])]
        assert abs(f[0] - f[1]) <= 1e-13 * max(abs(f[1]), 1.0)


def test_no_progress_near_the_optimum_stops_after_a_few_steps(monkeypatch):
    sp = _scaled(instance(np.random.default_rng(11), 5, 2, "random"), "trace")
    w = newton.solve_one(sp.Ys, sp.M, "trace", tol=1e-6).w[0]  # in the local phase
    monkeypatch.setattr(newton, "_nearest", lambda E, w_: w)  # a QP that never moves
    sol = newton.solve_one(sp.Ys, sp.M, "trace", w0=w)
    assert not sol.converged[0] and sol.iterations[0] == newton._STALL
    monkeypatch.setattr(newton, "_nearest", lambda E, w_: np.eye(5)[0])
    far = newton.solve_one(sp.Ys, sp.M, "trace", w0=np.eye(5)[0], max_iter=12)
    assert far.rel_gap[0] > 1e-3 and far.iterations[0] == 12  # far away it does not give up
