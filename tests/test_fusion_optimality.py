"""Optimality of CI/BCI weights against independent references: grids, a second solver,
closed forms, and the certificate itself."""

import itertools

import numpy as np
import pytest
from conftest import objective, random_instance
from test_fuzz import check_ci

import fusion_opt as fo

NS, NODES, CRITERIA = (1, 2, 3, 4, 6), (1, 2, 3, 5, 8), ("trace", "logdet")
SUITE = [(n, N, c, ill) for n, N, c, ill in itertools.product(NS, NODES, CRITERIA, (0, 1, 2, 3))]


def _tolerance(obj: float) -> float:
    return 1e-7 * max(abs(obj), 1.0)


@pytest.mark.parametrize("n,N,criterion,k", SUITE)
def test_gap_is_tiny_on_random_suite(n, N, criterion, k):
    """200 instances (half ill-conditioned): the certificate and an independent objective."""
    rng = np.random.default_rng([n, N, k, len(criterion)])
    means, covs = random_instance(rng, n, N, ill=k >= 2)
    r = fo.bci(means, covs, criterion)
    assert r.status == "optimal"
    assert 0.0 <= r.gap <= _tolerance(r.objective)
    assert np.all(r.weights >= 0) and abs(r.weights.sum() - 1.0) <= 4e-16
    # At condition up to 1e12 the objective itself is conditioned like n eps cond(P_i) in
    # the input's entries (exact arithmetic puts both our value and the reference's within
    # that of the true one); well conditioned, 1e-9 is far above the rounding of either.
    cond = max(np.linalg.cond(c) for c in covs)
    rel = 64 * n * np.finfo(float).eps * cond if k >= 2 else 1e-9
    assert r.objective == pytest.approx(objective(covs, r.weights, criterion), rel=rel)
    # never worse than the best single node
    vertices = (np.trace(covs, axis1=1, axis2=2) if criterion == "trace"
                else np.linalg.slogdet(covs)[1])
    assert r.objective <= vertices.min() + rel * max(abs(vertices.min()), 1.0)
    # the certificate, the fused mean and the objective against 60-digit arithmetic on the
    # input as given (test_fuzz.check_ci: an exact certificate above 1e-10 only within the
    # input's own sensitivity), not the library's own r.gap
    check_ci(r, means, covs, criterion)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("n", (1, 2, 3, 4, 6))
def test_pairwise_matches_100001_point_grid(n, criterion):
    rng = np.random.default_rng(100 + n)
    means, covs = random_instance(rng, n, 2)
    grid = np.linspace(0.0, 1.0, 100_001)
    f = objective(covs, np.stack([grid, 1 - grid], axis=1), criterion)
    r = fo.ci(means[0], covs[0], means[1], covs[1], criterion)
    assert r.objective <= f.min() + 1e-12 * abs(f.min())
    assert r.objective == pytest.approx(f.min(), rel=1e-6, abs=1e-9)


def _simplex_grid(k: int, center=(0.0, 0.0), radius=1.0) -> np.ndarray:
    """Points (K, 3) of the simplex on the grid of step 1/k (boundaries included), within
    radius of center in the first two coordinates."""
    def axis(c):
        return np.arange(max(0, round((c - radius) * k)), min(k, round((c + radius) * k)) + 1)

    A, B = np.meshgrid(axis(center[0]), axis(center[1]), indexing="ij")
    A, B = A.ravel(), B.ravel()
    keep = A + B <= k
    A, B = A[keep], B[keep]
    return np.stack([A / k, B / k, (k - A - B) / k], axis=1)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("n", (2, 3, 4))
def test_three_nodes_match_fine_simplex_grid(n, criterion):
    """A 1/400 grid on the simplex, then a 1/40000 grid around its best point."""
    rng = np.random.default_rng(200 + n)
    means, covs = random_instance(rng, n, 3)
    coarse = _simplex_grid(400)
    best = coarse[np.argmin(objective(covs, coarse, criterion))]
    fine = _simplex_grid(40_000, center=best, radius=2 / 400)
    f_min = min(objective(covs, fine, criterion).min(), objective(covs, coarse, criterion).min())
    r = fo.bci(means, covs, criterion)
    assert r.objective <= f_min + 1e-12 * abs(f_min)
    assert r.objective == pytest.approx(f_min, rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("n,N,criterion", [(n, N, c) for n in (2, 4, 6) for N in (2, 3, 5)
                                           for c in CRITERIA])
def test_clarabel_and_scs_agree(n, N, criterion):
    """The raw solver outputs (no polish) agree to 1e-5; polished ones to 1e-10."""
    rng = np.random.default_rng(300 + 10 * n + N)
    means, covs = random_instance(rng, n, N)
    raw = {b: fo.bci(means, covs, criterion, b, polish=False) for b in ("clarabel", "scs")}
    assert raw["scs"].objective == pytest.approx(raw["clarabel"].objective, rel=1e-5, abs=1e-7)
    pol = {b: fo.bci(means, covs, criterion, b) for b in ("clarabel", "scs")}
    assert pol["scs"].objective == pytest.approx(pol["clarabel"].objective, rel=1e-10, abs=1e-12)


def test_scalar_state_puts_all_weight_on_smallest_variance():
    rng = np.random.default_rng(7)
    for N in (2, 3, 5, 8):
        var = rng.uniform(0.1, 10.0, N)
        r = fo.bci(rng.standard_normal((N, 1)), var[:, None, None], "trace")
        expected = np.zeros(N)
        expected[np.argmin(var)] = 1.0
        np.testing.assert_array_equal(r.weights, expected)
        assert r.cov[0, 0] == pytest.approx(var.min(), rel=1e-14)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_identical_inputs_return_that_input(criterion):
    rng = np.random.default_rng(8)
    means, covs = random_instance(rng, 3, 1)
    r = fo.bci(np.repeat(means, 4, axis=0), np.repeat(covs, 4, axis=0), criterion)
    np.testing.assert_allclose(r.mean, means[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(r.cov, covs[0], rtol=1e-12, atol=1e-14)


def test_single_node_is_returned_with_weight_one():
    rng = np.random.default_rng(9)
    means, covs = random_instance(rng, 4, 1)
    r = fo.bci(means, covs)
    np.testing.assert_array_equal(r.weights, [1.0])
    np.testing.assert_allclose(r.cov, covs[0], rtol=1e-12)
    np.testing.assert_allclose(r.mean, means[0], rtol=1e-12)
    assert r.gap == 0.0


def numpy_gap(covs, w, criterion) -> float:
    """The certificate w.g - min_i g_i in numpy (well-conditioned covs): g_i = -tr(P Y_i P)
    ("trace") or -tr(P Y_i) ("logdet"), P = (sum_i w_i Y_i)^-1."""
    Ys = np.linalg.inv(covs)
    P = np.linalg.inv(np.einsum("i,ijk->jk", w, Ys))
    g = -np.einsum("ab,ibc,ca->i", P, Ys, P) if criterion == "trace" else \
        -np.einsum("ab,iba->i", P, Ys)
    return float(w @ g - g.min())


@pytest.mark.parametrize("criterion", CRITERIA)
def test_certificate_bounds_suboptimality_at_any_weights(criterion):
    """gap(w) is the certificate computed in numpy, is positive at random weights, and
    bounds f(w) - f* (f* by Clarabel, unpolished)."""
    rng = np.random.default_rng(10)
    for _ in range(20):
        means, covs = random_instance(rng, 3, 4)
        f_star = fo.bci(means, covs, criterion, "clarabel", polish=False).objective
        w = rng.dirichlet(np.ones(4))
        g = fo.optimality_gap(covs, w, criterion)
        assert g == pytest.approx(numpy_gap(covs, w, criterion), rel=1e-9)
        assert g > 0 and g >= objective(covs, w, criterion) - f_star - 1e-7 * abs(f_star)


def test_fused_mean_and_cov_follow_the_ci_formula():
    rng = np.random.default_rng(11)
    means, covs = random_instance(rng, 3, 4)
    r = fo.bci(means, covs)
    Y = sum(w * np.linalg.inv(P) for w, P in zip(r.weights, covs, strict=True))
    P = np.linalg.inv(Y)
    m = P @ sum(w * np.linalg.solve(P_i, m_i)
                for w, P_i, m_i in zip(r.weights, covs, means, strict=True))
    np.testing.assert_allclose(r.cov, P, rtol=1e-10)
    np.testing.assert_allclose(r.mean, m, rtol=1e-10, atol=1e-12)
    assert r.objective == pytest.approx(np.trace(P), rel=1e-12)


def test_results_are_frozen():
    rng = np.random.default_rng(12)
    r = fo.bci(*random_instance(rng, 2, 3))
    with pytest.raises(AttributeError):
        r.objective = 0.0
    with pytest.raises(ValueError):
        r.weights[0] = 0.5


# Two RBPF covariances of a Table 1 run on which Clarabel with chordal decomposition ended
# in InsufficientProgress (log-det criterion).
TABLE1_PAIR = np.array([
    [[0.009219691608134434, 7.937669689437101e-05, 0.014893297030032787, -5.2653393196455876e-05],
     [7.937669689437101e-05, 0.009179261371430578, -0.00010383403763244533, 0.015006466464030473],
     [0.014893297030032787, -0.00010383403763244533, 0.055625282926291646, -8.706124739618359e-05],
     [-5.2653393196455876e-05, 0.015006466464030473, -8.706124739618359e-05, 0.0560526860576159]],
    [[0.01027354637943516, 5.359313494769854e-05, 0.018059373853723536, 1.4136747668960579e-05],
     [5.359313494769854e-05, 0.010322994789870905, 2.675981727783219e-05, 0.018133699888725926],
     [0.018059373853723536, 2.675981727783219e-05, 0.06180551848421356, 0.00011159696774467528],
     [1.4136747668960579e-05, 0.018133699888725926, 0.00011159696774467528, 0.06195592325539716]],
])


@pytest.mark.parametrize("criterion", CRITERIA)
def test_clarabel_solves_the_table1_pair_that_once_failed(criterion):
    r = fo.bci(np.zeros((2, 4)), TABLE1_PAIR, criterion, "clarabel", polish=False)
    grid = np.linspace(0.0, 1.0, 100_001)
    f = objective(TABLE1_PAIR, np.stack([grid, 1 - grid], axis=1), criterion)
    assert r.objective == pytest.approx(f.min(), rel=1e-6, abs=1e-8)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_certificate_takes_float32_weights_and_names_what_is_wrong(criterion):
    """Fuzz G3: float32 weights of an optimum sum to 1 only within 1e-8 and were refused
    as "must be finite, >= 0 and sum to 1", naming neither the condition nor the sum. They
    are taken on the simplex (divided by their sum), where the certificate still bounds
    the suboptimality; what is refused says which condition fails, with the value."""
    rng = np.random.default_rng(12)
    means, covs = random_instance(rng, 3, 4)
    f_star = fo.bci(means, covs, criterion).objective
    optimum = fo.bci(means, covs, criterion).weights.astype(np.float32)
    for w, most in ((optimum, 1e-5 * abs(f_star)), (np.float32([0.2, 0.3, 0.1, 0.4]), np.inf)):
        w64 = w.astype(float) / w.astype(float).sum()
        g = fo.optimality_gap(covs, w, criterion)
        assert objective(covs, w64, criterion) - f_star - 1e-12 <= g <= most
        assert g == pytest.approx(numpy_gap(covs, w64, criterion), rel=1e-6, abs=1e-12)
    for w, message in (([0.5, 0.6, -0.1, 0.0], r"weights must be >= 0, got -0\.1 at node 2"),
                       ([0.5, 0.6, 0.1, 0.0], r"sum to 1 \(within 1e-09\), got a sum of 1\.2"),
                       ([np.nan, 0.5, 0.5, 0.0], r"weights must be finite, got \[nan"),
                       ([0.2, 0.3, 0.5, 1e-8], r"sum to 1 \(within 1e-09\), got a sum of 1\.0")):
        with pytest.raises(fo.FusionInputError, match=message):
            fo.optimality_gap(covs, w, criterion)
    # fuzz of 2026-11-29: N eps of float16 passed 1 at N = 1,024, so all-zero weights (an
    # infinite certificate) and weights summing to 2.9 were taken; the rounding of a
    # solution's weights to float16 (at most eps / 2 of their sum) still passes
    N = 2000
    many = np.stack([covs[i % 4] for i in range(N)])
    for w in (np.zeros(N, np.float16), np.float16([2.9] + [0] * (N - 1))):
        with pytest.raises(fo.FusionInputError, match=r"sum to 1 \(within 0\.0312\)"):
            fo.optimality_gap(many, w, criterion)
    uniform = np.full(N, 1 / N)
    g = fo.optimality_gap(many, uniform.astype(np.float16), criterion)
    assert g == pytest.approx(fo.optimality_gap(many, uniform, criterion), rel=1e-3)
