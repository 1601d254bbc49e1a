"""fuse_batch equals fuse problem by problem."""

import numpy as np
import pytest

import fusion_opt as fo
from studies.backends import instance


def _batch(seed, B, N, n):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((B, N, n)), instance(rng, B * N, n, "random").reshape(B, N, n, n)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("N,backend", [(2, "closed-form"), (2, "newton"), (4, "newton"),
                                       (3, "clarabel")])
def test_batch_equals_per_problem(N, backend, criterion):
    means, covs = _batch(N, 6, N, 3)
    r = fo.fuse_batch(means, covs, "bci", criterion, backend)
    assert r.weights.shape == (6, N) and r.cov.shape == (6, 3, 3)
    for b in range(6):
        q = fo.bci(means[b], covs[b], criterion, "clarabel")
        scale = abs(q.objective) if criterion == "trace" else 1.0
        assert abs(r.objective[b] - q.objective) <= 1e-9 * scale
        assert np.allclose(r.mean[b], q.mean, rtol=1e-6, atol=1e-8)
        assert np.allclose(r.cov[b], q.cov, rtol=1e-7, atol=1e-10)
        assert r.gap[b] <= 1e-9 * scale
    assert (r.status == "optimal").all()


def test_batch_mbci_per_problem_detection():
    means, covs = _batch(5, 4, 3, 2)
    p = np.array([[0.9, 0.7, 0.8]] * 2 + [[0.5, 1.0, 0.6]] * 2)
    r = fo.fuse_batch(means, covs, "mbci", backend="newton", p_detect=p, chi=0.9)
    for b in range(4):
        q = fo.mbci(means[b], covs[b], p[b], 0.9)
        assert np.allclose(r.cov[b], q.cov, rtol=1e-7)


def test_batch_bad_input_names_argument():
    means, covs = _batch(1, 2, 2, 2)
    with pytest.raises(fo.FusionInputError, match="problem 1"):
        fo.fuse_batch(means, covs, "mbci", p_detect=[[0.5, 0.5], [0.5, 2.0]], chi=1.0)
    with pytest.raises(fo.FusionInputError, match="'ci' fuses 2"):
        fo.fuse_batch(np.zeros((1, 3, 2)), np.broadcast_to(np.eye(2), (1, 3, 2, 2)), "ci")


@pytest.mark.parametrize("method", ["naive", "ifci"])
def test_batch_rules_equal_per_problem(method):
    means, covs = _batch(9, 5, 3, 2)
    r = fo.fuse_batch(means, covs, method, "logdet")
    for b in range(5):
        q = fo.fuse(means[b], covs[b], method=method, criterion="logdet")
        assert np.allclose(r.mean[b], q.mean) and np.allclose(r.cov[b], q.cov)
        assert np.isclose(r.objective[b], q.objective) and np.allclose(r.weights[b], q.weights)
