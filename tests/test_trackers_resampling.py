"""Systematic resampling and the effective sample size."""

import warnings

import numpy as np
import pytest

from fusion_opt import FusionInputError
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


def test_log_weights_across_the_float_range_raise_no_warning():
    """Fuzz E13: -1e308 - 1e308 overflowed with a RuntimeWarning (an error under -W error);
    that weight is 0 beside the other, exactly as exp gives it."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        logw = np.array([1e308, -1e308])
        assert resampling.effective_sample_size(logw) == 1.0
        np.testing.assert_array_equal(resampling.normalize_log_weights(logw), [0.0, -np.inf])
        assert resampling.logsumexp(logw) == 1e308


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


def test_normalisation_survives_a_huge_common_offset():
    """Regression: l - logsumexp(l) lost log N to rounding when every l_i was near -1e20
    (the weights then summed to N)."""
    for offset in (0.0, -1e20, 1e20, -1e300):
        logw = offset + np.log(np.array([1.0, 1.0, 2.0, 4.0]))
        w = np.exp(resampling.normalize_log_weights(logw))
        if offset == 0.0 or abs(offset) < 1e16:
            np.testing.assert_allclose(w, [0.125, 0.125, 0.25, 0.5], rtol=1e-12)
        else:  # the differences themselves are below the offset's rounding: equal weights
            np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-12)
        assert resampling.effective_sample_size(logw) <= 4.0 + 1e-12


def test_end_of_step_resamples_only_below_the_threshold():
    logw = np.log(np.array([0.7, 0.1, 0.1, 0.1])) - 5.0  # ESS = 1 / 0.52
    rng = np.random.default_rng(4)
    kept = resampling.end_of_step(logw, 1.9, rng)
    assert kept.ancestors is None and kept.ess == pytest.approx(1 / 0.52, rel=1e-12)
    np.testing.assert_allclose(kept.weights, [0.7, 0.1, 0.1, 0.1], rtol=1e-12)
    np.testing.assert_allclose(kept.logw, np.log(kept.weights), rtol=1e-12)
    state = rng.bit_generator.state
    done = resampling.end_of_step(logw, 2.0, np.random.default_rng(4))
    assert rng.bit_generator.state == state  # no draw when not resampling
    np.testing.assert_allclose(done.weights, kept.weights)
    np.testing.assert_array_equal(done.logw, np.full(4, -np.log(4)))
    # systematic resampling of (0.7, 0.1, 0.1, 0.1): particle 0 two or three times, and the
    # same ancestors as systematic_resample with the same generator state
    counts = np.bincount(done.ancestors, minlength=4)
    assert counts.sum() == 4 and counts[0] in (2, 3)
    ref = resampling.systematic_resample(logw, np.random.default_rng(4))
    np.testing.assert_array_equal(done.ancestors, ref)


@pytest.mark.parametrize("logw, match", [
    (np.array([-np.inf, -np.inf]), "not all weights 0"), (np.array([np.nan, 0.0]), "max nan"),
    (np.array([np.inf, 0.0]), "max inf"), (np.zeros(0), "non-empty"),
    (np.zeros((2, 2)), "non-empty"), ([True, False], "real numbers")])
def test_log_weights_that_are_no_distribution_are_refused(logw, match):
    """Regression: all-zero weights gave NaN weights and ESS, a NaN weight was silently
    never drawn, a list raised AttributeError."""
    for call in (resampling.normalize_log_weights, resampling.effective_sample_size,
                 lambda lw: resampling.systematic_resample(lw, np.random.default_rng(0)),
                 lambda lw: resampling.end_of_step(lw, 1.0, np.random.default_rng(0))):
        with pytest.raises(FusionInputError, match=match):
            call(logw)
    np.testing.assert_allclose(resampling.normalize_log_weights([-np.inf, 0.0]), [-np.inf, 0])


def test_resampling_refuses_a_bad_generator_and_threshold():
    with pytest.raises(FusionInputError, match="rng must be a numpy.random.Generator"):
        resampling.systematic_resample(np.zeros(2), 0)
    with pytest.raises(FusionInputError, match="rng must be a numpy.random.Generator"):
        resampling.end_of_step(np.array([0.0, -30.0]), 2.0, 0)
    with pytest.raises(FusionInputError, match="threshold must be a particle count"):
        resampling.end_of_step(np.zeros(3), np.nan, np.random.default_rng(0))


def test_logsumexp_agrees_with_scipy_at_the_edges():
    """Fuzz N12: no entries raised numpy's bare "zero-size array" ValueError; now as scipy:
    -inf for an empty sum, inf and NaN where an entry is, and random arrays to rounding."""
    from scipy.special import logsumexp as reference

    from trackers.resampling import logsumexp

    rng = np.random.default_rng(3)
    cases = [([], None), (np.zeros((0, 3)), 0), (np.zeros((0, 3)), 1), (np.zeros((2, 0)), 1),
             ([np.nan, 0.0], None), ([np.inf, 1.0], None), ([-np.inf, -np.inf], None),
             (rng.normal(0, 300, (4, 5)), 0), (rng.normal(0, 300, (4, 5)), None)]
    for a, axis in cases:
        np.testing.assert_allclose(logsumexp(a, axis), reference(a, axis=axis), rtol=1e-15)


def test_weights_past_the_memory_limit_are_refused_before_any_temporary():
    """Fuzz3 F4: a broadcast view of 10^9 log-weights costs 8 bytes to hold, and the
    normalisation and resampling then allocated several (N,) arrays of 8 GB: MemoryError,
    or the OOM killer with no message. Refused naming logw (a) before allocating."""
    big = np.broadcast_to(np.zeros(1), (10**9,))
    rng = np.random.default_rng(0)
    for call in (resampling.normalize_log_weights, resampling.effective_sample_size,
                 lambda w: resampling.systematic_resample(w, rng),
                 lambda w: resampling.end_of_step(w, 0.5, rng)):
        with pytest.raises(FusionInputError, match=r"logw of 1000000000 weights: .* GiB.*"
                                                   r"array_memory"):
            call(big)
    with pytest.raises(FusionInputError, match=r"a of shape \(1000000000,\): .*array_memory"):
        resampling.logsumexp(big)
    # a broadcast view within the limit is taken, and gives the uniform answer
    w = np.broadcast_to(np.zeros(1), (1000,))
    assert resampling.effective_sample_size(w) == pytest.approx(1000, rel=1e-12)
