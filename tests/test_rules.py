"""Fusion rules against closed forms, hand-computed cases and consistency properties."""

import numpy as np
import pytest

import fusion_opt as fo
from studies.backends import instance

M2 = np.array([[1.0, 2.0], [3.0, 5.0]])


def _joint(rng, covs, rho=0.6):
    """Joint covariance with blocks R_i C_ij R_j^T (R_i R_i^T = P_i), C PSD with identity
    diagonal blocks: a random PSD matrix whitened block by block, mixed with I (DESIGN §1)."""
    N, n = covs.shape[:2]
    R = np.linalg.cholesky(covs)
    A = rng.standard_normal((N * n, N * n + 2))
    C = (A @ A.T).reshape(N, n, N, n).transpose(0, 2, 1, 3)
    D = np.linalg.inv(np.linalg.cholesky(C[np.arange(N), np.arange(N)]))
    C = np.einsum("iab,ijbc,jdc->ijad", D, C, D)
    C = rho * C + (1 - rho) * np.eye(N)[:, :, None, None] * np.eye(n)
    return np.einsum("iab,ijbc,jdc->ijad", R, C, R)


def _true_error(gains, S):
    N, n = gains.shape[:2]
    K = gains.transpose(1, 0, 2).reshape(n, N * n)
    return K @ S.transpose(0, 2, 1, 3).reshape(N * n, N * n) @ K.T


def _gains(r, covs):
    """CI-type gains K_i = P w_i Y_i from a result."""
    return r.cov @ (r.weights[:, None, None] * np.linalg.inv(covs))


def test_naive_is_information_sum():
    rng = np.random.default_rng(0)
    covs, means = instance(rng, 3, 2, "random"), rng.standard_normal((3, 2))
    r = fo.fuse(means, covs, method="naive")
    Y = np.linalg.inv(covs)
    P = np.linalg.inv(Y.sum(0))
    assert np.allclose(r.cov, P) and np.allclose(r.mean, P @ np.einsum("ijk,ik->j", Y, means))


def test_known_cross_is_dense_blue_and_smallest():
    rng = np.random.default_rng(1)
    covs, means = instance(rng, 3, 2, "random"), rng.standard_normal((3, 2))
    S = _joint(rng, covs)
    r = fo.fuse(means, covs, method="known-cross", cross=S)
    Sd = S.transpose(0, 2, 1, 3).reshape(6, 6)
    H = np.tile(np.eye(2), (3, 1))
    P = np.linalg.inv(H.T @ np.linalg.solve(Sd, H))
    assert np.allclose(r.cov, P)
    assert np.allclose(r.mean, P @ H.T @ np.linalg.solve(Sd, means.ravel()))
    for method in ("naive", "fast-ci", "ifci", "bci"):
        q = fo.fuse(means, covs, method=method, backend="newton")
        gains = q.cov @ np.linalg.inv(covs) if method == "naive" else _gains(q, covs)
        err = _true_error(gains, S)
        assert np.linalg.eigvalsh(err - r.cov).min() >= -1e-10, method


def test_fast_ci_and_ifci_hand_computed():
    P = np.array([np.diag([1.0, 2.0]), np.diag([3.0, 1.0])])
    r = fo.fuse(M2, P, method="fast-ci")  # tr = 3, 4: w = (1/3, 1/4) / (7/12)
    assert np.allclose(r.weights, [4 / 7, 3 / 7]) and np.allclose(r.cov, 1.4 * np.eye(2))
    # det Ya = 1/2, det Yb = 1/3, det(Ya + Yb) = 4/3 * 3/2 = 2: w_a = (2 - 1/3 + 1/2) / 4
    q = fo.fuse(M2, P, method="ifci")
    assert np.allclose(q.weights, [13 / 24, 11 / 24])


def test_ici_and_ei_hand_computed():
    P = np.array([np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    # ICI: by symmetry w = 1/2, G = 2.5 I, P^-1 = diag(1 + 1/4 - 0.4, ...) = 0.85 I
    r = fo.fuse(M2, P, method="ici")
    assert np.allclose(r.weights, [0.5, 0.5], atol=1e-6)
    assert np.allclose(r.cov, np.eye(2) / 0.85)
    assert np.allclose(r.mean, (np.diag([1.0, 0.25]) - 0.2 * np.eye(2)) @ M2[0] / 0.85
                       + (np.diag([0.25, 1.0]) - 0.2 * np.eye(2)) @ M2[1] / 0.85)
    # EI keeps, per axis, the more informative estimate
    e = fo.fuse(M2, P, method="ei")
    assert np.allclose(e.cov, np.eye(2)) and np.allclose(e.mean, [1.0, 5.0])


@pytest.mark.parametrize("method", ["fast-ci", "ifci"])
def test_ci_rules_consistent_under_any_correlation(method):
    rng = np.random.default_rng(4)
    for _ in range(5):
        covs = instance(rng, 3, 3, "random")
        S = _joint(rng, covs, rho=rng.uniform(0.5, 1.0))
        r = fo.fuse(np.zeros((3, 3)), covs, method=method)
        assert np.linalg.eigvalsh(r.cov - _true_error(_gains(r, covs), S)).min() >= -1e-10


def test_ici_consistent_under_common_information():
    rng = np.random.default_rng(5)
    for _ in range(5):
        Ia, Ib, Ic = np.linalg.inv(instance(rng, 3, 2, "random"))
        Pa, Pb = np.linalg.inv(Ia + Ic), np.linalg.inv(Ib + Ic)
        # e_a = Pa (Ia ea + Ic ec), e_b = Pb (Ib eb + Ic ec), cov(e_x) = I_x^-1
        S = np.array([[Pa, Pa @ Ic @ Pb], [Pb @ Ic @ Pa, Pb]])
        r = fo.fuse(np.zeros((2, 2)), np.array([Pa, Pb]), method="ici")
        Ginv = np.linalg.inv(r.weights[0] * Pa + r.weights[1] * Pb)
        gains = np.stack([r.cov @ (Ia + Ic - r.weights[0] * Ginv),
                          r.cov @ (Ib + Ic - r.weights[1] * Ginv)])
        assert np.linalg.eigvalsh(r.cov - _true_error(gains, S)).min() >= -1e-10


def test_naive_overconfident_under_correlation():
    P = np.array([np.eye(2), np.eye(2)])
    S = np.array([[np.eye(2), np.eye(2)], [np.eye(2), np.eye(2)]])  # identical errors
    r = fo.fuse(np.zeros((2, 2)), P, method="naive")
    assert np.linalg.eigvalsh(r.cov - _true_error(r.cov @ np.linalg.inv(P), S)).max() < 0


def test_rule_inputs_checked():
    P = np.stack([np.eye(2)] * 3)
    with pytest.raises(fo.FusionInputError, match="'ei' fuses 2"):
        fo.fuse(np.zeros((3, 2)), P, method="ei")
    with pytest.raises(fo.FusionInputError, match="cross"):
        fo.fuse(np.zeros((3, 2)), P, method="known-cross")
