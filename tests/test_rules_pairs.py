"""The pair rules: ICI against brute force in exact arithmetic and its consistency under
common information; EI against Sijs & Lazar's formulas as the NRL Tracker Component Library
implements them, written here independently (symmetric square-root whitening of P_a,
60-digit decimals), including the near-equal eigen-directions of the issue."""

from decimal import Decimal, localcontext
from fractions import Fraction

import numpy as np
import pytest
from test_rules import assert_close, probed_gains, problem, spd, true_error
from test_rules_exact import DIGITS, decimal, det, eigh2, exact, inv, to_float

import fusion_opt as fo
from fusion_opt.rules import RULES

EPS = np.finfo(float).eps

T_ISSUE = np.array([[1.0, 0.3], [0.2, 1.0]])
M_ISSUE = np.array([[1.0, -1.0], [-0.5, 2.0]])

# --- ICI --------------------------------------------------------------------------------

# Weights of the brute-force search: a fine grid, and geometric towards both ends, where
# the optimum of nodes of very different scales lies.
W_GRID = sorted({0.0, 1.0, *np.linspace(0.0, 1.0, 41), *(10.0 ** -np.arange(1, 17)),
                 *(1.0 - 10.0 ** -np.arange(1, 16)), *(10.0 ** -np.arange(20, 320, 20.0))})


def exact_ici_cov(covs, w):
    """(Y_a + Y_b - (w P_a + (1 - w) P_b)^-1)^-1 in Fractions, at the float w."""
    Pa, Pb = exact(covs)
    w = Fraction(w)
    return inv(inv(Pa) + inv(Pb) - inv(w * Pa + (1 - w) * Pb))


def exact_ici_mean(means, covs, w):
    """ICI's mean P [(Y_a - w G) m_a + (Y_b - (1 - w) G) m_b] in Fractions at the float w,
    G = (w P_a + (1 - w) P_b)^-1 and P = `exact_ici_cov` (Noack et al. 2017)."""
    Pa, Pb = exact(covs)
    ma, mb = exact(means)
    w = Fraction(w)
    G = inv(w * Pa + (1 - w) * Pb)
    return exact_ici_cov(covs, w) @ ((inv(Pa) - w * G) @ ma + (inv(Pb) - (1 - w) * G) @ mb)


def exact_size(P, criterion) -> Fraction:
    """tr P or det P, exactly: each increases with the criterion."""
    return np.trace(P) if criterion == "trace" else det(P)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_ici_is_the_minimum_over_a_brute_force_grid(criterion):
    """At ICI's weight, its covariance is the exact ICI covariance and the exact objective
    is no larger than at any weight of the grid; nodes up to 1e300 apart in scale."""
    rng = np.random.default_rng(20)
    for spread in (0.0, 0.0, 8.0, 150.0):
        for n in (2, 3):
            covs = problem(rng, 2, n, spread, log10_cond=3.0)[1]
            out = RULES["ici"](np.zeros((2, n)), covs, criterion)
            P = exact_ici_cov(covs, out.weights[1])  # (1 - w, w)
            assert_close(out.cov, to_float(P), 1e-12)
            best = min(exact_size(exact_ici_cov(covs, w), criterion) for w in W_GRID)
            assert exact_size(P, criterion) <= best * (1 + Fraction(1e-15))


@pytest.mark.parametrize("scale", [1e16, 1e17])
def test_ici_scales_1e16_apart_give_the_better_node(scale):
    """Issue: P_a = scale [[2, 1], [1, 2]], P_b = diag(1, 3) gave an indefinite covariance
    (objective -5e16) at 1e16 and a LinAlgError at 1e17. The exact ICI objective only grows
    as w leaves 1, so the answer is P_b, m_b."""
    covs = np.stack([scale * np.array([[2.0, 1.0], [1.0, 2.0]]), np.diag([1.0, 3.0])])
    r = fo.fuse(M_ISSUE, covs, method="ici")
    assert np.linalg.eigvalsh(r.cov).min() > 0
    assert r.weights[1] == 1.0 and r.objective == pytest.approx(4.0, rel=1e-15)
    np.testing.assert_allclose(r.cov, covs[1], rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(r.mean, M_ISSUE[1], rtol=1e-15)
    assert all(np.trace(exact_ici_cov(covs, w)) > 4 for w in (1 - 2.0 ** -52, 1 - 1e-6, 0.5))


def test_ici_weights_are_in_cis_sense():
    """Fuzz G4: ICI returned node a with weights (0, 1), labelled CI weights, where fo.ci
    gives (1, 0): its w multiplies P_a in G = w P_a + (1 - w) P_b, so w = 0 gives node a."""
    covs = np.stack([0.1 * np.eye(2), np.eye(2)])
    means = np.array([[1.0, 2.0], [3.0, 4.0]])
    r, ci = fo.fuse(means, covs, method="ici"), fo.ci(means[0], covs[0], means[1], covs[1])
    np.testing.assert_array_equal(r.weights, [1.0, 0.0])
    np.testing.assert_array_equal(ci.weights, [1.0, 0.0])
    np.testing.assert_array_equal(r.mean, means[0])
    np.testing.assert_allclose(r.cov, covs[0], rtol=1e-15)


def test_ici_hand_computed():
    P = np.array([np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    m = np.array([[1.0, 2.0], [3.0, 5.0]])
    # by symmetry w = 1/2, G = 2.5 I, P^-1 = diag(1 + 1/4 - 0.4, ...) = 0.85 I
    r = RULES["ici"](m, P, "trace")
    np.testing.assert_allclose(r.weights, [0.5, 0.5], rtol=1e-15)
    np.testing.assert_allclose(r.cov, np.eye(2) / 0.85, rtol=1e-15)
    Ka = (np.diag([1.0, 0.25]) - 0.2 * np.eye(2)) / 0.85  # P (Y_a - w G^-1)
    Kb = (np.diag([0.25, 1.0]) - 0.2 * np.eye(2)) / 0.85
    np.testing.assert_allclose(r.mean, Ka @ m[0] + Kb @ m[1], rtol=1e-14)


@pytest.mark.parametrize("spread", [0.0, 3.0])
def test_ici_consistent_under_common_information(spread):
    """e_a = P_a (I_a e_a' + I_c e_c), e_b = P_b (I_b e_b' + I_c e_c) with independent
    information I_a, I_b and a common I_c: the joint has cross block P_a I_c P_b."""
    rng = np.random.default_rng(5)
    for _ in range(6):
        Ia, Ib, Ic = (np.linalg.inv(spd(rng, 3, rng.uniform(-spread, spread)))
                      for _ in range(3))
        Pa, Pb = np.linalg.inv(Ia + Ic), np.linalg.inv(Ib + Ic)
        covs = np.array([0.5 * (Pa + Pa.T), 0.5 * (Pb + Pb.T)])
        S = np.array([[covs[0], Pa @ Ic @ Pb], [Pb @ Ic @ Pa, covs[1]]])
        for criterion in ("trace", "logdet"):
            out = RULES["ici"](np.zeros((2, 3)), covs, criterion)
            excess = out.cov - true_error(probed_gains("ici", covs), S)
            assert np.linalg.eigvalsh(excess).min() >= -1e-12 * np.abs(out.cov).max()


def test_ici_symmetric_in_its_nodes():
    rng = np.random.default_rng(6)
    for _ in range(5):
        means, covs = problem(rng, 2, 3, 4.0)
        r, q = RULES["ici"](means, covs, "trace"), RULES["ici"](means[::-1], covs[::-1], "trace")
        assert_close(q.cov, r.cov, 1e-13)
        assert_close(q.mean, r.mean, 1e-12)
        assert abs(q.weights[0] - r.weights[1]) < 1e-12


# --- EI ---------------------------------------------------------------------------------

def ei_reference(means, covs, eigh, inverse, sqrt, tie):
    """EI as Sijs & Lazar (2012) eqs. 8 and 11-16 define it and the NRL library computes
    it: P_a = S_a D_a S_a^T, D_a^-1/2 S_a^T P_b S_a D_a^-1/2 = S_b D_b S_b^T,
    T = S_a D_a^1/2 S_b, Gam = T max(D_b, I) T^T, P = (Y_a + Y_b - Gam^-1)^-1; the mutual
    mean in T coordinates (z = T^-1 m) weighs z_a by 1/d_b - 1/d_Gam + eta and z_b by
    1 - 1/d_Gam + eta, eta = `tie` (else 0) when some d_b is 1 to within 1e-30.
    eigh, inverse, sqrt work on the arrays given (floats or Decimals)."""
    Pa, Pb = covs
    da, Sa = eigh(Pa)
    root = sqrt(da)
    W = Sa / root
    db, Sb = eigh(W.T @ Pb @ W)
    T = (Sa * root) @ Sb
    dG = np.array([max(d, d ** 0) for d in db], dtype=db.dtype)
    Gam_inv = inverse((T * dG) @ T.T)
    Ya, Yb = inverse(Pa), inverse(Pb)
    P = inverse(Ya + Yb - Gam_inv)
    eta = tie if any(abs(d - 1) < 1e-30 for d in db) else 0 * tie
    wa, wb = 1 / db - 1 / dG + eta, 1 - 1 / dG + eta
    z = inverse(T) @ means.T  # (n, 2)
    gam = T @ ((wa * z[:, 0] + wb * z[:, 1]) / (wa + wb))
    return P, P @ (Ya @ means[0] + Yb @ means[1] - Gam_inv @ gam)


def decimal_ei(means, covs):
    """ei_reference in 60-digit decimals (n = 2), eta = 1e-40."""
    with localcontext() as ctx:
        ctx.prec = DIGITS
        P, m = ei_reference(decimal(means), decimal(covs), eigh2, inv,
                            lambda v: np.array([x.sqrt() for x in v], dtype=object),
                            Decimal("1e-40"))
    return to_float(P), to_float(m)


def float_ei(means, covs):
    """ei_reference in doubles (no ties)."""
    return ei_reference(means, covs, np.linalg.eigh, np.linalg.inv, np.sqrt, 0.0)


def issue_pair(gap):
    """P_b = T T^T, P_a = T diag(1 + gap, 3) T^T for the issue's T."""
    return np.stack([T_ISSUE @ np.diag([1.0 + gap, 3.0]) @ T_ISSUE.T, T_ISSUE @ T_ISSUE.T])


def test_ei_near_equal_eigen_directions_gives_the_better_node():
    """Issue: gap 1e-9 gave the mean (-0.077, 2.085); P_b is smaller on both axes, so EI
    (exact, and the NRL library) gives m_b and P_b."""
    covs = issue_pair(1e-9)
    r = fo.fuse(M_ISSUE, covs, method="ei")
    np.testing.assert_allclose(r.mean, M_ISSUE[1], rtol=1e-14)
    assert_close(r.cov, covs[1], 1e-15)
    P, m = decimal_ei(M_ISSUE, covs)
    np.testing.assert_allclose(r.mean, m, rtol=1e-14)


def _ei_cases():
    """(means, covs): random, near-degenerate, exact ties, nodes 1e300 apart."""
    rng = np.random.default_rng(30)
    cases = [problem(rng, 2, 2, spread, 3.0) for spread in (0.0, 0.0, 0.0, 2.0, 150.0)]
    cases += [(M_ISSUE, issue_pair(gap)) for gap in (1e-6, -1e-6, 1e-9, -1e-9, 1e-12, 2.0)]
    cases.append((M_ISSUE, np.stack([np.diag([2.0, 5.0]), np.diag([2.0, 1.0])])))  # tie
    cases.append((M_ISSUE, np.stack([spd(rng, 2)] * 2)))  # P_a = P_b
    return cases


def test_ei_matches_the_decimal_reference():
    for means, covs in _ei_cases():
        r = RULES["ei"](means, covs, "trace")
        P, m = decimal_ei(means, covs)
        assert_close(r.cov, P, 1e-13)
        assert_close(r.mean, m, 1e-12)


def test_ei_matches_the_reference_in_higher_dimension():
    rng = np.random.default_rng(31)
    for n in (3, 4, 5):
        for spread in (0.0, 1.0):
            means, covs = problem(rng, 2, n, spread)
            r = RULES["ei"](means, covs, "trace")
            P, m = float_ei(means, covs)
            assert_close(r.cov, P, 1e-11)
            assert_close(r.mean, m, 1e-11)


def test_ei_commutes_with_a_change_of_coordinates():
    """EI(A m_i, A P_i A^T) = (A m, A P A^T): EI works per axis of the pair's own basis,
    so no choice of coordinates enters the result (cases without a tie, which A P A^T
    would round apart)."""
    rng = np.random.default_rng(32)
    for means, covs in _ei_cases()[:-2]:
        A = rng.standard_normal((2, 2)) + 2.0 * np.eye(2)
        r = RULES["ei"](means, covs, "trace")
        moved = A @ covs @ A.T
        q = RULES["ei"](means @ A.T, 0.5 * (moved + np.swapaxes(moved, 1, 2)), "trace")
        assert_close(q.cov, A @ r.cov @ A.T, 1e-12)
        assert_close(q.mean, A @ r.mean, 1e-11)


def test_ei_hand_computed():
    P = np.array([np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    e = RULES["ei"](np.array([[1.0, 2.0], [3.0, 5.0]]), P, "trace")
    np.testing.assert_allclose(e.cov, np.eye(2), rtol=1e-15)
    np.testing.assert_allclose(e.mean, [1.0, 5.0], rtol=1e-15)
    tie = RULES["ei"](np.array([[1.0, 2.0], [3.0, 5.0]]), np.stack([np.eye(2)] * 2), "trace")
    np.testing.assert_allclose(tie.mean, [2.0, 3.5], rtol=1e-15)  # a tie: the average


@pytest.mark.parametrize("n", [3, 4, 6])
def test_equal_covariances_are_an_exact_tie_in_every_dimension(n):
    """P_a = P_b: the pencil L_b^-1 L_a is exactly I (a triangular solve, as LAPACK's; the
    product with L_b^-1 was I to a few eps, so EI's tie rule gave the loser a share of
    0.08-0.4 instead of 1/2, and ICI picked an end by rounding). EI then splits every axis
    in half, ICI keeps node a (f is flat; its search stops at w = 0)."""
    rng = np.random.default_rng(n)
    P = spd(rng, n)
    means, covs = rng.standard_normal((2, n)), np.stack([P, P])
    e = fo.fuse(means, covs, method="ei")
    np.testing.assert_array_equal(e.weights, [0.5, 0.5])
    np.testing.assert_allclose(e.mean, means.mean(axis=0), rtol=0, atol=4 * EPS)
    i = fo.fuse(means, covs, method="ici")
    np.testing.assert_array_equal(i.weights, [1.0, 0.0])
    np.testing.assert_array_equal(i.mean, means[0])


@pytest.mark.parametrize("method", ["ici", "ei"])
@pytest.mark.parametrize("a, b", [(1e-280, 1e280), (1e280, 1e-280)])
def test_pair_rules_of_nodes_1e560_apart_give_the_better_node(method, a, b):
    """Within the range prepare accepts (2^1900 between nodes), the pair rules keep the
    better node: the compiled rules formed P = T f^2 T^T as T (f f) T^T, whose f^2 of
    1e-560 underflowed to 0 and was refused as not positive definite; (T f)(T f)^T."""
    covs = np.stack([np.eye(3) * a, np.diag([b, 2 * b, 3 * b])])
    means = np.array([[1.0, 2.0, 3.0], [-1.0, 0.0, 1.0]])
    better = int(b < a)
    r = fo.fuse(means, covs, method=method)
    assert r.weights[better] == 1.0
    # ICI's axes are exp(log-sums), exact to about eps |log mu| = 1.4e-13 relative here
    np.testing.assert_allclose(r.cov, covs[better], rtol=1e-12)
    np.testing.assert_allclose(r.mean, means[better], rtol=1e-14)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("method", ["ici", "ei"])
def test_a_node_that_wins_outright_is_returned_as_given(method, criterion):
    """Fuzz J4: where one node's gain is 1 on every axis (ICI at w = 0, EI won on every
    axis by one node), the rule rebuilt its covariance from the pencil, 25 ulps off, 2.6e-3
    in the node's own metric at condition 1e13, and reported a log det up to 6.6e-5 worse
    than the node's own. Now the node itself, mean, covariance and objective, bit for bit
    BCI's vertex, whichever node it is."""
    means = np.array([[1.5926766993746688, -0.29160567967055817, -1.3519203071885877],
                      [0.37059110358286773, -0.10173810041909909, 0.34765699069739425]])
    Pa = np.array([[2.4365542182216903e-03, 1.3705168397970324e-02, -1.6074024007216843e-03],
                   [1.3705168397970324e-02, 7.7092489429849309e-02, -9.0416514004402239e-03],
                   [-1.6074024007216843e-03, -9.0416514004402239e-03, 1.0604361247946545e-03]])
    Pb = np.array([[1.0213000355339727e+01, 1.7868458586828371e+01, -1.5377769852601791e+01],
                   [1.7868458586828371e+01, 3.2308613151905462e+01, -2.7055441764466224e+01],
                   [-1.5377769852601791e+01, -2.7055441764466224e+01, 2.3183375313644369e+01]])
    for order in ([0, 1], [1, 0]):  # cond(Pa) = 5.6e11, Pa below Pb on every axis
        covs = np.array([Pa, Pb])[order]
        r = fo.fuse(means[order], covs, method, criterion)
        vertex = fo.bci(means[order], covs, criterion)
        win = order.index(0)
        np.testing.assert_array_equal(r.cov, Pa)
        np.testing.assert_array_equal(r.mean, means[0])
        np.testing.assert_array_equal(r.weights, np.eye(2)[win])
        assert vertex.weights[win] == 1.0 and r.objective == vertex.objective
