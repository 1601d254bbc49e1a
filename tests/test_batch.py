"""fuse_batch equals fuse problem by problem, whatever the scales of the nodes and the
other problems of the batch (one path: a single problem is a batch of one)."""

import numpy as np
import pytest
from conftest import instance

import fusion_opt as fo


def _batch(seed, B, N, n, kind="random"):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((B, N, n)), instance(rng, B * N, n, kind).reshape(B, N, n, n)


def _same(r, q, b):
    np.testing.assert_array_equal(r.weights[b], q.weights)
    np.testing.assert_array_equal(r.mean[b], q.mean)
    np.testing.assert_array_equal(r.cov[b], q.cov)
    assert r.objective[b] == q.objective and r.gap[b] == q.gap and r.status[b] == q.status


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("N,backend", [(1, "newton"), (2, "closed-form"), (2, "newton"),
                                       (4, "newton"), (3, "clarabel")])
def test_batch_equals_per_problem_bit_for_bit(N, backend, criterion):
    means, covs = _batch(N, 6, N, 3, "ill-conditioned")
    r = fo.fuse_batch(means, covs, "bci", criterion, backend)
    assert r.weights.shape == (6, N) and r.cov.shape == (6, 3, 3)
    assert r.iterations.dtype.kind == "i"
    for b in range(6):
        _same(r, fo.bci(means[b], covs[b], criterion, backend), b)


def test_pairs_of_very_different_scales_are_exact():
    """Issue 9, defect 1: a node 1e16 above the other must leave the better node as it is
    (the batch gave [2.2e-8, 2.2e-8] for [1e-8, 1e-11])."""
    covs = np.array([[1e8 * np.eye(2), np.diag([1e-8, 1e-11])]])
    r = fo.fuse_batch(np.zeros((1, 2, 2)), covs)
    np.testing.assert_array_equal(r.cov[0], np.diag([1e-8, 1e-11]))
    np.testing.assert_array_equal(r.weights[0], [0.0, 1.0])


def test_node_scales_spread_to_1e16_equal_the_per_problem_result():
    rng = np.random.default_rng(3)
    B, n = 200, 3
    covs = instance(rng, 2 * B, n, "random").reshape(B, 2, n, n)
    covs *= 10.0 ** rng.uniform(-8, 8, (B, 2, 1, 1))
    means = rng.standard_normal((B, 2, n))
    r = fo.fuse_batch(means, covs)
    for b in range(0, B, 7):
        _same(r, fo.bci(means[b], covs[b]), b)
        ref = fo.bci(means[b], covs[b], backend="clarabel")
        assert abs(r.objective[b] - ref.objective) <= 1e-9 * abs(ref.objective)


def test_a_single_node_returns_its_input_unchanged():
    means, covs = _batch(2, 5, 1, 4, "ill-conditioned")
    r = fo.fuse_batch(means, covs)
    np.testing.assert_array_equal(r.cov, covs[:, 0])
    np.testing.assert_array_equal(r.mean, means[:, 0])


def test_batch_mbci_per_problem_detection():
    means, covs = _batch(5, 4, 3, 2)
    p = np.array([[0.9, 0.7, 0.8]] * 2 + [[0.5, 1.0, 0.6]] * 2)
    r = fo.fuse_batch(means, covs, "mbci", p_detect=p, growth=1.1)
    for b in range(4):
        _same(r, fo.mbci(means[b], covs[b], p[b], growth=1.1), b)


def test_batch_bad_input_names_argument():
    means, covs = _batch(1, 2, 2, 2)
    with pytest.raises(fo.FusionInputError, match="problem 1"):
        fo.fuse_batch(means, covs, "mbci", p_detect=[[0.5, 0.5], [0.5, 2.0]], chi=1.0)
    with pytest.raises(fo.FusionInputError, match="'ci' fuses 2"):
        fo.fuse_batch(np.zeros((1, 3, 2)), np.broadcast_to(np.eye(2), (1, 3, 2, 2)), "ci")
    bad = covs.copy()
    bad[1, 0, 0, 1] += 1.0
    with pytest.raises(fo.FusionInputError, match="covs of problem 1, node 0 is not symm"):
        fo.fuse_batch(means, bad)


@pytest.mark.parametrize("method", ["naive", "fast-ci", "ifci", "ici", "ei"])
def test_batch_rules_equal_per_problem(method):
    means, covs = _batch(9, 5, 2, 2)
    r = fo.fuse_batch(means, covs, method, "logdet")
    assert r.backend is None and r.weights_are in ("ci_weights", "gain_shares")
    for b in range(5):
        _same(r, fo.fuse(means[b], covs[b], method=method, criterion="logdet"), b)


def test_repr_is_a_summary():
    means, covs = _batch(4, 1000, 3, 2)
    text = repr(fo.fuse_batch(means, covs))
    assert "B=1000" in text and "optimal: 1000" in text and len(text) < 400


@pytest.mark.parametrize("method", ["naive", "fast-ci", "ifci"])
@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_batched_rules_of_many_nodes_equal_per_problem(method, criterion):
    """naive and fast-ci fuse a batch in one vectorised call (rules.BATCHED): each problem
    must come out as it does alone, bit for bit."""
    means, covs = _batch(11, 7, 5, 3)
    r = fo.fuse_batch(means, covs, method, criterion)
    for b in range(7):
        _same(r, fo.fuse(means[b], covs[b], method=method, criterion=criterion), b)
