"""Properties of CI/BCI: node permutation, covariance scaling, consistency under any
cross-correlation (DESIGN §1)."""

import numpy as np
import pytest
from conftest import random_instance
from hypothesis import given, settings
from hypothesis import strategies as st

import fusion_opt as fo

seeds = st.integers(0, 2**32 - 1)
crit = st.sampled_from(["trace", "logdet"])


@settings(max_examples=30, deadline=None)
@given(seed=seeds, n=st.integers(2, 4), N=st.integers(2, 3), criterion=crit)
def test_permuting_nodes_permutes_weights(seed, n, N, criterion):
    """N <= n(n+1)/2 keeps the weights unique, so they must follow the permutation."""
    rng = np.random.default_rng(seed)
    means, covs = random_instance(rng, n, N)
    perm = rng.permutation(N)
    r, rp = fo.bci(means, covs, criterion), fo.bci(means[perm], covs[perm], criterion)
    assert rp.objective == pytest.approx(r.objective, rel=1e-10, abs=1e-12)
    np.testing.assert_allclose(rp.weights, r.weights[perm], atol=1e-6)
    np.testing.assert_allclose(rp.mean, r.mean, rtol=1e-6, atol=1e-7)


@settings(max_examples=30, deadline=None)
@given(seed=seeds, n=st.integers(1, 4), N=st.integers(2, 5), criterion=crit,
       log_c=st.floats(-4, 4))
def test_scaling_covariances_keeps_weights(seed, n, N, criterion, log_c):
    rng = np.random.default_rng(seed)
    means, covs = random_instance(rng, n, N)
    c = 10.0**log_c
    r, rc = fo.bci(means, covs, criterion), fo.bci(means, c * covs, criterion)
    # objectives are compared, weights need not be unique (N may exceed n(n+1)/2)
    expected = c * r.objective if criterion == "trace" else r.objective + n * np.log(c)
    assert rc.objective == pytest.approx(expected, rel=1e-10, abs=1e-10)
    if N <= n * (n + 1) // 2:
        np.testing.assert_allclose(rc.weights, r.weights, atol=1e-6)
        np.testing.assert_allclose(rc.cov, c * r.cov, rtol=1e-6, atol=1e-9 * c)


def _joint_covariance(rng, covs, kind: str) -> np.ndarray:
    """A joint error covariance (Nn, Nn) with diagonal blocks covs[i] and random cross
    blocks P_i^(1/2) U_i^T U_j P_j^(1/2), U_i (m, n) with orthonormal columns, so the
    joint is PSD. kind "full" makes all U_i equal (fully correlated errors)."""
    N, n = covs.shape[:2]
    m = n if kind == "full" else rng.integers(n, 3 * n + 1)
    U = [np.linalg.qr(rng.standard_normal((m, n)))[0] for _ in range(N)]
    if kind == "full":
        U = [U[0]] * N
    roots = [np.linalg.cholesky(P) for P in covs]
    G = np.concatenate([u @ r.T for u, r in zip(U, roots, strict=True)], axis=1)  # (m, Nn)
    return G.T @ G


def _gains(method, criterion, covs) -> np.ndarray:
    """[K_1 ... K_N] (n, N n) of fo.fuse's mean, read off as a black box: at fixed
    covariances the weights are fixed and the mean is linear in the means, so a unit
    vector in a node's mean gives a column of its gain."""
    N, n = covs.shape[:2]
    K = np.empty((n, N * n))
    for j in range(N * n):
        unit = np.zeros(N * n)
        unit[j] = 1.0
        K[:, j] = fo.fuse(unit.reshape(N, n), covs, method, criterion).mean
    return K


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_ci_is_consistent_under_500_random_cross_correlations(criterion):
    """The fused covariance of BCI (its optimal weights) and of fast CI (heuristic weights)
    covers the true error covariance K S K^T of its own mean's gains whatever the
    correlations: r.cov - K S K^T is PSD, S random joints with the given diagonal blocks
    (one in five fully correlated)."""
    rng = np.random.default_rng(42 + len(criterion))
    worst = np.inf
    for k in range(500):
        n, N = rng.integers(1, 5), rng.integers(2, 5)
        means, covs = random_instance(rng, n, N)
        S = _joint_covariance(rng, covs, "full" if k % 5 == 0 else "random")
        for method in ("bci", "fast-ci"):
            r = fo.fuse(means, covs, method, criterion)
            K = _gains(method, criterion, covs)
            np.testing.assert_allclose(K @ means.reshape(-1), r.mean, rtol=1e-9, atol=1e-9)
            excess = r.cov - K @ S @ K.T
            worst = min(worst, np.linalg.eigvalsh(excess).min() / np.linalg.norm(r.cov, 2))
    assert worst >= -1e-10


def test_mbci_is_consistent_where_ci_is():
    """Phat >= P(w) for the MBCI weights, so the true error covariance is still covered."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        n, N = rng.integers(1, 5), rng.integers(2, 5)
        means, covs = random_instance(rng, n, N)
        S = _joint_covariance(rng, covs, "random")
        r = fo.mbci(means, covs, rng.uniform(0, 1, N), rng.uniform(0.2, 1, N))
        Ys = np.linalg.inv(covs)
        P = np.linalg.inv(np.einsum("i,ijk->jk", r.weights, Ys))
        K = np.concatenate([P @ (wi * Y) for wi, Y in zip(r.weights, Ys, strict=True)], axis=1)
        assert np.linalg.eigvalsh(r.cov - K @ S @ K.T).min() >= -1e-10 * np.linalg.norm(P, 2)
