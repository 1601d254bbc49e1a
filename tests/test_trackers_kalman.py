"""Kalman filter against the dense posterior of the stacked linear-Gaussian model."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from trackers import kalman, models


def dense_filtered(model, m0, P0, scans):
    """Filtered moments by conditioning the joint Gaussian of all states and measurements.

    States z = (x_0, ..., x_{T-1}) with x_{-1} ~ N(m0, P0) and x_k = A x_{k-1} + q_k; each
    measurement is y = H x_k + r. For step k condition on the measurements of steps <= k.
    """
    A, Q, H, R = model.A, model.Q, model.H, model.R
    n, T = model.n, len(scans)
    # x_k = A^{k+1} x_{-1} + sum_{j<=k} A^{k-j} q_j: write z = G w with w = (x_{-1}, q_0..)
    G = np.zeros((T * n, (T + 1) * n))
    for k in range(T):
        for j in range(-1, k + 1):
            G[k * n:(k + 1) * n, (j + 1) * n:(j + 2) * n] = np.linalg.matrix_power(A, k - j)
    W = np.zeros(((T + 1) * n, (T + 1) * n))
    W[:n, :n] = P0
    for j in range(T):
        W[(j + 1) * n:(j + 2) * n, (j + 1) * n:(j + 2) * n] = Q
    mu_w = np.concatenate([m0, np.zeros(T * n)])
    mu_z, S_z = G @ mu_w, G @ W @ G.T

    means, covs = [], []
    for k in range(T):
        rows, ys, steps = [], [], []
        for j in range(k + 1):
            for y in scans[j]:
                Hj = np.zeros((model.d, T * n))
                Hj[:, j * n:(j + 1) * n] = H
                rows.append(Hj)
                ys.append(y)
                steps.append(j)
        sl = slice(k * n, (k + 1) * n)
        if not rows:
            means.append(mu_z[sl])
            covs.append(S_z[sl, sl])
            continue
        Hs = np.vstack(rows)
        Rs = np.kron(np.eye(len(ys)), R)
        S = Hs @ S_z @ Hs.T + Rs
        K = S_z @ Hs.T @ np.linalg.inv(S)
        post_m = mu_z + K @ (np.concatenate(ys) - Hs @ mu_z)
        post_P = S_z - K @ S @ K.T
        means.append(post_m[sl])
        covs.append(post_P[sl, sl])
    return np.array(means), np.array(covs)


def test_kf_equals_dense_posterior():
    rng = np.random.default_rng(3)
    model = models.turn_model(0.4, 0.3, 0.2, 0.5)
    m0 = np.array([1.0, -1.0, 0.5, 0.2])
    P0 = np.diag([0.5, 0.4, 0.3, 0.2])
    counts = [1, 0, 2, 1, 0, 0, 3, 1]  # empty steps and several measurements per step
    scans = [rng.normal(size=(c, 2)) for c in counts]
    out = kalman.run(scans, model, m0, P0)
    ref_m, ref_P = dense_filtered(model, m0, P0, scans)
    np.testing.assert_allclose(out.means, ref_m, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(out.covs, ref_P, rtol=1e-9, atol=1e-10)


def test_batched_steps_equal_one_at_a_time():
    rng = np.random.default_rng(5)
    model = models.turn_model(0.0, 0.1, 0.05, 0.1)
    N = 7
    m = rng.normal(size=(N, 4))
    B = rng.normal(size=(N, 4, 4))
    P = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(4)
    y = rng.normal(size=(N, 2))
    mp, Pp = kalman.predict(m, P, model.A, model.Q)
    mu, Pu, ll = kalman.update_with_loglik(mp, Pp, y, model.H, model.R)
    for i in range(N):
        mpi, Ppi = kalman.predict(m[i], P[i], model.A, model.Q)
        np.testing.assert_allclose(mp[i], mpi, rtol=1e-13)
        np.testing.assert_allclose(Pp[i], Ppi, rtol=1e-13)
        mui, Pui = kalman.update(mpi, Ppi, y[i], model.H, model.R)
        np.testing.assert_allclose(mu[i], mui, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(Pu[i], Pui, rtol=1e-12, atol=1e-13)
        S = model.H @ Ppi @ model.H.T + model.R
        ref = multivariate_normal(model.H @ mpi, S).logpdf(y[i])
        assert ll[i] == pytest.approx(ref, rel=1e-12)
        lli = kalman.log_likelihood(mpi, Ppi, y[i], model.H, model.R)
        assert lli == pytest.approx(ref, rel=1e-12)


def test_run_rejects_bad_input():
    model = models.turn_model(0.0, 0.1, 0.05, 0.1)
    m0, P0 = np.zeros(4), np.eye(4)
    with pytest.raises(ValueError, match="m0 must have shape"):
        kalman.run([np.zeros((1, 2))], model, np.zeros((4, 1)), P0)
    with pytest.raises(ValueError, match="P0 must be positive definite"):
        kalman.run([np.zeros((1, 2))], model, m0, -P0)
    with pytest.raises(ValueError, match=r"scans\[1\] must have shape"):
        kalman.run([np.zeros((1, 2)), np.zeros((1, 3))], model, m0, P0)
    with pytest.raises(ValueError, match=r"scans\[0\] contains non-finite"):
        kalman.run([np.array([[np.nan, 0.0]])], model, m0, P0)
    with pytest.raises(ValueError, match="model must be"):
        kalman.run([np.zeros((1, 2))], "model", m0, P0)
