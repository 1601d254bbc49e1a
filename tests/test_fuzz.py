"""Seeded fuzz of every entry point on extreme but valid inputs and on bad ones (issue 9,
"Correct on every input").

Valid inputs: node scales from 1e-310 (denormal) to 1e300, conditions to 1e12, nodes up
to 1e32 apart, near-identical nodes, n up to 50, N up to 3000, MBCI with p = 0 and chi down to
1e-300; every method of `fo.fuse` with both criteria, `fo.ci` / `bci` / `mbci`, the
backends, and `fo.fuse_batch` against `fo.fuse`. Each call either raises
FusionInputError / FusionSolverError with a message, or returns a result that is

- finite, exactly symmetric and positive definite (Cholesky);
- CI weights on the simplex (CI family, fast-ci, ifci, ici), gain shares summing to 1;
- objective = tr(cov) or log det(cov), recomputed here from the returned cov;
- for the CI family, against the exact reference `Exact` below (80-digit decimal
  arithmetic on the inputs as given, no code of fusion_opt): the objective is f at the
  returned weights; never worse than the best single node; a result that is not a single
  node beats the best node in exact arithmetic (item 9: no unverified improvement); a
  single node comes back exactly as given; status "optimal" means an exact relative
  certificate within 1e-10, and the reported gap bounds the exact one, up to how far the
  input's own rounding moves the exact certificate (`sensitivity`: nothing on
  well-conditioned inputs, up to 1e-5 at condition 1e12 in random rotations);
- `fo.fuse_batch` equal to `fo.fuse` problem by problem, bit for bit.

Bad inputs of every kind raise FusionInputError whose message names the argument. The
defects this fuzz found have seeded regression tests at the end.
"""

from __future__ import annotations

from decimal import Decimal, localcontext

import numpy as np
import pytest
from conftest import extreme_instance, instance, joint, random_instance

import fusion_opt as fo

EPS = np.finfo(float).eps
OPTIMAL_RTOL = 1e-10
CRITERIA = ("trace", "logdet")


# --- the exact reference ----------------------------------------------------------------
#
# `Exact(covs, scales)` takes the covariances (N, n, n) as given (each float converted to a
# Decimal exactly) and MBCI's scales s_i (`exact_scales`, from p and chi in Decimal) and
# works in 80-digit decimal arithmetic: Y_i = s_i P_i^-1 by Gauss-Jordan elimination,
# Y(w) = sum_i w_i Y_i at the float weights w (exactly), P(w) = Y(w)^-1, and
#     f(w) = tr P(w) ("trace") or -log det Y(w) ("logdet"),
#     g_i(w) = -tr(P Y_i P) or -tr(P Y_i),      gap(w) = g.w - min_i g_i   (DESIGN §1),
# the gap relative to |f| for "trace", absolute for "logdet", as the library reports it.
# Trustworthy at condition 1e12: nothing is rounded to double precision; an elimination
# loses about log10 of the condition of what it inverts (12 digits for a node, 12 plus the
# nodes' spread in decades for Y(w), under 40 here) and the certificate, a difference of
# numbers of the size of f, another 12 where it is 1e-12 of f: 80 digits leave over 25
# (`test_exact_reference_is_converged` compares 80 with 120 digits).

DIGITS = 80


def _decimal(a):
    return [[Decimal(float(x)) for x in row] for row in np.asarray(a, dtype=float)]


def _inverse(A):
    """Gauss-Jordan elimination without pivoting (A symmetric positive definite)."""
    n = len(A)
    M = [row[:] + [Decimal(int(i == j)) for j in range(n)] for i, row in enumerate(A)]
    for c in range(n):
        pivot = M[c][c]
        assert pivot > 0, "not positive definite in exact arithmetic"
        row_c = [x / pivot for x in M[c]]
        M[c] = row_c
        for r in range(n):
            if r != c and M[r][c]:
                f = M[r][c]
                M[r] = [x - f * y for x, y in zip(M[r], row_c, strict=True)]
    return [row[n:] for row in M]


def _log_det(A):
    """log det of a symmetric positive definite A by elimination."""
    M = [row[:] for row in A]
    out = Decimal(0)
    for c in range(len(M)):
        pivot = M[c][c]
        assert pivot > 0, "not positive definite in exact arithmetic"
        out += pivot.ln()
        for r in range(c + 1, len(M)):
            if M[r][c]:
                f = M[r][c] / pivot
                M[r] = [x - f * y for x, y in zip(M[r], M[c], strict=True)]
    return out


def _matmul(A, B):
    cols = list(zip(*B, strict=True))
    return [[sum(a * b for a, b in zip(row, col, strict=True)) for col in cols] for row in A]


def exact_scales(p_detect, chi, N):
    """MBCI's s_i = p_i + (1 - p_i) chi_i prod_{j != i} (p_j + (1 - p_j) chi_j) (DESIGN §1)
    from the float p and chi (scalars or (N,)), in Decimal."""
    with localcontext() as ctx:
        ctx.prec = DIGITS
        p = [Decimal(float(x)) for x in np.broadcast_to(p_detect, (N,))]
        c = [Decimal(float(x)) for x in np.broadcast_to(chi, (N,))]
        t = [pi + (1 - pi) * ci for pi, ci in zip(p, c, strict=True)]
        out = []
        for i in range(N):
            prod = Decimal(1)
            for j in range(N):
                if j != i:
                    prod *= t[j]
            out.append(p[i] + (1 - p[i]) * c[i] * prod)
        return out


class Exact:
    """The CI problem of covs (N, n, n) (the covariances P_i / s_i with `scales` s_i), in
    `digits`-digit arithmetic; `perturb` (N, n, n) is added to the covariances exactly."""

    def __init__(self, covs, scales=None, digits=DIGITS, perturb=None):
        covs = np.asarray(covs, dtype=float)
        self.N, self.n = covs.shape[:2]
        self.digits = digits
        with localcontext() as ctx:
            ctx.prec = digits
            scales = [Decimal(1)] * self.N if scales is None else scales
            self.P = []
            for i, c in enumerate(covs):
                A = _decimal(c)
                A = [[(A[r][k] + A[k][r]) / 2 for k in range(self.n)] for r in range(self.n)]
                if perturb is not None:
                    E = _decimal(perturb[i])
                    A = [[a + e for a, e in zip(ra, re, strict=True)]
                         for ra, re in zip(A, E, strict=True)]
                self.P.append([[x / scales[i] for x in row] for row in A])
            self.Y = [_inverse(A) for A in self.P]

    def vertices(self, trace: bool) -> list:
        """f(e_i) of each node: tr(P_i / s_i) or log det(P_i / s_i)."""
        with localcontext() as ctx:
            ctx.prec = self.digits
            if trace:
                return [sum(A[k][k] for k in range(self.n)) for A in self.P]
            return [_log_det(A) for A in self.P]

    def at(self, w, trace: bool):
        """(f(w), certificate) at the float weights w (N,), the certificate relative to
        |f| for "trace"."""
        with localcontext() as ctx:
            ctx.prec = self.digits
            wd = [Decimal(float(x)) for x in w]
            n = self.n
            Y = [[sum(wd[i] * self.Y[i][r][c] for i in range(self.N) if wd[i])
                  for c in range(n)] for r in range(n)]
            P = _inverse(Y)
            f = sum(P[k][k] for k in range(n)) if trace else -_log_det(Y)
            g = []
            for Yi in self.Y:
                T = _matmul(_matmul(P, Yi), P) if trace else _matmul(P, Yi)
                g.append(-sum(T[k][k] for k in range(n)))
            gap = max(sum(a * b for a, b in zip(wd, g, strict=True)) - min(g), Decimal(0))
            return f, (gap / abs(f) if trace else gap)


    def mean(self, w, means) -> list:
        """The fused mean P(w) sum_i w_i Y_i m_i at the float weights w (N,) and means
        (N, n), Y_i the (scaled) informations: a list of n Decimals."""
        with localcontext() as ctx:
            ctx.prec = self.digits
            wd = [Decimal(float(x)) for x in w]
            md = [[Decimal(float(x)) for x in row] for row in np.asarray(means, dtype=float)]
            n = self.n
            Y = [[sum(wd[i] * self.Y[i][r][c] for i in range(self.N) if wd[i])
                  for c in range(n)] for r in range(n)]
            y = [sum(wd[i] * sum(self.Y[i][r][c] * md[i][c] for c in range(n))
                     for i in range(self.N) if wd[i]) for r in range(n)]
            P = _inverse(Y)
            return [sum(P[r][c] * y[c] for c in range(n)) for r in range(n)]


def sensitivity(covs, w, trace: bool, rng, scales=None, draws: int = 2) -> float:
    """How far the exact certificate at w moves when each node moves by a random symmetric
    E_i with |E_i|_F = 4 n eps |P_i|_F, about the backward error of its Cholesky factor in
    double precision (the largest change over `draws` draws). Where it exceeds 1e-10, no
    double-precision solver can certify the input as given to 1e-10."""
    covs = np.asarray(covs, dtype=float)
    n = covs.shape[1]
    base = float(Exact(covs, scales).at(w, trace)[1])
    worst = 0.0
    for _ in range(draws):
        E = rng.standard_normal(covs.shape)
        E = E + np.swapaxes(E, -1, -2)
        top = np.abs(covs).max(axis=(1, 2))[:, None, None]  # norms without overflow
        size = 4 * n * EPS * top * np.linalg.norm(covs / top, axis=(1, 2), keepdims=True)
        E *= size / np.linalg.norm(E, axis=(1, 2), keepdims=True)
        moved = float(Exact(covs, scales, perturb=E).at(w, trace)[1])
        worst = max(worst, abs(moved - base))
    return worst


# --- checks of a result -----------------------------------------------------------------

def cov_objective(cov, trace: bool) -> tuple[float, float]:
    """(tr cov or log det cov, the condition of cov's correlation form), in numpy: log det
    from the Cholesky factor of D^-1 cov D^-1, D a diagonal of powers of two near
    sqrt(diag cov), so no entry over- or underflows; raises if cov is not PD."""
    e = np.frexp(np.sqrt(np.diagonal(cov)))[1]
    C = np.ldexp(np.ldexp(cov, -e[:, None]), -e[None, :])
    L = np.linalg.cholesky(C)
    cond = np.linalg.cond(C)
    if trace:
        return float(np.trace(cov)), cond
    return float(2.0 * np.log(np.diagonal(L)).sum() + 2.0 * np.log(2.0) * e.sum()), cond


def check_estimate(r, N: int, n: int, trace: bool, cond_nodes: float = 1.0):
    """Finite, exactly symmetric, positive definite; weights as `weights_are` says (gain
    shares to the rounding that the nodes' largest condition `cond_nodes` allows); the
    objective recomputed from cov. Returns the condition of cov's correlation form."""
    assert r.weights.shape == (N,) and r.mean.shape == (n,) and r.cov.shape == (n, n)
    for name in ("weights", "mean", "cov"):
        assert np.isfinite(getattr(r, name)).all(), name
    assert np.isfinite(r.objective) and np.isfinite(r.gap) and r.gap >= 0
    assert np.array_equal(r.cov, r.cov.T), "cov not symmetric"
    obj, cond = cov_objective(r.cov, trace)  # Cholesky: positive definite
    if r.weights_are == "ci_weights":
        assert (r.weights >= 0).all() and abs(r.weights.sum() - 1.0) <= 4 * N * EPS
    else:  # gain shares tr(K_i) / n: sum_i K_i = I to the rounding of the informations
        assert abs(r.weights.sum() - 1.0) <= 1e-12 + 1e-14 * cond_nodes, r.weights.sum()
    # cov's own rounding: relative eps, or the spacing of denormals where entries are tiny
    eps = max(EPS, 2.0**-1074 / np.diagonal(r.cov).min())
    if trace:
        assert abs(obj - r.objective) <= 4 * n * eps * abs(obj), (obj, r.objective)
    else:
        assert abs(obj - r.objective) <= 16 * n * eps * (cond + abs(obj)), (obj, r.objective)
    return cond


def check_ci(r, means, covs, criterion, scales=None):
    """A result of the CI family (ci, bci, mbci): check_estimate, the single-node rule and
    everything against `Exact` (module docstring)."""
    N, n = covs.shape[:2]
    trace = criterion == "trace"
    check_estimate(r, N, n, trace)
    assert r.status in (fo.Status.OPTIMAL, fo.Status.OPTIMAL_INACCURATE)
    rel_reported = r.gap / abs(r.objective) if trace else r.gap
    assert (r.status == fo.Status.OPTIMAL) == (rel_reported <= OPTIMAL_RTOL)
    j = int(np.argmax(r.weights))
    single = r.weights[j] == 1.0
    if single and scales is None:  # a single node: its input, exactly
        np.testing.assert_array_equal(r.mean, means[j])
        np.testing.assert_array_equal(r.cov, 0.5 * (covs[j] + covs[j].T))
    ex = Exact(covs, scales)
    f, rel = ex.at(r.weights, trace)
    vertices = ex.vertices(trace)
    best = min(vertices)
    scale = abs(f) if trace else max(abs(f), 1)
    if single:
        assert abs(f - vertices[j]) <= Decimal("1e-50") * scale
    else:  # item 9: a fused result is reported only where it beats the best node
        assert f < best, ("fused result not better than the best node", float(f), float(best))
    # The objective is f at the weights, to the input's own accuracy: a change of each node
    # by eps of its norm moves f by up to about n eps cond (relative for "trace", absolute
    # for "logdet"; the condition of the worst node), far less on most problems.
    tol = Decimal(max(1e-9, 64 * n * EPS * np.linalg.cond(covs).max()))
    assert abs(Decimal(r.objective) - f) <= tol * scale, (r.objective, float(f))
    assert Decimal(r.objective) <= best + tol * scale  # never worse than the best node
    err, bound = mean_error(r, means, covs, ex)
    assert err <= bound, ("mean", float(err), float(bound))
    # "optimal" means the exact certificate is within 1e-10, and the reported gap bounds
    # it, up to how far the input's own rounding moves it (`sensitivity`, computed only
    # where it is needed): below 1e-13 for well-conditioned or diagonal nodes, so there the
    # check is strict; up to 1e-5 for nodes at condition 1e12 in random rotations, for
    # near-identical ones in "logdet", or near-identical ones that MBCI scales apart.
    rel = float(rel)
    over = max(rel - OPTIMAL_RTOL if r.status == fo.Status.OPTIMAL else 0.0,
               rel - 2 * rel_reported - OPTIMAL_RTOL / 2)
    if over > 0:
        rng = np.random.default_rng(0)
        moved = sensitivity(covs, r.weights, trace, rng, scales)
        if over > moved:  # two random directions can miss the sensitive one: look harder
            moved = max(moved, sensitivity(covs, r.weights, trace, rng, scales, 20))
        assert over <= 10 * moved, ("certificate beyond the input's sensitivity", rel,
                                    rel_reported, moved)


def mean_error(r, means, covs, ex: Exact) -> tuple[Decimal, Decimal]:
    """(error, bound) of r.mean against P(w) sum_i w_i Y_i m_i at r's weights in `ex`'s
    arithmetic: the bound is the rounding the conditions of the nodes and of the fused
    covariance allow, 64 n eps cond, relative to the largest input mean."""
    cond = max(np.linalg.cond(covs).max(), np.linalg.cond(r.cov))
    err = max(abs(Decimal(float(a)) - b) for a, b in zip(r.mean, ex.mean(r.weights, means),
                                                          strict=True))
    top = Decimal(float(np.abs(means).max()))
    return err, Decimal(64 * covs.shape[1] * EPS * cond) * top


def check_rule(r, means, covs, method, criterion):
    """A rule of rules.py: check_estimate and what each rule guarantees by construction."""
    N, n = covs.shape[:2]
    trace = criterion == "trace"
    check_estimate(r, N, n, trace, np.linalg.cond(covs).max())
    assert r.status in (fo.Status.CLOSED_FORM, fo.Status.OPTIMAL) and r.backend is None
    sym = 0.5 * (covs + np.swapaxes(covs, -1, -2))
    cond = np.linalg.cond(sym)  # (N,): the rules' rounding grows with it
    if method in ("naive", "known-cross", "ei"):  # never larger than a node: P <= P_i
        for P in sym:
            top = np.linalg.norm(P, 2)
            low = np.linalg.eigvalsh((P - r.cov) / top).min()
            assert low >= -64 * n * EPS * cond.max(), (method, low)
    if method == "ici":  # w = 0 and 1 give the nodes: never worse than the better one
        best = min(cov_objective(P, trace)[0] for P in sym)
        assert r.objective <= best + 64 * n * EPS * cond.max() * max(abs(best), 1.0)
    if method == "fast-ci":  # w_i proportional to 1 / tr P_i
        wt = r.weights * np.trace(sym, axis1=1, axis2=2)
        assert np.ptp(wt) <= 8 * n * EPS * wt.max()


def _draw(rng, kinds=("random", "ill-conditioned", "diagonal", "near-identical", "commuting"),
          ns=(1, 2, 3, 4, 6), Ns=(2, 3, 5, 8)):
    """(kind, N, n, means, covs): a problem with nodes spread up to 1e32 around a base
    scale between 1e-300 and 1e300 (the largest entry at most 1e300)."""
    kind = str(rng.choice(kinds))
    N, n = int(rng.choice(Ns)), int(rng.choice(ns))
    log10_cond = float(rng.uniform(0, 12)) if kind != "random" else 0.0
    spread = float(rng.choice([0.0, 4.0, 16.0, 32.0]))
    top = 300 - log10_cond - spread / 2 - 1
    base = float(rng.uniform(-300 + spread / 2 + 2, top))
    covs = extreme_instance(rng, N, n, kind, log10_cond=log10_cond, base=base, spread=spread)
    means = rng.standard_normal((N, n)) * 10.0 ** rng.uniform(-100, 100)
    return kind, N, n, means, covs


# --- the CI family ----------------------------------------------------------------------

@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("count", [60, pytest.param(200, marks=pytest.mark.slow)])
def test_ci_family_on_extreme_inputs(criterion, count):
    """bci with newton (closed-form and ci too for N = 2), checked against `Exact`: 60
    problems per criterion in the default run, 200 more in the slow one."""
    rng = np.random.default_rng([90, len(criterion), count])
    for _ in range(count):
        kind, N, n, means, covs = _draw(rng)
        check_ci(fo.bci(means, covs, criterion), means, covs, criterion)
        if N == 2:
            r = fo.ci(means[0], covs[0], means[1], covs[1], criterion, "closed-form")
            check_ci(r, means, covs, criterion)


@pytest.mark.parametrize("backend", ["clarabel-direct", "slsqp", "clarabel", "scs"])
def test_other_backends_on_extreme_inputs(backend):
    """The conic and SLSQP backends, polished, on a few hard problems of one shape each
    (test_campaign.py solves hundreds)."""
    rng = np.random.default_rng([91, len(backend)])
    checked = 0
    for i in range(10):
        kind, N, n, means, covs = _draw(rng, ns=(3,), Ns=(3,))
        criterion = CRITERIA[i % 2]
        try:
            r = fo.bci(means, covs, criterion, backend)
        except fo.FusionSolverError as exc:  # allowed, with a message naming the backend
            assert backend in str(exc)
            continue
        check_ci(r, means, covs, criterion)
        checked += 1
    assert checked >= 8  # a backend that fails everywhere is not "checked" (0 of 40 fail)


def test_near_identical_nodes_at_condition_1e12():
    """Items 3 and 9: the hardest family for a certificate; no claim of an improvement over
    the best node that exact arithmetic does not confirm."""
    rng = np.random.default_rng(92)
    for i in range(100):
        N, n = int(rng.choice([2, 3, 5, 8])), int(rng.choice([2, 3, 4, 6]))
        covs = extreme_instance(rng, N, n, "near-identical", base=rng.uniform(-200, 200))
        means = rng.standard_normal((N, n))
        criterion = CRITERIA[i % 2]
        check_ci(fo.bci(means, covs, criterion), means, covs, criterion)


def test_denormal_and_largest_covariances():
    """Covariances 1e-310 (denormal) and near 1e300, every method and both criteria: a
    result or a named error, never NaN."""
    rng = np.random.default_rng(93)
    results = []
    for base in (-310.0, -305.0, 290.0, 299.0):
        for N in (2, 3):
            n = 3
            covs = extreme_instance(rng, N, n, "random", base=base)
            means = rng.standard_normal((N, n))
            for criterion in CRITERIA:
                for method in fo.core.METHODS:
                    if method in fo.core.PAIR_METHODS and N != 2:
                        continue
                    results.append(_fuse_checked(method, means, covs, criterion, rng))
    _most_checked(results)


def _most_checked(results: list) -> None:
    """At least 90 % of `_fuse_checked`'s calls gave a result it checked, not an allowed
    refusal (an overflow): a fusion that refused everything would otherwise pass."""
    assert sum(r is not None for r in results) >= 0.9 * len(results), results


def test_the_issues_reproducers():
    """Issue 9's own inputs (items 1, 4, 5, 6), through the checks above, against their
    independent expectations."""
    rng = np.random.default_rng(104)
    # item 1: a pair 1e16 apart in a batch: the better node as it is
    covs = np.array([[1e8 * np.eye(2), np.diag([1e-8, 1e-11])]])
    r = fo.fuse_batch(np.zeros((1, 2, 2)), covs)
    np.testing.assert_array_equal(r.cov[0].diagonal(), [1e-8, 1e-11])
    # item 4: EI with nearly equal eigen-directions gives node b exactly (closed form)
    T = np.array([[1.0, 0.3], [0.2, 1.0]])
    P_b, P_a = T @ T.T, T @ np.diag([1 + 1e-9, 3.0]) @ T.T
    m = np.array([[1.0, -1.0], [-0.5, 2.0]])
    r = fo.fuse(m, np.stack([P_a, P_b]), method="ei")
    np.testing.assert_allclose(r.mean, m[1], rtol=1e-12)
    np.testing.assert_allclose(r.cov, P_b, rtol=1e-12)
    # item 5: ICI with nodes 1e16 and 1e17 apart
    for s in (1e16, 1e17):
        covs = np.stack([s * np.array([[2.0, 1.0], [1.0, 2.0]]), np.diag([1.0, 3.0])])
        for criterion in CRITERIA:
            _fuse_checked("ici", np.zeros((2, 2)), covs, criterion, rng)
    # item 6: determinants that overflow, denormal covariances, everywhere
    for n, scale in ((12, 1e-30), (2, 1e200), (3, 1e-310)):
        covs = np.stack([scale * np.eye(n), 2 * scale * np.eye(n)])
        for method in fo.core.METHODS:
            for criterion in CRITERIA:
                _fuse_checked(method, np.zeros((2, n)), covs, criterion, rng)
    covs = np.stack([1e-310 * np.eye(3)] * 3)
    assert fo.optimality_gap(covs, [0.5, 0.25, 0.25]) == 0.0
    r = fo.fuse_batch(np.zeros((2, 3, 3)), np.stack([covs, 3 * covs]))
    np.testing.assert_allclose(r.cov, [covs[0], 3 * covs[0]], rtol=1e-12)


def _fuse_checked(method, means, covs, criterion, rng):
    """fo.fuse with `method` (its arguments drawn), checked; a FusionInputError or
    FusionSolverError is allowed only where the result cannot be represented in double
    precision, and must say so ("overflows", "range")."""
    N = len(covs)
    args, scales = {}, None
    if method == "mbci":
        p, chi = rng.uniform(0, 1, N), 10.0 ** -rng.uniform(0, 3, N)
        args, scales = {"p_detect": p, "chi": chi}, exact_scales(p, chi, N)
    if method == "known-cross":
        args = {"cross": joint(rng, covs, rng.uniform(0, 0.9))}
    try:
        r = fo.fuse(means, covs, method, criterion, **args)
    except (fo.FusionInputError, fo.FusionSolverError) as exc:
        assert "overflow" in str(exc) or "range" in str(exc), str(exc)
        return None
    if method in fo.core.CI_METHODS:
        check_ci(r, means, covs, criterion, scales)
    else:
        check_rule(r, means, covs, method, criterion)
    return r


@pytest.mark.parametrize("criterion", CRITERIA)
def test_every_method_on_extreme_inputs(criterion):
    """Every method of fuse on the extreme problems of `_draw` (scales 1e-300..1e300,
    conditions to 1e12, nodes up to 1e32 apart)."""
    rng = np.random.default_rng([94, len(criterion)])
    results = []
    for _ in range(30):
        kind, N, n, means, covs = _draw(rng, Ns=(2, 3, 4))
        for method in fo.core.METHODS:
            if method in fo.core.PAIR_METHODS and N != 2:
                continue
            results.append(_fuse_checked(method, means, covs, criterion, rng))
    _most_checked(results)


def test_mbci_with_extreme_detection():
    """p = 0, chi down to 1e-300 (scales far below the float range: the product
    underflows), growth to 1e300, p = 1: against the scales computed in Decimal."""
    rng = np.random.default_rng(95)
    cases = [(0.0, 1e-200), (0.0, 1e-300), (1.0, 1e-300), (0.0, 1.0), (0.5, 5e-324),
             ([0.0, 1.0, 0.3], [1e-300, 1e-10, 1.0]), ([0.0, 0.0, 0.0], [1e-150, 1e-1, 1e-5]),
             (0.0, 1e-100), ([0.0, 0.0, 1.0], [1e-100, 1e-120, 1e-300])]
    for criterion in CRITERIA:
        batch = []
        for p, chi in cases:
            covs = extreme_instance(rng, 3, 2, "random", base=rng.uniform(-100, 100))
            means = rng.standard_normal((3, 2))
            scales = exact_scales(p, chi, 3)
            try:
                r = fo.mbci(means, covs, p, chi, criterion)
            except fo.FusionInputError as exc:  # only where the result cannot be represented
                assert "overflows" in str(exc)
                big = Decimal(float(np.abs(covs).max())) / min(scales)
                assert big > Decimal("1e280"), (p, chi, float(big))
                continue
            check_ci(r, means, covs, criterion, scales)
            batch.append((means, covs, np.broadcast_to(p, 3), np.broadcast_to(chi, 3), r))
            with np.errstate(divide="ignore", over="ignore"):
                growth = 1.0 / np.asarray(chi)
            if np.isfinite(growth).all():
                g = fo.mbci(means, covs, p, growth=growth, criterion=criterion)
                np.testing.assert_allclose(g.cov, r.cov, rtol=1e-13)
        # the same problems in one fuse_batch, with (B, N) p_detect and chi
        means, covs, p, chi, rs = (np.stack(x) if i < 4 else x
                                   for i, x in enumerate(zip(*batch, strict=True)))
        rb = fo.fuse_batch(means, covs, "mbci", criterion, p_detect=p, chi=chi)
        for b, r in enumerate(rs):
            np.testing.assert_array_equal(rb.cov[b], r.cov)
            np.testing.assert_array_equal(rb.weights[b], r.weights)


@pytest.mark.slow
def test_many_nodes_with_newton():
    """N up to 3000 (the SQP's support has at most n(n+1)/2 + 1 nodes whatever N), each
    result checked against exact arithmetic (`check_ci`)."""
    rng = np.random.default_rng(96)
    for N, n, kind in [(3000, 2, "random"), (1000, 2, "diagonal"), (600, 3, "ill-conditioned"),
                       (300, 2, "near-identical")]:
        covs = extreme_instance(rng, N, n, kind, base=rng.uniform(-50, 50), spread=4.0)
        means = rng.standard_normal((N, n))
        for criterion in CRITERIA:
            r = fo.bci(means, covs, criterion)
            check_ci(r, means, covs, criterion)  # the certificate in 60 digits, all N nodes
            assert r.status == fo.Status.OPTIMAL or (r.weights == 1).any()


def test_large_dimension():
    """n = 50 with newton, against numpy on the well-conditioned "random" kind: objective
    and certificate from inverted informations (condition <= 1e3 there)."""
    rng = np.random.default_rng(97)
    for N in (3, 8):
        means, covs = random_instance(rng, 50, N)
        Ys = np.linalg.inv(covs)
        for criterion in CRITERIA:
            r = fo.bci(means, covs, criterion)
            check_estimate(r, N, 50, criterion == "trace")
            P = np.linalg.inv(np.einsum("i,ijk->jk", r.weights, Ys))
            if criterion == "trace":
                f, g = np.trace(P), -np.einsum("ab,ibc,ca->i", P, Ys, P)
            else:
                f, g = np.linalg.slogdet(P)[1], -np.einsum("ab,iba->i", P, Ys)
            assert r.objective == pytest.approx(f, rel=1e-11)
            rel = (g @ r.weights - g.min()) / (abs(f) if criterion == "trace" else 1.0)
            assert r.status == fo.Status.OPTIMAL and rel <= 2 * OPTIMAL_RTOL


def test_n_200_newton_solves_and_conic_backends_refuse_before_allocating(monkeypatch):
    """Item 7: n = 200, N = 3 with newton (test_campaign.py's docstring has the timing),
    while Clarabel's KKT system (about 100 GB) is refused with the backend, n and the
    estimate named; the limit is settable."""
    rng = np.random.default_rng(103)
    means, covs = random_instance(rng, 200, 3)
    r = fo.bci(means, covs, "trace")
    check_estimate(r, 3, 200, True)
    assert r.status == fo.Status.OPTIMAL
    for backend in ("clarabel", "clarabel-direct"):
        with pytest.raises(fo.FusionSolverError, match=rf"'{backend}'.*n = 200.*GiB"):
            fo.bci(means, covs, "trace", backend)
    monkeypatch.setattr(fo.limits, "conic_memory", fo.limits.conic_memory)
    fo.limits.conic_memory = 1e4  # n = 6, N = 3 needs about 1e5 bytes
    with pytest.raises(fo.FusionSolverError, match=r"n = 6.*conic_memory"):
        fo.bci(*random_instance(rng, 6, 3), backend="clarabel-direct")


# --- fuse_batch -------------------------------------------------------------------------

@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("method", ["bci", "ci", "mbci", "naive", "fast-ci", "ifci", "ici",
                                    "ei", "known-cross"])
def test_fuse_batch_equals_fuse_bit_for_bit(method, criterion):
    """Problems of every kind and scale in one batch, each equal to its own fuse."""
    rng = np.random.default_rng([98, len(method), len(criterion)])
    N = 2 if method in fo.core.PAIR_METHODS else 3
    B, n = 8, 3
    covs = np.stack([_draw(rng, ns=(n,), Ns=(N,))[4] for _ in range(B)])
    means = rng.standard_normal((B, N, n))
    args = {}
    if method == "mbci":
        args = {"p_detect": rng.uniform(0, 1, (B, N)), "chi": rng.uniform(0.1, 1, (B, N))}
    if method == "known-cross":
        args = {"cross": np.stack([joint(rng, c, rng.uniform(0, 0.9)) for c in covs])}
    try:
        r = fo.fuse_batch(means, covs, method, criterion, **args)
    except (fo.FusionInputError, fo.FusionSolverError):
        r = None  # then some problem fails alone too
    failed = 0
    for b in range(B):
        one = {k: v[b] for k, v in args.items()}
        try:
            q = fo.fuse(means[b], covs[b], method, criterion, **one)
        except (fo.FusionInputError, fo.FusionSolverError):
            failed += 1
            continue
        assert r is not None
        for name in ("weights", "mean", "cov"):
            np.testing.assert_array_equal(getattr(r, name)[b], getattr(q, name))
        assert (r.objective[b], r.gap[b], r.status[b]) == (q.objective, q.gap, q.status)
    assert (r is None) == (failed > 0)
    assert failed <= 2, failed  # most problems compared (0 of 144 fail alone)


def test_fuse_batch_of_one_node_returns_the_input():
    rng = np.random.default_rng(99)
    covs = np.stack([extreme_instance(rng, 1, 4, k, base=rng.uniform(-300, 280))[0]
                     for k in ("random", "ill-conditioned", "diagonal", "commuting")])[:, None]
    means = rng.standard_normal((4, 1, 4)) * 1e200
    for criterion in CRITERIA:
        r = fo.fuse_batch(means, covs, "bci", criterion)
        np.testing.assert_array_equal(r.cov, covs[:, 0])
        np.testing.assert_array_equal(r.mean, means[:, 0])
        assert (r.weights == 1).all()


# --- the exact reference itself ---------------------------------------------------------

def test_exact_reference_is_converged():
    """80 digits agree with 120 on hard problems, so the reference's own rounding is far
    below every tolerance above."""
    rng = np.random.default_rng(100)
    for kind in ("ill-conditioned", "near-identical", "commuting"):
        covs = extreme_instance(rng, 4, 4, kind, spread=16.0)
        w = rng.dirichlet(np.ones(4))
        for trace in (True, False):
            f1, c1 = Exact(covs).at(w, trace)
            f2, c2 = Exact(covs, digits=120).at(w, trace)
            assert abs(f1 - f2) <= Decimal("1e-40") * abs(f2)
            assert abs(c1 - c2) <= Decimal("1e-30")


def test_exact_reference_matches_numpy_where_numpy_is_accurate():
    rng = np.random.default_rng(101)
    means, covs = random_instance(rng, 3, 4)
    w = rng.dirichlet(np.ones(4))
    Ys = np.linalg.inv(covs)
    P = np.linalg.inv(np.einsum("i,ijk->jk", w, Ys))
    g = -np.einsum("ab,ibc,ca->i", P, Ys, P)
    f, rel = Exact(covs).at(w, True)
    assert float(f) == pytest.approx(np.trace(P), rel=1e-13)
    assert float(rel) == pytest.approx((g @ w - g.min()) / np.trace(P), rel=1e-9)
    f, _ = Exact(covs).at(w, False)
    assert float(f) == pytest.approx(np.linalg.slogdet(P)[1], rel=1e-13)


# --- bad inputs -------------------------------------------------------------------------

M3, C3 = random_instance(np.random.default_rng(102), 2, 3)
M2, C2 = M3[:2], C3[:2]
EST = fo.Estimates(M3[:1], C3[:1], [0], 0.0, "a")

BAD = [  # (id, call, the argument the message must name)
    ("means str", lambda: fo.bci("abc", C3), "means"),
    ("covs str", lambda: fo.bci(M3, "1.0"), "covs"),
    ("means numeric str", lambda: fo.bci(M3.astype(str), C3), "means"),
    ("covs numeric str", lambda: fo.bci(M3, C3.astype(str)), "covs"),
    ("means ragged", lambda: fo.bci([[0.0, 1.0], [0.0]], C3), "means"),
    ("covs ragged", lambda: fo.bci(M3, [np.eye(2), np.eye(3), np.eye(2)]), "covs"),
    ("means dict", lambda: fo.bci({"a": 1.0}, C3), "means"),
    ("covs dict", lambda: fo.bci(M3, {"a": C3}), "covs"),
    ("means complex", lambda: fo.bci(M3 + 0j, C3), "means"),
    ("covs complex", lambda: fo.bci(M3, C3 + 0j), "covs"),
    ("means bool", lambda: fo.bci(M3 > 0, C3), "means"),
    ("covs bool", lambda: fo.bci(M3, C3 > 0), "covs"),
    ("means object", lambda: fo.bci(np.array([[None, 1.0]] * 3), C3), "means"),
    ("ci P_a dict", lambda: fo.ci(M2[0], {"x": 1}, M2[1], C2[1]), "P_a"),
    ("ci m_a str", lambda: fo.ci("ab", C2[0], M2[1], C2[1]), "m_a"),
    ("ci P_b ragged", lambda: fo.ci(M2[0], C2[0], M2[1], [[1.0, 0.0], [0.0]]), "P_b"),
    ("ci m_b complex", lambda: fo.ci(M2[0], C2[0], M2[1] + 1j, C2[1]), "m_b"),
    ("ci P_b not PD", lambda: fo.ci(M2[0], C2[0], M2[1], -C2[1]), "P_b"),
    ("ci m_a nan", lambda: fo.ci(M2[0] * np.nan, C2[0], M2[1], C2[1]), "m_a"),
    ("gap covs str", lambda: fo.optimality_gap("abc", [1.0]), "covs"),
    ("gap covs ragged", lambda: fo.optimality_gap([np.eye(2), np.eye(3)], [0.5, 0.5]),
     "covs"),
    ("gap weights str", lambda: fo.optimality_gap(C3, "abc"), "weights"),
    ("gap weights dict", lambda: fo.optimality_gap(C3, {"a": 1}), "weights"),
    ("gap weights bool", lambda: fo.optimality_gap(C3, [True, False, False]), "weights"),
    ("gap weights shape", lambda: fo.optimality_gap(C3, [0.5, 0.5]), "weights"),
    ("gap weights nan", lambda: fo.optimality_gap(C3, [np.nan, 0.5, 0.5]), "weights"),
    ("gap criterion", lambda: fo.optimality_gap(C3, [1 / 3] * 3, "det"), "criterion"),
    ("gap covs not PD", lambda: fo.optimality_gap(-C3, [1 / 3] * 3), "covs"),
    ("cross str", lambda: fo.fuse(M3, C3, "known-cross", cross="x"), "cross"),
    ("cross shape", lambda: fo.fuse(M3, C3, "known-cross", cross=np.eye(3)), "cross"),
    ("cross missing", lambda: fo.fuse(M3, C3, "known-cross"), "cross"),
    ("cross complex", lambda: fo.fuse(M3, C3, "known-cross",
                                      cross=np.zeros((3, 3, 2, 2), complex)), "cross"),
    ("cross not PD", lambda: fo.fuse(M2, C2, "known-cross",
                                     cross=_cross_with(C2, 10.0)), "cross"),
    ("batch cross wrong B", lambda: fo.fuse_batch(M2[None], C2[None], "known-cross",
                                                  cross=np.zeros((2, 2, 2, 2, 2))), "cross"),
    ("batch cross unbatched", lambda: fo.fuse_batch(M2[None], C2[None], "known-cross",
                                                    cross=_cross_with(C2, 0.1)), "cross"),
    ("mbci p 2-D", lambda: fo.mbci(M3, C3, np.full((2, 3), 0.5), 0.9), "p_detect"),
    ("mbci chi 2-D", lambda: fo.mbci(M3, C3, 0.5, np.full((2, 3), 0.9)), "chi"),
    ("mbci p str", lambda: fo.mbci(M3, C3, "0.5", 0.9), "p_detect"),
    ("mbci chi complex", lambda: fo.mbci(M3, C3, 0.5, 0.9 + 0j), "chi"),
    ("mbci growth bool", lambda: fo.mbci(M3, C3, 0.5, growth=True), "growth"),
    ("mbci p > 1", lambda: fo.mbci(M3, C3, [0.5, 1.5, 0.5], 0.9), "p_detect"),
    ("mbci chi 0", lambda: fo.mbci(M3, C3, 0.5, 0.0), "chi"),
    ("mbci growth < 1", lambda: fo.mbci(M3, C3, 0.5, growth=0.5), "growth"),
    ("mbci p nan", lambda: fo.mbci(M3, C3, np.nan, 0.5), "p_detect"),
    ("mbci no chi", lambda: fo.mbci(M3, C3, 0.5), "chi"),
    ("batch p wrong B", lambda: fo.fuse_batch(M3[None], C3[None], "mbci",
                                              p_detect=np.full((2, 3), 0.5), chi=0.9),
     "p_detect"),
    ("backend list", lambda: fo.bci(M3, C3, backend=["newton"]), "backend"),
    ("backend array", lambda: fo.bci(M3, C3, backend=np.array("newton")), "backend"),
    ("backend unknown", lambda: fo.bci(M3, C3, backend="gurobi"), "backend"),
    ("backend for a rule", lambda: fo.fuse(M3, C3, "naive", backend="newton"), "backend"),
    ("method list", lambda: fo.fuse(M3, C3, method=["bci"]), "method"),
    ("method unknown", lambda: fo.fuse(M3, C3, method="magic"), "method"),
    ("criterion list", lambda: fo.bci(M3, C3, criterion=["trace"]), "criterion"),
    ("criterion array", lambda: fo.bci(M3, C3, criterion=np.array("trace")), "criterion"),
    ("criterion None", lambda: fo.bci(M3, C3, criterion=None), "criterion"),
    ("polish str", lambda: fo.bci(M3, C3, polish="yes"), "polish"),
    ("stray chi for bci", lambda: fo.fuse(M3, C3, "bci", chi=0.5), "chi"),
    ("stray p for a rule", lambda: fo.fuse(M3, C3, "naive", p_detect=0.5), "p_detect"),
    ("stray cross", lambda: fo.fuse(M3, C3, "fast-ci", cross=np.zeros(3)), "cross"),
    ("stray keyword", lambda: fo.fuse(M3, C3, "ifci", weights=[1, 0, 0]), "weights"),
    ("batch stray", lambda: fo.fuse_batch(M3[None], C3[None], "ei", chi=0.5), "chi"),
    ("scales n_nodes -1", lambda: fo.detection_scales(0.5, 0.9, n_nodes=-1), "n_nodes"),
    ("scales n_nodes 1.5", lambda: fo.detection_scales(0.5, 0.9, n_nodes=1.5), "n_nodes"),
    ("scales n_nodes str", lambda: fo.detection_scales(0.5, 0.9, n_nodes="3"), "n_nodes"),
    ("scales n_nodes 1e12", lambda: fo.detection_scales(0.5, 0.9, n_nodes=10**12), "n_nodes"),
    ("scales n_nodes bool", lambda: fo.detection_scales(0.5, 0.9, n_nodes=True), "n_nodes"),
    ("scales p str", lambda: fo.detection_scales("0.5", 0.9), "p_detect"),
    ("scales chi dict", lambda: fo.detection_scales(0.5, {"a": 1}), "chi"),
    ("associate threshold str", lambda: fo.associate({"a": EST}, "2"), "threshold"),
    ("associate threshold nan", lambda: fo.associate({"a": EST}, np.nan), "threshold"),
    ("associate threshold array", lambda: fo.associate({"a": EST}, np.array([1.0])),
     "threshold"),
    ("associate dims out of range", lambda: fo.associate({"a": EST}, 1.0, dims=[0, 3]),
     "dims"),
    ("associate dims negative", lambda: fo.associate({"a": EST}, 1.0, dims=[-1]), "dims"),
    ("associate dims float", lambda: fo.associate({"a": EST}, 1.0, dims=[0.5]), "dims"),
    ("associate dims str", lambda: fo.associate({"a": EST}, 1.0, dims="01"), "dims"),
    ("associate different n", lambda: fo.associate(
        {"a": EST, "b": fo.Estimates(M2[:1, :1], C2[:1, :1, :1], [0], 0.0, "b")}, 1.0),
     "dimension"),
    ("associate method", lambda: fo.associate({"a": EST}, 1.0, method=["nearest"]),
     "method"),
    ("warmup n", lambda: fo.warmup(1.5, 3), "n must be an integer"),
    # numbers past the float range (10**400), which crashed np.isfinite with a TypeError
    ("associate threshold 1e400", lambda: fo.associate({"a": EST}, 10**400), "threshold"),
    ("node threshold 1e400", lambda: fo.ProcessingNode(["a"], method="bci",
                                                       threshold=10**400), "threshold"),
    ("node growth 1e400", lambda: fo.ProcessingNode(["a"], threshold=1.0, p_detect={"a": 1},
                                                    growth=10**400), "growth"),
    ("node chi 1e20", lambda: fo.ProcessingNode(["a"], threshold=1.0, p_detect={"a": 1},
                                                chi=10**20), "chi"),
    ("node p 1e400", lambda: fo.ProcessingNode(["a"], threshold=1.0, p_detect={"a": 10**400},
                                               chi=0.5), "p_detect"),
    ("estimates time 1e400", lambda: fo.Estimates(M2, C2, time=10**400), "time"),
    ("network time 1e400", lambda: fo.Network({}, {}).step({}, time=10**400), "time"),
    # memory, refused before the copies are made
    ("empty n 1e12", lambda: fo.Estimates.empty(10**12), "n = 1000000000000"),
    ("estimates over memory", lambda: fo.Estimates(np.broadcast_to(np.zeros(8), (10**7, 8)),
                                                   np.broadcast_to(np.eye(8), (10**7, 8, 8))),
     "means"),
    ("batch means 2-D", lambda: fo.fuse_batch(M3, C3), "means"),
    ("batch covs mismatch", lambda: fo.fuse_batch(M3[None], C3[None, :2]), "covs"),
    ("batch empty", lambda: fo.fuse_batch(np.zeros((0, 2, 2)), np.zeros((0, 2, 2, 2))),
     "B = 0"),
]


def _cross_with(covs, c):
    """cross (2, 2, n, n) with off-diagonal blocks c I (PSD only for small c)."""
    n = covs.shape[1]
    return np.array([[covs[0], c * np.eye(n)], [c * np.eye(n), covs[1]]])


@pytest.mark.parametrize("call,name", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input_raises_an_error_naming_the_argument(call, name):
    with pytest.raises(fo.FusionInputError) as err:
        call()
    assert name in str(err.value), str(err.value)


# --- regressions of defects this fuzz found ---------------------------------------------

_HUGE = -10**5000  # its repr raises ValueError (Python's 4,300-digit limit)


@pytest.mark.parametrize("value", [_HUGE, [_HUGE], (1, _HUGE), {"a": _HUGE}],
                         ids=["int", "list", "tuple", "dict"])
def test_an_option_holding_an_int_of_5001_digits_is_refused_by_name(value):
    """Fuzz T4: the refusal of such an option showed it with repr(), which raised
    ValueError ("Exceeds the limit (4300 digits)") in place of the refusal, for a criterion,
    backend, method, polish, threshold, dims, a lost link's name, min_sources, a count
    and more; every refusal shows a value through `validation.safe_repr` now."""
    from trackers import _checks, metrics

    M, C = np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1))
    e = fo.Estimates(M, C)
    calls = [lambda: fo.bci(M, C, value), lambda: fo.bci(M, C, "trace", value),
             lambda: fo.bci(M, C, polish=value), lambda: fo.fuse(M, C, value),
             lambda: fo.fuse(M, C, "bci", extra=value), lambda: fo.warmup(value, 2),
             lambda: fo.Estimates(M, C, time=value), lambda: fo.associate({"a": e}, value),
             lambda: fo.associate({"a": e}, 1.0, value),
             lambda: fo.associate({"a": e}, 1.0, dims=value),
             lambda: fo.ProcessingNode(["a"], threshold=value),
             lambda: fo.ProcessingNode(["a"], threshold=1.0, method=value),
             lambda: fo.ProcessingNode(["a", "b"], threshold=1.0, min_sources=value),
             lambda: fo.Network({}, {}).step({}, lost=value),
             lambda: metrics.mse(M, M, value), lambda: metrics.id_switches([[value]]),
             lambda: _checks.positive_int("n", value), lambda: _checks.boolean("x", value)]
    for call in calls:
        with pytest.raises(fo.FusionInputError) as err:
            call()
        assert "4300" not in str(err.value)


def test_names_and_counts_of_5001_digits_are_refused_by_name(tmp_path):
    """Fuzz T4, a helper's sweep of 3,100 calls: names (any hashable: here an int of 5,001
    digits) and counts shown with str() in refusals of processing nodes, networks,
    detection scales, Estimates.empty, the trackers' particle counts, the scenarios' step
    counts and the memory limits' messages raised ValueError or OverflowError instead."""
    from studies import config as configs
    from trackers import rbpf, scenarios

    big, M, C = 10**5000, np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1))
    e2, e3 = fo.Estimates(M, C), fo.Estimates(np.zeros((1, 3)), np.eye(3)[None])
    node = fo.ProcessingNode([big, "b"], threshold=1.0, method="bci")
    model = scenarios.Table1Config().filter_model()
    calls = [lambda: fo.detection_scales(0.9, 0.5, n_nodes=big), lambda: fo.Estimates.empty(big),
             lambda: fo.associate({big: e2, "b": e3}, 1.0),
             lambda: fo.ProcessingNode([big, big], threshold=1.0, method="bci"),
             lambda: fo.ProcessingNode(["a"], threshold=1.0, p_detect={"a": 0.9, big: 0.8},
                                       growth=1.1),
             lambda: node.step({big: e2, "c": e2}), lambda: node.step({big: e2, "b": e3}),
             lambda: fo.Network({big: None}, {}),
             lambda: rbpf.RBPF(model, np.zeros(model.n), np.eye(model.n),
                               rng=np.random.default_rng(0), n_particles=big),
             lambda: scenarios.Table1Config(n_steps=big),
             lambda: scenarios.CrossingConfig(n_steps=big),
             lambda: scenarios.CrossingConfig(n_targets=big)]
    for call in calls:
        with pytest.raises(fo.FusionInputError) as err:
            call()
        assert "4300" not in str(err.value)
    with pytest.raises(fo.FusionSolverError, match="an integer of about 5001 digits"):
        fo.warmup(2, big)
    path = tmp_path / "c.toml"
    path.write_text("runs = 1" + "0" * 5000 + "\n")
    with pytest.raises(configs.ConfigError, match="an integer of more than 4,300 digits"):
        configs.load("table1", path=path)


def test_network_numbers_of_any_real_type_are_read_as_floats():
    """A Fraction or a Python int past 2**63 crashed np.isfinite in the network's checks
    (a TypeError naming nothing), and `associate` handed a float16 or longdouble threshold
    on to its "assignment" raw (overflow, or a cast error in scipy) (fuzz, 2026-11-26)."""
    from fractions import Fraction

    near = fo.Estimates([[0.0, 0.0]], [np.eye(2)])
    far = fo.Estimates([[100.0, 0.0]], [np.eye(2)])
    apart, together = [("a",), ("b",)], [("a", "b")]
    for threshold, expected in ((np.float16(1.0), apart), (np.longdouble(1.0), apart),
                                (Fraction(1), apart), (1, apart), (10**20, together)):
        for method in ("nearest", "assignment"):
            groups = fo.associate({"a": near, "b": far}, threshold, method)
            assert sorted(g.sources for g in groups) == expected
    node = fo.ProcessingNode(["a", "b"], threshold=10**20, growth=10**20,
                             p_detect={"a": Fraction(1, 2), "b": np.float16(0.5)})
    assert (node.threshold, node.chi, node.p_detect) == (1e20, 1e-20, {"a": 0.5, "b": 0.5})
    assert fo.Estimates([[0.0]], [[[1.0]]], time=Fraction(1, 3)).time == 1 / 3
    assert node.step({"a": near}, time=Fraction(1, 2)).time == 0.5


def _ill_batch_4_3():
    """The (n, N) = (4, 3) "ill-conditioned" batch of 10^5 problems of issue 9, item 2."""
    rng = np.random.default_rng([4, 3, len("ill-conditioned")])
    return instance(rng, 300_000, 4, "ill-conditioned").reshape(100_000, 3, 4, 4)


def _native(covs, criterion="trace"):
    """The compiled solver alone (no rescue): relative certificates (B,) of covs
    (B, N, n, n)."""
    means = np.zeros(covs.shape[:-1])
    a = fo.core._Arrays(*means.shape)
    q, E = fo.core._unit_scales(*means.shape[:2])
    fo.core.fuse_exact(means, covs, q, E, criterion == "trace", a.F, a.k, a.vertex, a.pnorm,
                       a.where, a.W, a.rel, a.iters, a.mean, a.cov, a.stats)
    return a.rel


# Problems of that batch on which the SQP's line search stalled above the tolerance (near
# the optimum a Newton step's decrease of f is below f's rounding) and the Clarabel rescue
# did not help: all 27 came back "optimal_inaccurate" (relative certificates 2e-10 to
# 4e-7) where SCS-polished weights reach 1e-13.
STALLED_TRACE = [6961, 7781, 9701, 14890, 23266, 27052, 32275, 33955, 40958, 43245, 44217,
                 44283, 51447, 51650, 53975, 57660, 58280, 59010, 60779, 61715, 63862,
                 63996, 65914, 73083, 93426, 98731, 99784]


def test_sqp_takes_newton_steps_below_the_rounding_of_f():
    """Issue 9, item 2 (defect 1 of this fuzz): the native solver alone certifies all 27,
    and fuse_batch returns them optimal."""
    covs = _ill_batch_4_3()[STALLED_TRACE]
    assert _native(covs).max() <= OPTIMAL_RTOL
    r = fo.fuse_batch(np.zeros(covs.shape[:-1]), covs, "bci", "trace")
    assert (r.status == fo.Status.OPTIMAL).all()


def test_sqp_does_not_count_a_change_of_support_as_a_stall():
    """Defect 2: problem 49946 of that batch reached 2.4e-5, dropped a node (its
    certificate jumped to 2.2 on the new support) and was stopped as stalled after 5 steps
    that were converging (2.2, 0.82, 0.25, 0.046, 2e-3); the native solver left it at
    2.4e-5 (Clarabel's rescue saved it)."""
    covs = _ill_batch_4_3()[[49946]]
    assert _native(covs).max() <= OPTIMAL_RTOL


# Diagonal nodes 1e21 to 1e45 (defect 3): the fused trace is 1e-12 of the nodes' middle
# scale, so the SQP's nearest-point vectors (of the size of sqrt(f)) were 1e-6 against
# the simplex row of ones, the rank test dropped their difference, and the SQP stalled at
# a relative certificate of 1.9e-10 (also from Clarabel's weights; SCS's reach 5e-13).
TINY_TRACE_DIAGONALS = [
    [3.4810666273027294e+32, 1.383433027272479e+36, 5.986648167961592e+25],
    [1.9032917657445112e+29, 1.4063864315103094e+23, 2.1411521691620387e+28],
    [3.639845717935357e+30, 8.099659963010202e+36, 1.9691676834959466e+31],
    [1.8000709408699725e+38, 1.7245610679267532e+38, 2.9574840965544907e+32],
    [2.1984257260381175e+23, 1.2850615182158286e+28, 8.845235522907547e+21],
    [1.8952203459514186e+45, 1.0082917356906707e+39, 2.306276137827247e+38],
    [2.3235968975860787e+25, 1.7779082189222459e+27, 1.2976528955908442e+23],
    [2.4669482487544182e+41, 1.137063694757173e+43, 1.6489087865200944e+35]]


def test_sqp_nearest_point_does_not_depend_on_the_scale_of_the_trace():
    covs = np.stack([np.diag(d) for d in TINY_TRACE_DIAGONALS])
    assert _native(covs[None]).max() <= OPTIMAL_RTOL
    means = np.zeros((8, 3))
    r = fo.bci(means, covs, "trace")
    assert r.status == fo.Status.OPTIMAL
    check_ci(r, means, covs, "trace")
    for shift in (-600, -100, 100, 600):  # the same problem at other scales, exactly
        q = fo.bci(means, np.ldexp(covs, shift), "trace")
        assert q.status == fo.Status.OPTIMAL
        np.testing.assert_allclose(q.weights, r.weights, rtol=1e-9, atol=1e-12)
