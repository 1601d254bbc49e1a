"""The rules of `rules.py`: their contract, naive / fast-ci / ifci / known-cross against
exact rational arithmetic (also for nodes 1e150 apart in scale), consistency under random
joint covariances (DESIGN §1), known-cross's checks of `cross`, and the glue of `fuse` and
`fuse_batch`. ICI and EI: test_rules_pairs.py; extreme inputs: test_rules_extremes.py."""

import numpy as np
import pytest
import scipy.linalg
from conftest import joint
from test_rules_exact import det, exact, inv, to_float

import fusion_opt as fo
from fusion_opt.results import Status
from fusion_opt.rules import PAIR_ONLY, RULE_ARGS, RULES, RuleOutput


def spd(rng, n, log10_scale=0.0, log10_cond=2.0):
    """A random SPD matrix (n, n): random rotation, eigenvalues log-uniform over a factor
    10^log10_cond around 10^log10_scale."""
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    P = (Q * 10.0 ** (log10_scale + log10_cond * rng.uniform(-0.5, 0.5, n))) @ Q.T
    return 0.5 * (P + P.T)


def problem(rng, N, n, spread=0.0, log10_cond=2.0):
    """means (N, n) and covs (N, n, n), node scales 10^U(-spread, spread)."""
    covs = np.stack([spd(rng, n, rng.uniform(-spread, spread), log10_cond) for _ in range(N)])
    return rng.standard_normal((N, n)), covs


def flat(S):
    """(N, N, n, n) blocks -> (N n, N n)."""
    N, n = S.shape[1:3]
    return S.transpose(0, 2, 1, 3).reshape(N * n, N * n)


def probed_gains(name, covs, **args):
    """K_i (N, n, n) read off the rule as a black box: the mean is linear in the means, so
    a unit vector in node i's mean gives a column of K_i."""
    N, n = covs.shape[:2]
    K = np.empty((N, n, n))
    for i in range(N):
        for k in range(n):
            m = np.zeros((N, n))
            m[i, k] = 1.0
            K[i, :, k] = RULES[name](m, covs, "trace", **args).mean
    return K


def true_error(gains, S):
    """cov(sum_i K_i e_i) = K S K^T for the joint S (N, N, n, n)."""
    N, n = gains.shape[:2]
    K = gains.transpose(1, 0, 2).reshape(n, N * n)
    return K @ flat(S) @ K.T


def assert_close(actual, reference, rtol):
    """max |actual - reference| <= rtol * max |reference| (reference not 0)."""
    err = np.abs(np.asarray(actual) - reference).max()
    assert err <= rtol * np.abs(reference).max(), (err, np.abs(reference).max())


# --- exact references -------------------------------------------------------------------

def exact_ci(means, covs, w):
    """The CI formula in Fractions for weights w (Fractions): P, m as floats."""
    Ys = [inv(P) for P in exact(covs)]
    P = inv(sum(wi * Y for wi, Y in zip(w, Ys, strict=True)))
    m = P @ sum(wi * Y @ mi for wi, Y, mi in zip(w, Ys, exact(means), strict=True))
    return to_float(P), to_float(m)


def exact_weights(name, covs):
    """Weights of naive (all 1), fast-ci and ifci, in Fractions."""
    if name == "naive":
        return [1] * len(covs)
    if name == "fast-ci":
        inv_tr = [1 / np.trace(P) for P in exact(covs)]
        return [x / sum(inv_tr) for x in inv_tr]
    Ys = [inv(P) for P in exact(covs)]
    Y = sum(Ys)
    score = [det(Y) - det(Y - Yi) + det(Yi) for Yi in Ys]
    return [s / sum(score) for s in score]


def exact_blue(means, S):
    """P = (H^T S^-1 H)^-1, m = P H^T S^-1 m_stack in Fractions, as floats."""
    N, n = means.shape
    Sinv = inv(exact(flat(S)))
    H = np.concatenate([np.eye(n, dtype=int).astype(object)] * N)
    P = inv(H.T @ Sinv @ H)
    return to_float(P), to_float(P @ H.T @ Sinv @ exact(means.ravel()))


@pytest.mark.parametrize("spread", [0.0, 150.0])
@pytest.mark.parametrize("name", ["naive", "fast-ci", "ifci"])
def test_ci_family_matches_exact_arithmetic(name, spread):
    rng = np.random.default_rng(10)
    for N, n in [(2, 2), (3, 2), (2, 3), (4, 1)]:
        means, covs = problem(rng, N, n, spread)
        out = RULES[name](means, covs, "trace")
        w = exact_weights(name, covs)
        P, m = exact_ci(means, covs, w)
        assert_close(out.cov, P, 1e-13)
        assert_close(out.mean, m, 1e-12)
        if out.weights_are == "ci_weights":
            assert_close(out.weights, to_float(np.array(w)), 1e-13)


def test_known_cross_matches_exact_blue():
    rng = np.random.default_rng(11)
    for spread in (0.0, 150.0):
        for N, n in [(2, 2), (3, 2), (2, 3)]:
            means, covs = problem(rng, N, n, spread)
            S = joint(rng, covs, rho=0.8)
            out = RULES["known-cross"](means, covs, "trace", cross=S)
            P, m = exact_blue(means, S)
            assert_close(out.cov, P, 1e-12)
            assert_close(out.mean, m, 1e-11)


@pytest.mark.parametrize("N, n", [(16, 4), (17, 4), (9, 8)])
def test_known_cross_on_joints_of_order_past_64_matches_a_second_solver(N, n):
    """Past N n = 64 the joint's Cholesky factor and inverse come from LAPACK
    (rules._LAPACK_ABOVE): the BLUE against scipy's Cholesky solve of the joint itself,
    unwhitened; a joint that is not positive definite is refused on both paths."""
    rng = np.random.default_rng(N * n)
    means, covs = problem(rng, N, n)
    S = joint(rng, covs, rho=0.5)
    r = fo.fuse(means, covs, "known-cross", cross=S)
    c = scipy.linalg.cho_factor(flat(S))
    H = np.tile(np.eye(n), (N, 1))
    P = np.linalg.inv(H.T @ scipy.linalg.cho_solve(c, H))
    m = P @ H.T @ scipy.linalg.cho_solve(c, means.ravel())
    assert_close(r.cov, P, 1e-12)
    assert_close(r.mean, m, 1e-11)
    # whitened cross block sqrt(2) I: not a correlation
    S[0, 1] = np.sqrt(2.0) * np.linalg.cholesky(covs[0]) @ np.linalg.cholesky(covs[1]).T
    S[1, 0] = S[0, 1].T
    with pytest.raises(fo.FusionInputError, match="cross: the joint covariance is not "
                                                  "positive definite"):
        fo.fuse(means, covs, "known-cross", cross=S)


def test_hand_computed_fast_ci_and_ifci():
    P = np.array([np.diag([1.0, 2.0]), np.diag([3.0, 1.0])])
    means = np.array([[1.0, 2.0], [3.0, 5.0]])
    r = RULES["fast-ci"](means, P, "trace")  # tr = 3, 4: w = (1/3, 1/4) / (7/12)
    np.testing.assert_allclose(r.weights, [4 / 7, 3 / 7], rtol=1e-15)
    np.testing.assert_allclose(r.cov, 1.4 * np.eye(2), rtol=1e-15)
    # det Ya = 1/2, det Yb = 1/3, det(Ya + Yb) = 2: w_a = (2 - 1/3 + 1/2) / 4
    np.testing.assert_allclose(RULES["ifci"](means, P, "trace").weights, [13 / 24, 11 / 24],
                               rtol=1e-15)


# --- the contract -----------------------------------------------------------------------

@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_a_single_node_is_returned_as_it_is_by_every_rule(criterion):
    """Fuzz M4: with N = 1 every gain is I, so each rule (and BCI) returns the node: its
    mean and symmetrised covariance exactly, weight 1 and the criterion there (log det by
    numpy's slogdet, to the rounding condition 1e10 allows), where naive, fast-ci and ifci
    were 8e-11 off in the mean at condition 1e10 and known-cross's share was 1.00000006.
    Statuses as fo.Status says: CLOSED_FORM for a rule, OPTIMAL for BCI and MBCI (fuzz
    M3), in fuse and fuse_batch alike."""
    rng = np.random.default_rng(1)
    Q = np.linalg.qr(rng.standard_normal((4, 4)))[0]
    m = np.array([100.0, -50.0, 20.0, 3.0])
    for scale in (1.0, 1e300, 1e-300):
        P = (Q * np.array([1.0, 1e-3, 1e-6, 1e-10])) @ Q.T * scale
        sym = 0.5 * P + 0.5 * P.T
        f = np.trace(sym) if criterion == "trace" else np.linalg.slogdet(sym / scale)[1] + \
            4 * np.log(scale)
        for method in ("bci", "mbci", "naive", "fast-ci", "ifci", "known-cross"):
            args = {"cross": P[None, None]} if method == "known-cross" else \
                {"p_detect": 1.0, "chi": 1.0} if method == "mbci" else {}
            status = Status.OPTIMAL if method in ("bci", "mbci") else Status.CLOSED_FORM
            r = fo.fuse(m[None], P[None], method, criterion, **args)
            rb = fo.fuse_batch(m[None, None], P[None, None], method, criterion,
                               **{k: v[None] if k == "cross" else v for k, v in args.items()})
            for w, mean, cov, obj, st in ((r.weights, r.mean, r.cov, r.objective, r.status),
                                          (rb.weights[0], rb.mean[0], rb.cov[0],
                                           rb.objective[0], rb.status[0])):
                assert w.tolist() == [1.0] and st == status, (method, w, st)
                np.testing.assert_array_equal(mean, m)
                np.testing.assert_array_equal(cov, sym)
                # log det to the input's own rounding, n eps cond (1e10 here)
                assert obj == pytest.approx(f, rel=1e-13, abs=16 * 4 * 2.2e-16 * 1e10)


def test_tables_name_every_rule():
    assert set(RULES) == {"naive", "known-cross", "fast-ci", "ifci", "ici", "ei"}
    assert RULE_ARGS == {name: frozenset({"cross"} if name == "known-cross" else ())
                         for name in RULES}
    assert PAIR_ONLY == {"ici", "ei"}


@pytest.mark.parametrize("name", list(RULES))
def test_output_contract_and_gains(name):
    """Types and shapes; gains sum to I; weights are what weights_are says: CI weights
    reproduce the gains K_i = P w_i Y_i read off the mean, gain shares are tr(K_i) / n."""
    rng = np.random.default_rng(12)
    N = 2 if name in PAIR_ONLY else 3
    means, covs = problem(rng, N, 3)
    args = {"cross": joint(rng, covs, 0.5)} if name == "known-cross" else {}
    out = RULES[name](means, covs, "logdet", **args)
    assert isinstance(out, RuleOutput)
    assert out.weights.shape == (N,) and out.mean.shape == (3,) and out.cov.shape == (3, 3)
    assert out.status == (Status.OPTIMAL if name == "ici" else Status.CLOSED_FORM)
    assert np.array_equal(out.cov, out.cov.T) and np.linalg.eigvalsh(out.cov).min() > 0
    K = probed_gains(name, covs, **args)
    assert_close(K.sum(0), np.eye(3), 1e-13)
    np.testing.assert_allclose(out.mean, np.einsum("ijk,ik->j", K, means), atol=1e-13)
    assert abs(out.weights.sum() - 1.0) < 1e-14
    if name in ("naive", "known-cross", "ei"):
        assert out.weights_are == "gain_shares"
        assert_close(out.weights, np.trace(K, axis1=1, axis2=2) / 3, 1e-13)
    else:
        assert out.weights_are == "ci_weights" and (out.weights >= 0).all()
        if name != "ici":
            Ys = np.linalg.inv(covs)
            assert_close(K, out.cov @ (out.weights[:, None, None] * Ys), 1e-13)


# --- consistency (DESIGN §1) -----------------------------------------------------------

@pytest.mark.parametrize("name", ["fast-ci", "ifci"])
def test_ci_rules_consistent_under_random_correlation(name):
    rng = np.random.default_rng(4)
    for spread in (0.0, 2.0, 2.0, 0.0, 1.0):
        means, covs = problem(rng, 3, 3, spread)
        S = joint(rng, covs, rho=rng.uniform(0.5, 1.0))
        out = RULES[name](means, covs, "trace")
        excess = out.cov - true_error(probed_gains(name, covs), S)
        assert np.linalg.eigvalsh(excess).min() >= -1e-12 * np.abs(out.cov).max()


def test_naive_overconfident_under_correlation():
    P = np.array([np.eye(2), np.eye(2)])
    S = np.array([[np.eye(2), np.eye(2)], [np.eye(2), np.eye(2)]])  # identical errors
    out = RULES["naive"](np.zeros((2, 2)), P, "trace")
    assert np.linalg.eigvalsh(out.cov - true_error(probed_gains("naive", P), S)).max() < 0


def test_known_cross_reports_its_true_error_and_is_smallest():
    """BLUE: its P is the true error covariance K S K^T of its own mean, and no other
    rule's true error is smaller."""
    rng = np.random.default_rng(1)
    means, covs = problem(rng, 3, 2)
    S = joint(rng, covs, rho=0.6)
    out = RULES["known-cross"](means, covs, "trace", cross=S)
    assert_close(true_error(probed_gains("known-cross", covs, cross=S), S), out.cov, 1e-12)
    for name in ("naive", "fast-ci", "ifci"):
        err = true_error(probed_gains(name, covs), S)
        assert np.linalg.eigvalsh(err - out.cov).min() >= -1e-12, name


# --- known-cross checks its cross -------------------------------------------------------

def _bad_cross():
    """(cross, what the message must say) pairs for covs = problem(rng(5), 2, 2, 150)."""
    rng = np.random.default_rng(5)
    means, covs = problem(rng, 2, 2, 150.0)
    S = joint(rng, covs, 0.5)
    small = int(np.argmin(np.trace(covs, axis1=1, axis2=2)))
    asym = S.copy()  # 1e-6 of the small node's scale: invisible beside the large node's
    asym[small, small, 0, 1] *= 1.0 + 1e-6
    wrong_diag = S.copy()
    wrong_diag[small, small] *= 1.0 + 1e-6
    too_correlated = S.copy()  # whitened cross block 1.01 I: a correlation above 1
    R = np.linalg.cholesky(covs)
    too_correlated[0, 1] = 1.01 * R[0] @ R[1].T
    too_correlated[1, 0] = too_correlated[0, 1].T
    nan = S.copy()
    nan[0, 1, 0, 0] = np.nan
    cases = [(S[:, :, :1], "shape"), (nan, "non-finite"), (S.astype(complex), "real"),
             ([["a"]], "real"), (asym, "not symmetric"), (wrong_diag, r"cross\[\d, \d\]"),
             (too_correlated, "not positive definite")]
    return means, covs, cases


def test_known_cross_refuses_bad_cross_by_name():
    means, covs, cases = _bad_cross()
    for cross, what in cases:
        with pytest.raises(fo.FusionInputError, match="cross") as info:
            RULES["known-cross"](means, covs, "trace", cross=cross)
        assert info.match(what), (what, str(info.value))


def test_known_cross_in_a_batch_names_the_problem_of_a_bad_cross():
    """Each refusal of the kernel (`_check_cross`, the whitened joint) names the problem and
    the block or index of the user's array, in the user's units."""
    means, covs, cases = _bad_cross()
    good = joint(np.random.default_rng(5), covs, 0.5)
    for cross, what in cases[1:2] + cases[4:]:
        stack = np.stack([good, good, cross])
        with pytest.raises(fo.FusionInputError, match="cross") as info:
            fo.fuse_batch(np.stack([means] * 3), np.stack([covs] * 3), "known-cross",
                          cross=stack)
        assert info.match(what), (what, str(info.value))
        assert info.match(r"problem 2|index \(2, 0, 1, 0, 0\)"), str(info.value)
    asym = cases[4][0]
    small = int(np.argmin(np.trace(covs, axis1=1, axis2=2)))
    by = np.abs(asym[small, small] - asym[small, small].T).max()
    with pytest.raises(fo.FusionInputError, match=f"by {by:.3g}"):
        fo.fuse(means, covs, "known-cross", cross=asym)


# --- the glue of fuse and fuse_batch ----------------------------------------------------

@pytest.mark.parametrize("name", list(RULES))
def test_fuse_and_fuse_batch_call_the_rules(name):
    rng = np.random.default_rng(7)
    N = 2 if name in PAIR_ONLY else 3
    B = 3
    means = rng.standard_normal((B, N, 2))
    covs = np.stack([problem(rng, N, 2)[1] for _ in range(B)])
    cross = np.stack([joint(rng, c, 0.5) for c in covs]) if name == "known-cross" else None
    batch = fo.fuse_batch(means, covs, name, "logdet", cross=cross)
    for b in range(B):
        args = {} if cross is None else {"cross": cross[b]}
        r = fo.fuse(means[b], covs[b], method=name, criterion="logdet", **args)
        direct = RULES[name](means[b], covs[b], "logdet", **args)
        np.testing.assert_allclose(r.cov, direct.cov, rtol=1e-14)
        np.testing.assert_allclose(r.mean, direct.mean, rtol=1e-14)
        assert r.objective == pytest.approx(np.linalg.slogdet(r.cov)[1], rel=1e-14, abs=1e-14)
        assert r.status == direct.status and r.method == name
        np.testing.assert_allclose(batch.cov[b], r.cov, rtol=1e-14)


def test_fuse_refuses_wrong_rule_arguments():
    P = np.stack([np.eye(2)] * 3)
    with pytest.raises(fo.FusionInputError, match="'ei' fuses 2"):
        fo.fuse(np.zeros((3, 2)), P, method="ei")
    with pytest.raises(fo.FusionInputError, match="cross"):
        fo.fuse(np.zeros((3, 2)), P, method="known-cross")
    with pytest.raises(fo.FusionInputError, match="cross"):
        fo.fuse(np.zeros((3, 2)), P, method="naive", cross=np.zeros((3, 3, 2, 2)))


@pytest.mark.parametrize("method", ["naive", "fast-ci", "ifci"])
def test_the_fixed_weight_kernel_reports_informations_that_do_not_factor(method):
    """The compiled kernel of naive, fast-ci and ifci, given factors whose informations sum
    to a singular matrix (node 1's factor 0, node 0's of rank 1), reports NOT_PD before it
    divides by IFCI's score sum or computes on unset outputs."""
    from fusion_opt import rules

    F = np.zeros((1, 2, 2, 2))
    F[0, 0, 0, 0] = 1.0
    covs = np.tile(np.eye(2), (1, 2, 1, 1))
    out = [np.empty(s) for s in ((1, 2), (1, 2), (1, 2, 2), (1,), (1, 2))]
    where = np.zeros(3, np.int64)
    assert rules.fuse_fixed(rules.COMPILED[method], F, np.zeros((1, 2, 2)), covs,
                            np.zeros(1, np.int64), True, *out, where) == rules.NOT_PD
    assert where[0] == 0


@pytest.mark.parametrize("method", ["naive", "fast-ci", "ifci", "ici", "ei"])
@pytest.mark.parametrize("code, error, message", [
    ("NOT_PD", fo.FusionSolverError, "^method '{}' failed with status 'numerical_error'"),
    ("RATIO", fo.FusionSolverError, "^method '{}' failed .* the covariances' ratio exceeds"),
    ("OVERFLOW", fo.FusionInputError, r"^the fused (estimate|objective \(its trace\)) "
                                      "overflows float64")])
def test_a_compiled_rule_raises_for_what_its_kernel_reports(method, code, error, message,
                                                            monkeypatch):
    """What the kernel reports becomes the rule's error, naming it, without a warning from
    computing on the unset outputs."""
    import warnings

    from fusion_opt import rules

    kernel = "fuse_pair" if method in rules.PAIR_ONLY else "fuse_fixed"
    monkeypatch.setattr(rules, kernel, lambda *args: getattr(rules, code))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(error, match=message.format(method)):
            fo.fuse(np.zeros((2, 2)), np.stack([np.eye(2)] * 2), method)


def test_a_rule_whose_trace_overflows_is_refused_without_a_warning():
    """Regression: fast CI of covariances 1e308 I and 1.7e308 I (a fused covariance of
    1.26e308 I, whose trace overflows) was refused, but numpy's overflow warning leaked from
    the scaling back to the caller's units."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(fo.FusionInputError, match="overflows float64"):
            fo.fuse(np.ones((2, 2)), np.stack([1e308 * np.eye(2), 1.7e308 * np.eye(2)]),
                    "fast-ci")


def test_an_asymmetry_past_float64_is_said_without_inf_or_a_warning():
    """Fuzz L6: cross blocks near +-1.8e308 that differ by more than float64 holds made the
    message say "by inf" and warn of an overflow (an error under -W error)."""
    import warnings

    covs = np.stack([np.eye(2) * 1e308] * 2)
    cross = np.zeros((2, 2, 2, 2))
    cross[0, 0], cross[1, 1] = covs
    cross[0, 1] = [[1.7e308, 0.0], [0.0, 0.0]]
    cross[1, 0] = [[-1.7e308, 0.0], [0.0, 0.0]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(fo.FusionInputError, match=r"not symmetric: .* by 2 x 1\.7e\+308$"):
            fo.fuse(np.zeros((2, 2)), covs, "known-cross", cross=cross)
