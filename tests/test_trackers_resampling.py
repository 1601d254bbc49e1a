"""Systematic resampling and the effective sample size."""

import numpy as np
import pytest

from trackers import resampling


def test_systematic_resampling_counts_are_floor_or_ceil():
    rng = np.random.default_rng(2)
    for _ in range(50):
        N = int(rng.integers(1, 40))
        w = rng.dirichlet(np.full(N, 0.3))
        idx = resampling.systematic_resample(np.log(w) + 3.0, rng)  # unnormalised logs
        counts = np.bincount(idx, minlength=N)
        assert counts.sum() == N
        assert np.all(counts >= np.floor(N * w) - 1e-9) and np.all(counts <= np.ceil(N * w))


def test_zero_weights_never_chosen_and_ess():
    logw = np.array([0.0, -np.inf, 0.0, -np.inf])
    idx = resampling.systematic_resample(logw, np.random.default_rng(0))
    assert set(idx) <= {0, 2}
    assert resampling.effective_sample_size(logw) == pytest.approx(2.0)
    assert resampling.effective_sample_size(np.zeros(7)) == pytest.approx(7.0)
    np.testing.assert_allclose(np.exp(resampling.normalize_log_weights(np.log([1.0, 3.0]))),
                               [0.25, 0.75])


def test_logsumexp_matches_scipy():
    from scipy.special import logsumexp as ref

    rng = np.random.default_rng(1)
    a = rng.normal(scale=300, size=(6, 5))
    a[0, 1] = -np.inf
    a[2] = -np.inf
    np.testing.assert_allclose(resampling.logsumexp(a, axis=1), ref(a, axis=1), rtol=1e-13)
    np.testing.assert_allclose(resampling.logsumexp(a, axis=0), ref(a, axis=0), rtol=1e-13)
    assert resampling.logsumexp(a) == pytest.approx(ref(a), rel=1e-13)
    assert resampling.logsumexp(np.full(3, -np.inf)) == -np.inf
