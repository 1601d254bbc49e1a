"""Metrics on hand-computed cases and against brute force."""

import itertools
import math
from fractions import Fraction

import numpy as np
import pytest

from fusion_opt import FusionInputError
from trackers import metrics


def brute_force_assignment(X, Y, c, p):
    """min over injective maps of the smaller set into the larger, by enumeration."""
    if len(X) > len(Y):
        X, Y = Y, X
    if len(X) == 0:
        return 0.0
    best = np.inf
    for perm in itertools.permutations(range(len(Y)), len(X)):
        cost = sum(min(c, np.linalg.norm(X[i] - Y[j])) ** p for i, j in enumerate(perm))
        best = min(best, cost)
    return best


E = np.zeros((0, 2))


@pytest.mark.parametrize(
    ("X", "Y", "c", "p", "ospa", "gospa"),
    [
        # 1-D: pair 0-1 (cost 1), one extra point costs c
        ([[0.0]], [[1.0], [3.0]], 5.0, 1, (1 + 5) / 2, 1 + 5 / 2),
        # greedy nearest pairing (2-1.9, 0-10) is not optimal; optimal is 0-1.9, 2-10
        ([[0.0], [2.0]], [[1.9], [10.0]], 20.0, 1, (1.9 + 8) / 2, 1.9 + 8),
        ([[0.0], [2.0]], [[1.9], [10.0]], 20.0, 2, np.sqrt((1.9**2 + 64) / 2),
         np.sqrt(1.9**2 + 64)),
        # cut-off: distance 10 counts as c = 2
        ([[0.0]], [[10.0]], 2.0, 2, 2.0, 2.0),
        # 2-D: two vertical pairs at distance 1
        ([[0.0, 0.0], [1.0, 0.0]], [[0.0, 1.0], [1.0, 1.0]], 10.0, 2, 1.0, np.sqrt(2.0)),
        # 2-D, 3-4-5 triangle and an extra point beyond the cut-off
        ([[0.0, 0.0]], [[3.0, 4.0], [100.0, 0.0]], 6.0, 1, (5 + 6) / 2, 5 + 3),
        # empty sets
        (E, E, 3.0, 2, 0.0, 0.0),
        (E, [[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]], 2.0, 2, 2.0, np.sqrt(4 / 2 * 3)),
    ],
)
def test_ospa_gospa_hand_computed(X, Y, c, p, ospa, gospa):
    X, Y = np.asarray(X, float), np.asarray(Y, float)
    assert metrics.ospa(X, Y, c, p) == pytest.approx(ospa, rel=1e-12)
    assert metrics.gospa(X, Y, c, p) == pytest.approx(gospa, rel=1e-12)
    assert metrics.ospa(Y, X, c, p) == pytest.approx(ospa, rel=1e-12)
    assert metrics.gospa(Y, X, c, p) == pytest.approx(gospa, rel=1e-12)


def test_ospa_gospa_brute_force_symmetry_identity():
    rng = np.random.default_rng(11)
    for _ in range(30):
        m, k = rng.integers(0, 5, size=2)
        X, Y = rng.normal(size=(m, 2)) * 2, rng.normal(size=(k, 2)) * 2
        c, p = rng.uniform(0.5, 3), rng.choice([1, 2, 3])
        cost = brute_force_assignment(X, Y, c, p)
        big = max(m, k)
        ref_ospa = 0.0 if big == 0 else ((cost + c**p * abs(m - k)) / big) ** (1 / p)
        ref_gospa = (cost + c**p / 2 * abs(m - k)) ** (1 / p)
        assert metrics.ospa(X, Y, c, p) == pytest.approx(ref_ospa, rel=1e-10, abs=1e-12)
        assert metrics.gospa(X, Y, c, p) == pytest.approx(ref_gospa, rel=1e-10, abs=1e-12)
        assert metrics.ospa(X, Y, c, p) == pytest.approx(metrics.ospa(Y, X, c, p))
        assert metrics.gospa(X, Y, c, p) == pytest.approx(metrics.gospa(Y, X, c, p))
        assert metrics.ospa(X, X[::-1], c, p) == pytest.approx(0.0, abs=1e-12)
        assert metrics.gospa(X, X, c, p) == pytest.approx(0.0, abs=1e-12)
        assert metrics.ospa(X, Y, c, p) <= c + 1e-12


def test_ospa_rejects_bad_input():
    with pytest.raises(ValueError, match="c must be a finite positive"):
        metrics.ospa(E, E, 0.0, 2)
    with pytest.raises(ValueError, match="p must be >= 1"):
        metrics.gospa(E, E, 1.0, 0.5)
    with pytest.raises(ValueError, match="X must be a"):
        metrics.ospa(np.zeros(3), E, 1.0, 2)
    with pytest.raises(ValueError, match="differ in dimension"):
        metrics.ospa(np.zeros((1, 2)), np.zeros((1, 3)), 1.0, 2)
    with pytest.raises(ValueError, match="alpha must be in"):
        metrics.gospa(E, E, 1.0, 2, alpha=3.0)


def test_mse_rmse_mncm_hand_computed():
    est = np.array([[1.0, 0.0, 2.0, 0.0], [0.0, 2.0, 0.0, 0.0]])
    truth = np.zeros((2, 4))
    assert metrics.mse(est, truth) == pytest.approx((5 + 4) / 2)
    assert metrics.mse(est, truth, components=(0, 1)) == pytest.approx((1 + 4) / 2)
    assert metrics.rmse(est, truth) == pytest.approx(np.sqrt(4.5))
    covs = np.array([np.diag([3.0, 1.0, 7.0, 0.5]), np.eye(4)])
    covs[1, :2, :2] = [[2.0, 1.0], [1.0, 2.0]]  # eigenvalues 1 and 3
    assert metrics.mncm(covs) == pytest.approx((7 + 3) / 2)
    assert metrics.mncm(covs, components=(0, 1)) == pytest.approx((3 + 3) / 2)
    np.testing.assert_allclose(metrics.spectral_norms(covs, components=(0, 1)), [3, 3])
    with pytest.raises(ValueError, match="same shape"):
        metrics.mse(est, truth[:1])
    with pytest.raises(ValueError, match="components must be"):
        metrics.mse(est, truth, components=(0, 9))


def test_nees_and_bounds():
    est = np.array([[1.0, 2.0], [0.0, 0.0]])
    covs = np.array([np.diag([1.0, 4.0]), np.eye(2)])
    np.testing.assert_allclose(metrics.nees(est, np.zeros((2, 2)), covs), [2.0, 0.0])
    assert metrics.anees(est, np.zeros((2, 2)), covs) == pytest.approx(1.0)
    # chi-square table values: chi2(4) 2.5% / 97.5% quantiles, and chi2(80) / 20
    lo, hi = metrics.nees_bounds(4)
    assert (lo, hi) == pytest.approx((0.4844, 11.1433), abs=1e-4)
    lo, hi = metrics.anees_bounds(4, 20)
    assert (lo, hi) == pytest.approx((57.1532 / 20, 106.6286 / 20), abs=1e-4)
    with pytest.raises(ValueError, match="count must be an integer"):
        metrics.anees_bounds(4, 0)
    with pytest.raises(ValueError, match="level must be a probability"):
        metrics.anees_bounds(4, 2, level=1.5)
    for level in (0.0, 1.0):  # fuzz E6: (0, inf) at 1, an interval of width 0 at 0
        with pytest.raises(ValueError, match="level must lie strictly between 0 and 1"):
            metrics.nees_bounds(2, level)


def test_cardinality_error():
    np.testing.assert_array_equal(metrics.cardinality_error([1, 3, 2], [1, 2, 4]), [0, 1, -2])
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        metrics.cardinality_error([1, 2], [1])


def test_metrics_refuse_complex_booleans_and_fractional_components():
    """Regression: complex points were truncated to their real part and components=(0.5,)
    to index 0."""
    est, truth = np.zeros((3, 4)), np.ones((3, 4))
    with pytest.raises(ValueError, match="components must be integer indices"):
        metrics.mse(est, truth, components=(0.5, 1))
    with pytest.raises(ValueError, match="components must be integer indices"):
        metrics.mncm(np.broadcast_to(np.eye(4), (3, 4, 4)), components=(True, False))
    with pytest.raises(ValueError, match="X must be an array of real numbers"):
        metrics.ospa(np.array([[1 + 1j, 0.0]]), E, 1.0, 2)
    with pytest.raises(ValueError, match="estimates must be an array of real numbers"):
        metrics.mse([[True, 0.0]], [[0.0, 0.0]])


def test_metrics_refuse_a_state_of_no_component_and_repeated_components():
    """Fuzz3 F2, F3: a state of dimension 0 ended in numpy's "zero-size array to reduction
    operation maximum" from rmse and the four covariance metrics (mse gave 0.0). F5:
    components=(0, 0) counted one error twice (mse 10.0 where (0,) gives 5.0) and nees then
    blamed covs."""
    empty, covs = np.zeros((2, 0)), np.zeros((2, 0, 0))
    for call in (metrics.mse, metrics.rmse):
        with pytest.raises(FusionInputError, match=r"estimates must be \(T, n\) with n >= 1"):
            call(empty, empty)
    for call in (metrics.nees, metrics.anees):
        with pytest.raises(FusionInputError, match=r"estimates must be \(T, n\) with n >= 1"):
            call(empty, empty, covs)
    for call in (metrics.spectral_norms, metrics.mncm):
        with pytest.raises(FusionInputError, match=r"covs must be \(T, n, n\) with n >= 1"):
            call(covs)
    est, truth, eye = np.array([[1.0, 2.0], [3.0, 4.0]]), np.zeros((2, 2)), np.eye(2)[None]
    assert metrics.mse(est, truth, components=(0,)) == (1 + 9) / 2
    assert metrics.mse(est, truth, components=np.array([1, 0])) == (1 + 4 + 9 + 16) / 2
    for call in (lambda c: metrics.mse(est, truth, c), lambda c: metrics.rmse(est, truth, c),
                 lambda c: metrics.nees(est, truth, np.repeat(eye, 2, axis=0), c),
                 lambda c: metrics.mncm(np.repeat(eye, 2, axis=0), c)):
        with pytest.raises(FusionInputError, match=r"components must be distinct indices, "
                                                   r"got \(0, 0\)"):
            call((0, 0))


def test_set_errors_against_brute_force_and_each_metric_alone():
    """set_errors' OSPA and GOSPA (one shared assignment) against enumeration; its pairs
    (match's order-1 assignment) cost, with c for each of the smaller set's points left
    unmatched, the enumerated order-1 optimum; and all of it is what ospa, gospa and match
    give alone, to the bit."""
    rng = np.random.default_rng(12)
    for _ in range(40):
        m, k = rng.integers(0, 5, size=2)
        X, Y = rng.normal(size=(m, 2)) * 2, rng.normal(size=(k, 2)) * 2
        c, p, alpha = rng.uniform(0.5, 3), rng.choice([1, 2, 3]), rng.uniform(0.5, 2)
        e = metrics.set_errors(X, Y, c, p, alpha)
        cost, big = brute_force_assignment(X, Y, c, p), max(m, k)
        ref_ospa = 0.0 if big == 0 else ((cost + c**p * abs(m - k)) / big) ** (1 / p)
        assert e.ospa == pytest.approx(ref_ospa, rel=1e-10, abs=1e-12)
        assert e.gospa == pytest.approx((cost + c**p / alpha * abs(m - k)) ** (1 / p),
                                        rel=1e-10, abs=1e-12)
        d = np.linalg.norm(X[e.rows] - Y[e.cols], axis=-1)
        assert np.all(d < c) and len(set(e.rows)) == len(e.rows) == len(set(e.cols))
        matched_cost = d.sum() + c * (min(m, k) - len(d))
        assert matched_cost == pytest.approx(brute_force_assignment(X, Y, c, 1), rel=1e-12)
        rows, cols = metrics.match(X, Y, c)
        assert (e.ospa, e.gospa) == (metrics.ospa(X, Y, c, p), metrics.gospa(X, Y, c, p, alpha))
        assert e.rows.tolist() == rows.tolist() and e.cols.tolist() == cols.tolist()
    with pytest.raises(FusionInputError, match="alpha must be in"):
        metrics.set_errors(E, E, 1.0, 2, alpha=3.0)
    # fuzz T1: (k - m) / alpha past float64 with a tiny c: the root from logs overflowed
    # before c multiplied it, and a finite GOSPA was refused (exact: c (k - m) / alpha, p = 1)
    for c, alpha in ((5e-324, 1e-320), (1e-300, 5e-324)):
        exact = float(Fraction(c) / Fraction(alpha))
        assert metrics.gospa(np.zeros((1, 1)), np.zeros((0, 1)), c, 1.0, alpha) == \
            pytest.approx(exact, rel=1e-12)
    # fuzz T3: an integer c past float64 is refused by name, not with an OverflowError
    for c in (2**2000, 10**5000):
        with pytest.raises(FusionInputError, match="c must be a finite positive number, got"):
            metrics.ospa(E, E, c, 2)
    from trackers import _checks  # such an int is +-inf in the trackers' scalar checks
    assert _checks.real("x", -(2**2000)) == -np.inf and _checks.real("x", 2**2000) == np.inf
    with pytest.raises(FusionInputError, match="p must be >= 1"):
        metrics.set_errors(E, E, 1.0, 0.5)


def test_matching_is_the_optimal_assignment_not_greedy():
    """Targets at x = 0 and 0.45, estimates at 0.2 and -0.3, c = 0.5: greedy nearest pairs
    0.2 with 0 and leaves -0.3 (0.75 from 0.45) unmatched; the optimal assignment pairs
    0.2 with 0.45 and -0.3 with 0 (capped cost 0.25 + 0.3 against 0.2 + 0.5)."""
    means = np.array([[0.2, 0.0], [-0.3, 0.0]])
    truth = np.array([[0.0, 0.0], [0.45, 0.0]])
    rows, cols = metrics.match(means, truth, 0.5)
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(0, 1), (1, 0)]


def test_id_switches_count_changes_of_the_matched_id():
    """Target 0 keeps id 7 through a gap, target 1 goes 3 -> 4 -> 3, target 2 never matched."""
    np.testing.assert_array_equal(metrics.id_switches([[7, 7, 7], [3, 4, 3], []]), [0, 2, 0])
    # ids are compared as integers: as floats, 2^53 and 2^53 + 1 would be one id
    np.testing.assert_array_equal(metrics.id_switches([[2**53, 2**53 + 1], [2.0, 2.0]]),
                                  [1, 0])
    for bad, match in ((5, "ids must be a sequence"), ([[1, "a"]], r"ids\[0\]"),
                       ([[[1, 2]]], r"ids\[0\] must be a 1-D sequence of integer"),
                       ([[1, 1.5]], r"ids\[0\] must be a 1-D sequence of integer")):
        with pytest.raises(FusionInputError, match=match):
            metrics.id_switches(bad)


def test_metrics_at_the_ends_of_float64_by_hand():
    """Regression: these overflowed or underflowed to inf, 0 or a raw scipy error. Hand
    values: errors of 1e200 in 4 components, RMSE 2e200; covariances 1e308 I, MNCM 1e308;
    OSPA of {0} against {(1, 1), (1, 1)} is sqrt((2 + c^2) / 2) for c > sqrt 2, c if every
    distance is cut off."""
    big, tiny = np.full((3, 4), 1e200), np.full((3, 4), 1e-200)
    assert metrics.rmse(big, np.zeros((3, 4))) == pytest.approx(2e200, rel=1e-15)
    assert metrics.rmse(tiny, np.zeros((3, 4))) == pytest.approx(2e-200, rel=1e-15)
    assert metrics.mncm(np.stack([1e308 * np.eye(2)] * 3)) == 1e308
    X, Y = np.zeros((1, 2)), np.ones((2, 2))
    assert metrics.ospa(X, Y, 1e200, 2) == pytest.approx(1e200 / np.sqrt(2), rel=1e-15)
    assert metrics.ospa(X, Y, 3.0, 2) == pytest.approx(np.sqrt(11 / 2), rel=1e-15)
    assert metrics.ospa(X, Y, 1e-200, 2) == pytest.approx(1e-200, rel=1e-15)
    assert metrics.ospa(X, Y, 10.0, 1e300) == pytest.approx(10.0, rel=1e-15)
    assert metrics.gospa(X, Y, 1e200, 2) == pytest.approx(1e200 / np.sqrt(2), rel=1e-15)
    far = np.array([[1.7e308, 1.7e308]]), np.array([[-1.7e308, 0.0]])
    assert metrics.ospa(*far, 5.0, 1) == 5.0 and metrics.match(*far, 5.0)[0].size == 0
    lo, hi = metrics.anees_bounds(10**12, 10**12)
    assert 1e12 - 3 < lo < 1e12 < hi < 1e12 + 3


@pytest.mark.parametrize("call, match", [
    (lambda: metrics.mse(np.zeros((0, 4)), np.zeros((0, 4))), "at least one step"),
    (lambda: metrics.mncm(np.zeros((0, 4, 4))), "mean over no step"),
    (lambda: metrics.anees(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2, 2))),
     "mean over no step"),
    (lambda: metrics.mncm(-np.eye(2)[None]), r"covs\[0\] is not positive semidefinite"),
    (lambda: metrics.nees(np.ones((3, 4)), np.zeros((3, 4)), np.zeros((3, 4, 4))),
     r"covs\[0\] is not positive definite"),
    (lambda: metrics.nees(np.ones((1, 2)), np.zeros((1, 2)), 1e-320 * np.eye(2)[None]),
     "NEES of step 0 overflows"),
    (lambda: metrics.mse(np.full((3, 4), 1e200), np.zeros((3, 4))), "MSE overflows"),
    (lambda: metrics.anees_bounds(10**300, 10**300), "below 1e300")])
def test_metrics_refuse_what_float64_cannot_give(call, match):
    """Regression: each returned NaN, inf, a negative NEES or a LinAlgError."""
    with pytest.raises(FusionInputError, match=match):
        call()


def _brute_ospa_gospa(X, Y, c, p):
    """OSPA and GOSPA (alpha = 2) of equal-size sets by every permutation, each sum of
    d^p taken in units of its own largest distance (math.hypot's distances: no square
    over- or underflows), so that no term that matters underflows at any p."""
    k = len(X)
    D = [[min(math.hypot(*(x - y)), c) for y in Y] for x in X]
    best = np.inf  # (sum_i d_i^p)^(1/p) of the best permutation
    for perm in itertools.permutations(range(k)):
        d = [D[i][j] for i, j in enumerate(perm)]
        top = max(d)
        best = min(best, top * sum((v / top) ** p for v in d) ** (1 / p) if top > 0 else 0.0)
    return best * k ** (-1 / p), best


@pytest.mark.parametrize("scale", [1e-170, 1e-100, 1.0, 1e150, 1e200])
@pytest.mark.parametrize("p", [1.0, 2.0, 400.0, 2000.0])
def test_ospa_and_gospa_at_any_scale_and_order_match_brute_force(scale, p):
    """Fuzz N1: distances of 2e200 came back as c (the squares overflowed) and of 2e-170
    as 0; N2: at p = 400 every assigned term (d / u)^p underflowed, u the largest of all
    distances, and OSPA of two pairs 0.1 apart was 0. Against every permutation."""
    rng = np.random.default_rng([int(p), int(abs(np.log10(scale)))])
    for _ in range(5):
        X = rng.normal(0, 3, (4, 2)) * scale
        Y = X + rng.normal(0, 0.5, (4, 2)) * scale
        ospa, gospa = _brute_ospa_gospa(X, Y, 1e300, p)
        assert metrics.ospa(X, Y, 1e300, p) == pytest.approx(ospa, rel=1e-12)
        assert metrics.gospa(X, Y, 1e300, p) == pytest.approx(gospa, rel=1e-12)
    pairs = metrics.match([[1e200, 0.0]], [[-1e200, 0.0]], 1e300)
    assert [a.tolist() for a in pairs] == [[0], [0]]


def test_gospa_with_a_subnormal_alpha_is_its_root_from_logs():
    """Fuzz O2: with alpha = 5e-324, (k - m) / alpha overflowed and a GOSPA of 2.105 was
    refused as an overflow. Against the root taken in logs by hand,
    c ((k - m) / alpha)^(1/p)."""
    import math

    for k, c, p, alpha in ((1, 1.0, 1000.0, 5e-324), (3, 2.0, 500.0, 1e-310)):
        want = c * math.exp((math.log(k) - math.log(alpha)) / p)
        got = metrics.gospa(np.zeros((0, 1)), np.zeros((k, 1)), c=c, p=p, alpha=alpha)
        assert got == pytest.approx(want, rel=1e-14)


@pytest.mark.parametrize("call,match", [
    (lambda: metrics.gospa([[0.0, 0.0], [1.0, 1.0]], np.zeros((0, 2)), 1e308, 2, 0.5),
     "GOSPA overflows"),
    (lambda: metrics.gospa([[0.0, 0.0]], np.zeros((0, 2)), 1e10, 1, 1e-300),
     "GOSPA overflows"),
    (lambda: metrics.spectral_norms(np.full((1, 2, 2), 1e308)),
     r"spectral norm of covs\[0\] overflows"),
    (lambda: metrics.mncm(np.full((1, 2, 2), 1e308)), r"spectral norm of covs\[0\] overflows"),
    (lambda: metrics.cardinality_error([1e308], [1.0]), "whole numbers from 0 to 2\\^53"),
    (lambda: metrics.cardinality_error([1.5], [2]), r"n_estimated must be counts.*got 1\.5"),
    (lambda: metrics.cardinality_error([1], [-1]), r"n_true must be counts.*got -1")])
def test_metrics_refuse_an_overflow_or_a_count_that_is_none(call, match):
    """Fuzz N3-N5: inf from GOSPA and the spectral norms, NaN from MNCM, inf and 1.5
    targets from cardinality_error."""
    with pytest.raises(FusionInputError, match=match):
        call()


@pytest.mark.parametrize("c", [10.0, 1e155, 1e200, 1e300])
@pytest.mark.parametrize("p", [1.0, 2.0, 3.0])
def test_ospa_and_gospa_with_a_cutoff_far_above_the_distances(c, p):
    """Fuzz I5: with c = 1e300, (d / c)^p underflowed to 0 and OSPA and GOSPA of two point
    sets 4.5 m apart came back 0. Against brute force over the assignments, from the
    distances themselves (all far below c and its powers)."""
    rng = np.random.default_rng(int(np.log10(c)) + int(p))
    X, Y = rng.normal(0, 3, (4, 2)), rng.normal(0, 3, (4, 2))
    D = np.minimum(np.linalg.norm(X[:, None] - Y[None], axis=-1), c)
    best = min(sum(D[i, j] ** p for i, j in enumerate(perm))
               for perm in itertools.permutations(range(4)))
    assert metrics.ospa(X, Y, c, p) == pytest.approx((best / 4) ** (1 / p), rel=1e-12)
    assert metrics.gospa(X, Y, c, p) == pytest.approx(best ** (1 / p), rel=1e-12)
    # one target more: the unassigned one costs c^p / 2 (alpha = 2), which dominates for
    # the large c
    Y5 = np.vstack([Y, [[1.0, 1.0]]])
    D5 = np.minimum(np.linalg.norm(X[:, None] - Y5[None], axis=-1), c)
    best5 = min(sum(D5[i, j] ** p for i, j in enumerate(perm))
                for perm in itertools.permutations(range(5), 4))
    assert metrics.gospa(X, Y5, c, p) == pytest.approx(
        (best5 + c ** p / 2) ** (1 / p) if c < 1e100 else c * 0.5 ** (1 / p), rel=1e-12)


def test_rmse_of_errors_near_the_top_of_float64_is_exact_or_refused():
    """Fuzz U1: errors of 1e308 made rmse NaN (their scale 2^1024 was inf). A single error
    of 1e308 has RMSE 1e308 exactly; errors of 1e308 in four components, an RMSE of 2e308,
    are refused as an overflow, by name."""
    assert metrics.rmse([[1e308]], [[0.0]]) == 1e308
    assert metrics.rmse([[-1e308], [1e308]], [[0.0], [0.0]]) == 1e308
    assert metrics.rmse([[2.0**1023, 0.0]], [[0.0, 0.0]]) == 2.0**1023
    with pytest.raises(FusionInputError, match="the RMSE overflows float64"):
        metrics.rmse(np.full((3, 4), 1e308), np.ones((3, 4)))


@pytest.mark.parametrize("level", [0.95, 1 - 1e-12, 1 - 1e-16, np.nextafter(1.0, 0.0)])
def test_nees_bounds_of_two_dimensions_are_the_closed_form_up_to_a_level_below_one(level):
    """Fuzz U2: at a level within 1e-16 of 1 the upper bound was inf (1 - a rounded to 1 in
    chi2.ppf). chi2(2) is exponential: its quantiles are -2 log(1 - p), so the two-sided
    interval at level L is (-2 log(1 - a), -2 log(a)), a = (1 - L) / 2."""
    lo, hi = metrics.nees_bounds(2, level)
    a = (1.0 - level) / 2.0
    assert hi == pytest.approx(-2.0 * math.log(a), rel=1e-13)
    assert lo == pytest.approx(-2.0 * math.log1p(-a), rel=1e-13)
