"""`fusion_opt.criteria`, the numpy objective, gradient, Hessian and certificate that the
Newton tests and the backend study take as their reference: against `conftest.objective`
and central finite differences of it, computed here apart from the module."""

import numpy as np
import pytest
from conftest import random_instance

from fusion_opt import criteria


def _f(Ys, w, criterion, M):
    """tr(M P(w)) or -log det Y(w), P = Y^-1, Y(w) = sum_i w_i Y_i, straight from numpy."""
    Y = np.einsum("i,ijk->jk", w, Ys)
    if criterion == "logdet":
        return -np.linalg.slogdet(Y)[1]
    return np.trace(M @ np.linalg.inv(Y))


def _differences(Ys, w, criterion, M, h=1e-4):
    """Gradient (N,) and Hessian (N, N) of _f at w by central differences (error O(h^2),
    about 1e-8 relative here), in every direction of R^N."""
    N = len(w)
    E = np.eye(N) * h
    g = np.array([(_f(Ys, w + e, criterion, M) - _f(Ys, w - e, criterion, M)) / (2 * h)
                  for e in E])
    H = np.array([[(_f(Ys, w + a + b, criterion, M) - _f(Ys, w + a - b, criterion, M)
                    - _f(Ys, w - a + b, criterion, M) + _f(Ys, w - a - b, criterion, M))
                   / (4 * h * h) for b in E] for a in E])
    return g, H


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("weighted", [False, True])
def test_objective_gradient_and_hessian_match_finite_differences(criterion, weighted):
    rng = np.random.default_rng(11 + weighted)
    for n, N in ((1, 2), (2, 3), (3, 4), (4, 5)):
        covs = random_instance(rng, n, N)[1]
        Ys = np.linalg.inv(covs)
        A = rng.standard_normal((n, n))
        M = A @ A.T + np.eye(n) if weighted else np.eye(n)
        w = rng.dirichlet(np.ones(N))
        ev = criteria.evaluate(Ys, w, criterion, M if weighted else None, hessian=True)
        g, H = _differences(Ys, w, criterion, M)
        assert ev.f == pytest.approx(_f(Ys, w, criterion, M), rel=1e-12)
        np.testing.assert_allclose(ev.g, g, rtol=1e-6, atol=1e-7 * np.abs(g).max())
        np.testing.assert_allclose(ev.H, H, rtol=1e-4, atol=1e-5 * np.abs(H).max())
        np.testing.assert_allclose(ev.H, ev.H.T, rtol=1e-14, atol=0)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_nodes_give_a_block_of_the_hessian_and_batches_broadcast(criterion):
    rng = np.random.default_rng(12)
    B, N, n = 3, 5, 3
    Ys = np.linalg.inv(np.stack([random_instance(rng, n, N)[1] for _ in range(B)]))
    w = rng.dirichlet(np.ones(N), size=B)
    nodes = np.stack([rng.choice(N, 3, replace=False) for _ in range(B)])
    whole = criteria.evaluate(Ys, w, criterion, hessian=True)
    block = criteria.evaluate(Ys, w, criterion, hessian=True, nodes=nodes)
    for b in range(B):
        one = criteria.evaluate(Ys[b], w[b], criterion, hessian=True)
        np.testing.assert_allclose(whole.f[b], one.f, rtol=1e-14)
        np.testing.assert_allclose(whole.g[b], one.g, rtol=1e-13)
        np.testing.assert_allclose(whole.H[b], one.H, rtol=1e-13)
        np.testing.assert_allclose(block.H[b], one.H[np.ix_(nodes[b], nodes[b])], rtol=1e-13)


def test_gap_is_the_vertex_bound():
    """gap(g, w) = g.w - min_i g_i, 0 at a vertex whose gradient entry is the least."""
    g = np.array([[-3.0, -1.0, -2.0], [-1.0, -2.0, -0.5]])
    w = np.array([[0.2, 0.5, 0.3], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(criteria.gap(g, w), [-0.6 - 0.5 - 0.6 + 3.0, 0.0])
