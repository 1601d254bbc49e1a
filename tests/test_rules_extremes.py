"""The rules on extreme inputs, against exact arithmetic: determinants that overflow,
denormal covariances, nodes 1e150 around 1 with condition numbers up to 1e13, thousands of
nodes, large and offset means. Never a NaN or inf, never a covariance that is not positive
definite."""

from fractions import Fraction

import numpy as np
import pytest
from test_rules import (
    assert_close,
    exact_blue,
    exact_ci,
    exact_weights,
    joint,
    probed_gains,
    problem,
)
from test_rules_exact import to_float
from test_rules_pairs import W_GRID, decimal_ei, exact_ici_cov, exact_ici_mean

import fusion_opt as fo
from fusion_opt.rules import PAIR_ONLY, RULES


@pytest.mark.parametrize("n,scales", [(12, (1e-30, 3e-30)), (2, (1e200, 2e200)),
                                      (40, (1e-8, 1e8))])
def test_ifci_weights_do_not_overflow(n, scales):
    """Issue: det Y overflowed (n = 12, 1e-30 I; n = 2, 1e200 I) and gave NaN."""
    covs = np.stack([s * np.eye(n) for s in scales])
    out = RULES["ifci"](np.zeros((2, n)), covs, "trace")
    assert_close(out.weights, to_float(np.array(exact_weights("ifci", covs))), 1e-14)


def _denormal_problem(name):
    rng = np.random.default_rng(40)
    means, covs = problem(rng, 2, 2, log10_cond=1.0)
    covs = covs * 1e-310  # denormal: the entries keep ~45 of their bits
    covs = 0.5 * (covs + np.swapaxes(covs, 1, 2))
    cross = joint(rng, covs, 0.5) if name == "known-cross" else None
    return means, covs, cross


@pytest.mark.parametrize("name", list(RULES))
def test_denormal_covariances_through_fuse(name):
    """Issue: covariances 1e-310 gave NaN in every rule but ifci. Exact references take the
    denormal inputs as they are."""
    means, covs, cross = _denormal_problem(name)
    args = {} if cross is None else {"cross": cross}
    r = fo.fuse(means, covs, method=name, **args)
    assert np.isfinite(r.cov).all() and np.isfinite(r.mean).all()
    if name in ("naive", "fast-ci", "ifci"):
        P, m = exact_ci(means, covs, exact_weights(name, covs))
    elif name == "known-cross":
        P, m = exact_blue(means, cross)
    elif name == "ici":  # at ICI's weight, which no weight of the grid betters
        w = r.weights[1]
        P, m = to_float(exact_ici_cov(covs, w)), to_float(exact_ici_mean(means, covs, w))
        best = min(np.trace(exact_ici_cov(covs, v)) for v in W_GRID)
        assert np.trace(exact_ici_cov(covs, w)) <= best * (1 + Fraction(1e-15))
    else:
        P, m = decimal_ei(means, covs)
    assert_close(r.cov, P, 1e-12)
    assert_close(r.mean, m, 1e-12)


def _extreme_cases(rng, count):
    """(name, means, covs, args): nodes 10^U(-150, 150), conditions up to 1e13."""
    for _ in range(count):
        for name in RULES:
            N = 2 if name in PAIR_ONLY else int(rng.integers(2, 6))
            n = int(rng.choice([1, 2, 4, 8]))
            means, covs = problem(rng, N, n, 150.0, log10_cond=rng.uniform(0.0, 13.0))
            args = {"cross": joint(rng, covs, rng.uniform(0, 0.99))} \
                if name == "known-cross" else {}
            yield name, means, covs, args


def test_no_nan_and_positive_definite_on_extreme_inputs():
    """Finite and positive definite always; CI weights sum to 1, gain shares to 1 within
    the rounding the conditioning allows."""
    for name, means, covs, args in _extreme_cases(np.random.default_rng(41), 40):
        for criterion in ("trace", "logdet"):
            out = RULES[name](means, covs, criterion, **args)
            assert all(np.isfinite(x).all() for x in out[:3]), name
            np.linalg.cholesky(out.cov)
            cond = np.linalg.cond(covs).max()
            tol = 1e-14 if out.weights_are == "ci_weights" else 1e-14 * cond
            assert abs(out.weights.sum() - 1.0) <= tol, name


@pytest.mark.parametrize("name", ["naive", "fast-ci", "ifci", "known-cross"])
def test_extreme_inputs_match_exact_arithmetic(name):
    """Nodes 1e150 apart, conditions up to 1e13: errors within (condition x eps)."""
    rng = np.random.default_rng(42)
    for _ in range(12):
        N, n = int(rng.integers(2, 4)), int(rng.choice([1, 2, 3]))
        log10_cond = rng.uniform(0.0, 13.0)
        means, covs = problem(rng, N, n, 150.0, log10_cond)
        if name == "known-cross":
            S = joint(rng, covs, 0.5)
            out = RULES[name](means, covs, "trace", cross=S)
            P, m = exact_blue(means, S)
        else:
            out = RULES[name](means, covs, "trace")
            P, m = exact_ci(means, covs, exact_weights(name, covs))
        rtol = 1e-14 * 10.0 ** log10_cond
        assert_close(out.cov, P, rtol)
        assert_close(out.mean, m, rtol)


def test_many_nodes():
    """N = 40 against exact arithmetic; N = 2000 against the textbook formulas in doubles
    (scales within 1e+-1, where they are accurate, except that det Y - det(Y - Y_i) loses
    about log10(N) digits to cancellation); nodes 1e150 around 1: finite and positive
    definite."""
    rng = np.random.default_rng(43)
    means, covs = problem(rng, 40, 2, 1.0)
    for name in ("naive", "fast-ci", "ifci"):
        out = RULES[name](means, covs, "trace")
        P, m = exact_ci(means, covs, exact_weights(name, covs))
        assert_close(out.cov, P, 1e-14)
        assert_close(out.mean, m, 1e-14)
    means, covs = problem(rng, 2000, 3, 1.0)
    Ys = np.linalg.inv(covs)
    Y = Ys.sum(0)
    inv_tr = 1.0 / np.trace(covs, axis1=1, axis2=2)
    score = np.linalg.det(Y) - np.linalg.det(Y - Ys) + np.linalg.det(Ys)
    for name, w, rtol in [("naive", np.ones(2000), 1e-13),
                          ("fast-ci", inv_tr / inv_tr.sum(), 1e-13),
                          ("ifci", score / score.sum(), 1e-11)]:
        out = RULES[name](means, covs, "trace")
        P = np.linalg.inv(np.einsum("i,ijk->jk", w, Ys))
        assert_close(out.cov, P, rtol)
        assert_close(out.mean, P @ np.einsum("i,ijk,ik->j", w, Ys, means), rtol)
        if name != "naive":
            assert_close(out.weights, w, rtol)
    means, covs = problem(rng, 2000, 3, 150.0, 13.0)
    for name in ("naive", "fast-ci", "ifci"):
        out = RULES[name](means, covs, "trace")
        assert np.isfinite(out.mean).all()
        np.linalg.cholesky(out.cov)


def test_large_and_offset_means():
    """The mean is formed from differences to the nearest node's mean, scaled by a power of
    two: means near 1e300 do not overflow, and a common offset of 1e8 costs no digit even
    where the gains are large (known-cross, correlation 0.9999: gains near +-11)."""
    rng = np.random.default_rng(44)
    means, covs = problem(rng, 3, 2)
    for name in ("naive", "fast-ci", "ifci"):
        big = 1e300 * np.sign(means)
        out = RULES[name](big, covs, "trace")
        assert_close(out.mean, exact_ci(big, covs, exact_weights(name, covs))[1], 1e-14)
    covs = np.stack([np.eye(2), 1.21 * np.eye(2)])
    S = np.array([[covs[0], 0.9999 * 1.1 * np.eye(2)], [0.9999 * 1.1 * np.eye(2), covs[1]]])
    assert np.abs(probed_gains("known-cross", covs, cross=S)).max() > 10.0
    offset = rng.standard_normal((2, 2)) + 1e8
    out = RULES["known-cross"](offset, covs, "trace", cross=S)
    m = exact_blue(offset, S)[1]
    assert np.abs(out.mean - m).max() <= np.spacing(np.abs(m).max())


def test_known_cross_refuses_a_joint_covariance_beyond_the_condition_limit():
    """Regression: a correlation of 1 - 1e-14 between two nodes (whitened condition
    5.7e14) was accepted and gave a covariance off by 1e-2, where a single covariance is
    refused above prepare.MAX_CONDITION; 1 - 1e-10 (condition 5.7e10) still fuses."""
    def fuse(rho):
        cross = np.zeros((2, 2, 2, 2))
        cross[0, 0] = cross[1, 1] = np.eye(2)
        cross[0, 1] = cross[1, 0] = rho * np.eye(2)
        return fo.fuse(np.zeros((2, 2)), np.stack([np.eye(2)] * 2), "known-cross",
                       cross=cross)
    with pytest.raises(fo.FusionInputError, match="numerically singular"):
        fuse(1 - 1e-14)
    np.testing.assert_allclose(fuse(1 - 1e-10).cov, (1 - 0.5e-10) * np.eye(2), rtol=1e-6)


def test_independent_nodes_do_not_make_a_correlated_pair_singular():
    """Fuzz L7: a pair correlated at 1 - 1e-13 (condition 2e13) fused alone, but with 30
    independent nodes beside it was refused, the estimate |C|_F |C^-1|_F growing with
    the joint's order; now the joint's estimate is the largest of independent blocks'.
    Reference: the pair is one node of information 2 / (1 + rho) beside the others."""
    rng = np.random.default_rng(7)
    n, rho = 2, 1 - 1e-13
    for extra in (0, 30):
        N = 2 + extra
        cross = np.zeros((N, N, n, n))
        cross[np.arange(N), np.arange(N)] = np.eye(n)
        cross[0, 1] = cross[1, 0] = rho * np.eye(n)
        means = rng.standard_normal((N, n))
        r = fo.fuse(means, np.tile(np.eye(n), (N, 1, 1)), "known-cross", cross=cross)
        info = extra + 2 / (1 + rho)
        np.testing.assert_allclose(r.cov, np.eye(n) / info, rtol=1e-15, atol=0)
        mean = (means[2:].sum(0) + (means[0] + means[1]) / (1 + rho)) / info
        np.testing.assert_allclose(r.mean, mean, rtol=0, atol=1e-13)


@pytest.mark.parametrize("N, n", [(2, 1), (3, 2), (8, 4), (20, 3)])
def test_the_joint_condition_estimate_bounds_the_condition_number(N, n):
    """`_joint_condition` is at least numpy's 2-norm condition number of the joint and at
    most m^1.5 times it (m = N n), on random joints from well to badly conditioned."""
    from fusion_opt.rules import _joint_condition, _norm1
    rng = np.random.default_rng(N * n)
    m = N * n
    for spread in (0.0, 4.0, 10.0):
        Q = np.linalg.qr(rng.standard_normal((m, m)))[0]
        C = (Q * 10.0 ** rng.uniform(-spread, 0.0, m)) @ Q.T
        C = 0.5 * (C + C.T)
        Ri = np.linalg.inv(np.linalg.cholesky(C))
        estimate, cond = _joint_condition(_norm1(C), Ri), np.linalg.cond(C)
        assert cond * (1 - 1e-6) <= estimate <= m**1.5 * cond * (1 + 1e-6)


def _independent(covs):
    """The joint covariance (N, N, n, n) of independent nodes: known-cross is naive."""
    N = len(covs)
    cross = np.zeros((N, N, *covs.shape[1:]))
    cross[np.arange(N), np.arange(N)] = covs
    return cross


@pytest.mark.parametrize("name", list(RULES))
def test_an_overflow_in_a_batch_names_the_problem_and_what_overflowed(name):
    """Fuzz J2: a rule's overflow in fuse_batch said neither which problem nor whether the
    objective (a trace of 2e308 and more) or the estimate overflowed, as BCI's does."""
    B, N, n = 4, 2, 4
    covs = np.tile(np.eye(n), (B, N, 1, 1))
    covs[2] *= 1e308  # every rule's P is at least 0.5e308 I: a trace of 2e308 or more
    args = {"cross": np.stack([_independent(c) for c in covs])} if name == "known-cross" else {}
    with pytest.raises(fo.FusionInputError,
                       match=r"^problem 2: the fused objective \(its trace\) overflows"):
        fo.fuse_batch(np.zeros((B, N, n)), covs, name, **args)


@pytest.mark.parametrize("name", list(RULES))
def test_a_fused_mean_beyond_float64_is_an_overflow_for_every_rule(name):
    """Fuzz J3: where only the fused mean leaves float64 (its exact value about 3.4e308),
    ici, ei and known-cross said "the fused mean or covariance is not finite or not
    positive definite" (a FusionSolverError) where the fixed-weight rules said the estimate
    overflows (FusionInputError)."""
    P = np.array([[[1, .999, 0], [.999, 1, 0], [0, 0, 1]],
                  [[1, -.999, 0], [-.999, 1, 0], [0, 0, 1]]])
    m = np.array([[1.7e308, -1.7e308, 0], [1.7e308, 1.7e308, 0]])
    args = {"cross": _independent(P)} if name == "known-cross" else {}
    with pytest.raises(fo.FusionInputError, match=r"^the fused estimate overflows"):
        fo.fuse(m, P, name, **args)
    with pytest.raises(fo.FusionInputError, match=r"^problem 1: the fused estimate overflows"):
        fo.fuse_batch(np.stack([m / 1e300, m]), np.stack([P, P]), name,
                      **{k: np.stack([v, v]) for k, v in args.items()})


def test_known_cross_keeps_the_share_of_a_node_whose_gain_underflows():
    """Fuzz J5: nodes 2^1100 apart in scale (within what prepare accepts): the far node's
    gain, 2^-1100, was below float64's range and its share of the mean, 2^-500 of the
    exact 2^-499 (naive's, and the BLUE's for an independent cross), was lost; the mean
    is now formed without the gains."""
    Pa, Pb = np.ldexp(np.eye(1), -1000), np.ldexp(np.eye(1), 100)
    means = np.array([[np.ldexp(1.0, -500)], [np.ldexp(1.0, 600)]])
    cross = np.zeros((2, 2, 1, 1))
    cross[0, 0], cross[1, 1] = Pa, Pb
    exact = np.ldexp(1.0, -499)  # (2^1000 2^-500 + 2^-100 2^600) / (2^1000 + 2^-100)
    for method, args in (("naive", {}), ("known-cross", {"cross": cross})):
        r = fo.fuse(means, np.array([Pa, Pb]), method, **args)
        assert r.mean[0] == exact, (method, r.mean[0] / exact)


def test_a_fused_mean_in_range_is_not_refused_where_its_correction_alone_overflows():
    """Fuzz L10: the mean m_r + correction overflowed in its correction (2/3 of 3.4e308)
    before m_r was added, so known-cross refused means of -1.7e308, 1.7e308, 1.7e308 that
    naive fuses to 5.67e307; ei and ici alike (gain_mean). Each now agrees with the same
    rule on the means divided by 2^20 and scaled back."""
    M = np.array([[-1.7e308], [1.7e308], [1.7e308]])
    C = np.ones((3, 1, 1))
    cross = np.zeros((3, 3, 1, 1))
    cross[0, 0] = cross[1, 1] = cross[2, 2] = 1.0
    naive = fo.fuse(M, C, "naive").mean
    np.testing.assert_allclose(naive, [1.7e308 / 3], rtol=1e-15)
    np.testing.assert_allclose(fo.fuse(M, C, "known-cross", cross=cross).mean, naive,
                               rtol=1e-15)
    M2 = np.array([[1.5546171585032048e+308, 1.4868991974538816e+308],
                   [1.5877419589967942e+308, -1.5536402496854725e+308]])
    C2 = np.array([[[6.263140775677595, 1.6624627626004775],
                    [1.6624627626004775, 4.112101286563053]],
                   [[6.403818740744428, 0.03788878049541373],
                    [0.03788878049541373, 4.337752800769174]]])
    for method in ("ei", "ici"):
        r = fo.fuse(M2, C2, method)
        scaled = fo.fuse(M2 / 2**20, C2, method).mean * 2**20
        np.testing.assert_allclose(r.mean, scaled, rtol=1e-13)
        exact_mean = decimal_ei(M2, C2)[1] if method == "ei" else \
            to_float(exact_ici_mean(M2, C2, r.weights[1]))
        np.testing.assert_allclose(r.mean, exact_mean, rtol=1e-13)
