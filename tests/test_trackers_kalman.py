"""Kalman filter against the dense posterior of the stacked linear-Gaussian model."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from fusion_opt import Estimates, FusionInputError
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


def _table1_scans(n_steps=200, seed=1):
    from trackers import scenarios

    cfg = scenarios.Table1Config(n_steps=n_steps)
    data = scenarios.simulate_table1(cfg, np.random.default_rng(seed))
    m0, P0 = cfg.prior()
    return cfg.filter_model(), m0, P0, data.nodes[1].scans


def test_stepped_filter_equals_run_bit_for_bit():
    model, m0, P0, scans = _table1_scans()
    out = kalman.run(scans, model, m0, P0)
    kf = kalman.KalmanFilter(model, m0, P0, name="node a")
    for t, scan in enumerate(scans):
        est = kf.step(scan, time=0.025 * (t + 1))
        assert isinstance(est, Estimates) and len(est) == 1
        assert est.ids.tolist() == [0] and est.node == "node a"
        assert est.time == 0.025 * (t + 1)
        np.testing.assert_array_equal(est.means[0], out.means[t])
        np.testing.assert_array_equal(est.covs[0], out.covs[t])
        np.testing.assert_array_equal(kf.mean, out.means[t])
    assert kf.steps == len(scans)
    assert kalman.KalmanFilter(model, m0, P0).step([]).time is None


def test_filter_state_is_read_only_and_empty_scans_predict():
    model, m0, P0, _ = _table1_scans(n_steps=2)
    kf = kalman.KalmanFilter(model, m0, P0)
    np.testing.assert_array_equal(kf.mean, m0)
    for empty in ([], np.empty((0, 2))):
        kf.step(empty)
    ref = kalman.predict(*kalman.predict(m0, P0, model.A, model.Q), model.A, model.Q)
    np.testing.assert_allclose(kf.mean, ref[0], rtol=1e-14)
    np.testing.assert_allclose(kf.cov, ref[1], rtol=1e-13)
    with pytest.raises(ValueError):
        kf.mean[0] = 1.0
    with pytest.raises(ValueError):
        kf.cov[0, 0] = 1.0


@pytest.mark.parametrize(
    ("scan", "match"),
    [(None, "scan must be an array-like"), ("1, 2", "scan must be an array of real numbers"),
     ([[1 + 1j, 0.0]], "complex"), ([[True, 0.0]], "boolean"),
     ([[np.nan, 0.0]], "non-finite"), ([0.1, 0.2], r"shape \(k, 2\)"),
     ({"y": 1}, "scan must be an array of real numbers"), ([[1.0], [2.0]], r"shape \(k, 2\)")])
def test_step_refuses_bad_scans(scan, match):
    model, m0, P0, _ = _table1_scans(n_steps=2)
    kf = kalman.KalmanFilter(model, m0, P0)
    with pytest.raises(FusionInputError, match=match):
        kf.step(scan)
    assert kf.steps == 0
    with pytest.raises(FusionInputError, match=match.replace("scan", r"scans\[0\]")):
        kalman.run([scan], model, m0, P0)


@pytest.mark.parametrize("scans", [None, "abc", 3.0, {"a": 1}, []])
def test_run_refuses_non_sequences(scans):
    model, m0, P0, _ = _table1_scans(n_steps=2)
    with pytest.raises(FusionInputError, match="scans must"):
        kalman.run(scans, model, m0, P0)


def _network_errors(model, m0, P0, detected, runs, rng):
    """Errors x - m_i (runs, N, n) after len(detected) steps of N Kalman filters of one
    target: truth drawn from the model and the prior, node i measuring at step k iff
    detected[k, i], with its own noise. Filters run batched over the runs."""
    T, N = detected.shape
    n = model.n
    Lq, Lr = np.linalg.cholesky(model.Q), np.linalg.cholesky(model.R)
    x = m0 + rng.standard_normal((runs, n)) @ np.linalg.cholesky(P0).T
    m = np.broadcast_to(m0, (N, runs, n)).copy()
    P = [np.broadcast_to(P0, (runs, n, n)).copy() for _ in range(N)]
    for k in range(T):
        x = x @ model.A.T + rng.standard_normal((runs, n)) @ Lq.T
        for i in range(N):
            m[i], P[i] = kalman.predict(m[i], P[i], model.A, model.Q)
            if detected[k, i]:
                y = x @ model.H.T + rng.standard_normal((runs, model.d)) @ Lr.T
                m[i], P[i] = kalman.update(m[i], P[i], y, model.H, model.R)
    return x[:, None, :] - np.swapaxes(m, 0, 1)


def test_cross_covariance_matches_monte_carlo():
    """The recursion against the sample covariance of the joint errors of three filters
    with a common prior over 4000 seeded runs (a fixed detection pattern, so the exact
    joint covariance is the same in every run)."""
    model = models.turn_model(0.0, 0.5, 0.2, 0.5)
    m0, P0 = np.array([0.0, 0.0, 1.0, 0.0]), np.diag([1.0, 1.0, 0.5, 0.5])
    detected = np.array([[1, 0, 1], [1, 1, 0], [0, 1, 0], [1, 1, 1], [0, 0, 1], [1, 0, 0]],
                        dtype=bool)
    N, n = 3, 4
    C = np.broadcast_to(P0, (N, N, n, n)).copy()
    for det in detected:
        C, _ = kalman.cross_covariance_step(C, det, model)
    runs = 4000
    err = _network_errors(model, m0, P0, detected, runs, np.random.default_rng(7))
    sample = np.cov(err.reshape(runs, N * n).T)
    exact = C.transpose(0, 2, 1, 3).reshape(N * n, N * n)
    # entry-wise sampling sd is sqrt((S_ii S_jj + S_ij^2) / runs) <= sqrt(2 / runs) max S_ii
    tol = 4.5 * np.sqrt(2.0 / runs) * np.sqrt(np.outer(np.diag(exact), np.diag(exact)))
    assert np.all(np.abs(sample - exact) <= tol)
    # the cross terms matter: with them set to 0 (independent nodes) the check would fail
    cross = ~np.kron(np.eye(N, dtype=bool), np.ones((n, n), dtype=bool))
    assert np.sum(np.abs(sample - np.where(cross, 0.0, exact)) > tol) > 20


def test_cross_covariance_diagonal_and_gains_are_each_filters_own():
    """C_ii is node i's Kalman covariance and K_i its gain: the mean update with K_i equals
    the filter's, for every node and step (a node that missed has K_i = 0)."""
    model = models.turn_model(0.3, 0.2, 0.1, 0.2)
    m0, P0 = np.array([1.0, -1.0, 0.5, 0.0]), 0.7 * np.eye(4)
    rng = np.random.default_rng(3)
    N = 4
    filters = [kalman.KalmanFilter(model, m0, P0) for _ in range(N)]
    m = np.tile(m0, (N, 1))
    C = np.broadcast_to(P0, (N, N, 4, 4)).copy()
    for _ in range(15):
        det = rng.random(N) < 0.6
        ys = rng.normal(size=(N, 2))
        C, K = kalman.cross_covariance_step(C, det, model)
        assert np.all(K[~det] == 0.0)
        m_pred = m @ model.A.T
        m = m_pred + np.einsum("iab,ib->ia", K, ys - m_pred @ model.H.T)
        for i, f in enumerate(filters):
            f.step(ys[i:i + 1] if det[i] else [])
            np.testing.assert_allclose(C[i, i], f.cov, rtol=1e-11, atol=1e-14)
            np.testing.assert_allclose(m[i], f.mean, rtol=1e-11, atol=1e-13)
        np.testing.assert_array_equal(C, np.swapaxes(C, 0, 1).swapaxes(-1, -2))
        assert np.linalg.eigvalsh(C.transpose(0, 2, 1, 3).reshape(4 * N, 4 * N)).min() > -1e-12


def test_cross_covariance_rejects_bad_input():
    model = models.turn_model(0.0, 0.1, 0.05, 0.1)
    C = np.broadcast_to(np.eye(4), (2, 2, 4, 4))
    with pytest.raises(FusionInputError, match=r"C must have shape \(N, N, 4, 4\)"):
        kalman.cross_covariance_step(C[:, :1], np.array([True, False]), model)
    with pytest.raises(FusionInputError, match="detected must be a boolean array"):
        kalman.cross_covariance_step(C, np.array([1, 0]), model)
    with pytest.raises(FusionInputError, match="C contains non-finite"):
        kalman.cross_covariance_step(C * np.nan, np.array([True, False]), model)
    with pytest.raises(FusionInputError, match="model must be"):
        kalman.cross_covariance_step(C, np.array([True, False]), "model")


def test_a_step_that_overflows_is_refused_and_the_state_kept():
    """Regression: A = 1e200 I overflows the prediction; `run` returned inf and then NaN
    covariances, and `step` kept the inf state before the Estimates refused it."""
    I = np.eye(2)
    model = models.LinearGaussian(1e200 * I, I, I, I)
    with pytest.raises(FusionInputError, match=r"scans\[0\]: step 1's estimate cannot be "
                       r"represented in float64 \(not finite"):
        kalman.run([[]] * 3, model, np.zeros(2), I)
    kf = kalman.KalmanFilter(model, np.zeros(2), I)
    with pytest.raises(FusionInputError, match="scan: step 1's estimate"):
        kf.step([])
    assert kf.steps == 0
    np.testing.assert_array_equal(kf.cov, I)
    np.testing.assert_array_equal(kf.mean, np.zeros(2))


def test_a_step_whose_report_an_estimates_would_refuse_is_refused_and_the_state_kept():
    """Fuzz K2: a covariance diag(1e-300, 1e-300, 1e300, 1e300) passed the filter's own
    check (numpy's Cholesky), the filter stepped (state, step count and time) and only its
    Estimates refused it, naming neither tracker nor step; every later step failed alike."""
    I4 = np.eye(4)
    model = models.LinearGaussian(I4, np.zeros((4, 4)), np.eye(2, 4), 1e-300 * np.eye(2))
    kf = kalman.KalmanFilter(model, np.zeros(4), 1e300 * I4)
    with pytest.raises(FusionInputError, match=r"^scan: step 1's estimate cannot be represented "
                                               r"in float64 \(covs of estimate 0 is numerically "
                                               r"singular"):
        kf.step([[1.0, 2.0]], time=1.0)
    assert kf.steps == 0
    np.testing.assert_array_equal(kf.cov, 1e300 * I4)
    np.testing.assert_array_equal(kf.mean, np.zeros(4))
    kf.step([], time=0.5)  # the refused step's time was not kept either
    with pytest.raises(FusionInputError, match=r"scans\[0\]: step 1's estimate"):
        kalman.run([[[1.0, 2.0]]], model, np.zeros(4), 1e300 * I4)  # the same rule as step's


def test_cross_covariance_step_refuses_what_is_no_joint_covariance():
    """Regression: C = -1 raised LinAlgError, C = -2 returned 2, an asymmetric C was
    averaged silently and C = 1e308 returned inf."""
    model = models.LinearGaussian(np.eye(1), np.eye(1), np.eye(1), np.eye(1))
    for C, match in ((-np.ones((1, 1, 1, 1)), r"C\[0, 0\], filter 0's covariance"),
                     (np.array([[[[1.0]], [[5.0]]], [[[-3.0]], [[1.0]]]]), "symmetric"),
                     (1e308 * np.ones((1, 1, 1, 1)), "overflows float64")):
        with pytest.raises(FusionInputError, match=match):
            kalman.cross_covariance_step(C, np.zeros(C.shape[0], dtype=bool), model)


def _exact_update(P, H, R):
    """P - P H^T (H P H^T + R)^-1 H P in exact rational arithmetic (d = 2), floats in."""
    from fractions import Fraction as Fr

    def mat(X):
        return [[Fr(float(x)) for x in row] for row in np.atleast_2d(X)]

    def mul(X, Y):
        return [[sum(X[i][k] * Y[k][j] for k in range(len(Y))) for j in range(len(Y[0]))]
                for i in range(len(X))]

    P_, H_, R_ = mat(P), mat(H), mat(R)
    Ht = [list(c) for c in zip(*H_, strict=True)]
    PHt = mul(P_, Ht)
    S = [[a + b for a, b in zip(r1, r2, strict=True)] for r1, r2 in zip(mul(H_, PHt), R_,
                                                                         strict=True)]
    det = S[0][0] * S[1][1] - S[0][1] * S[1][0]
    Si = [[S[1][1] / det, -S[0][1] / det], [-S[1][0] / det, S[0][0] / det]]
    KSK = mul(mul(PHt, Si), [list(c) for c in zip(*PHt, strict=True)])
    return np.array([[float(p - k) for p, k in zip(r1, r2, strict=True)]
                     for r1, r2 in zip(P_, KSK, strict=True)])


@pytest.mark.parametrize("ratio", [1e8, 1e16, 1e20])
def test_update_keeps_a_vague_prior_positive_definite_and_exact(ratio):
    """A prior ratio times the measurement noise: P - K S K^T cancels to rounding (at 1e16
    it lost positive definiteness and a Table 1 run with prior_cov = 1e16 failed at its
    second step); Joseph's form keeps every entry of P+ at the exact update's, to 1e-9 of
    its diagonal's scale (the smallest eigenvalue, 1e-16 of the largest at ratio 1e16, is
    below the rounding of an eigenvalue solver; Cholesky still factors P+)."""
    model = models.turn_model(0.0, q=0.1, r=0.05, dt=0.025)
    rng = np.random.default_rng(3)
    G = rng.standard_normal((4, 4))
    P = ratio * 0.05 * (G @ G.T / 4 + np.eye(4))
    m, P_new = kalman.update(np.zeros(4), P, np.ones(2), model.H, model.R)
    exact = _exact_update(P, model.H, model.R)
    scale = np.sqrt(np.outer(np.diag(exact), np.diag(exact)))
    assert np.all(np.abs(P_new - exact) <= 1e-9 * scale)
    np.linalg.cholesky(P_new)  # positive definite in float64, as a fusion checks it
    assert np.all(np.isfinite(m))
