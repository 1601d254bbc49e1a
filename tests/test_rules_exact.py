"""Exact references for the tests, and their own checks against numpy.

Matrices are numpy object arrays of `Fraction`s (exactly the given floats, then exact
arithmetic: no rounding, no overflow whatever the scale) or of 60-digit `Decimal`s (for the
square roots of an eigen-decomposition, 2 x 2 only, by its closed form).
"""

from decimal import Decimal, localcontext
from fractions import Fraction
from math import log

import numpy as np
import pytest
from conftest import objective

import fusion_opt as fo

DIGITS = 60


def exact(a) -> np.ndarray:
    """A float array as Fractions, exactly."""
    return np.vectorize(Fraction, otypes=[object])(np.asarray(a, dtype=float))


def decimal(a) -> np.ndarray:
    """A float array as Decimals, exactly."""
    return np.vectorize(Decimal, otypes=[object])(np.asarray(a, dtype=float))


def to_float(A) -> np.ndarray:
    """Fractions or Decimals to the nearest floats."""
    return np.vectorize(float, otypes=[float])(A)


def eye(n, one=Fraction(1)) -> np.ndarray:
    return np.array([[one if i == j else one * 0 for j in range(n)] for i in range(n)],
                    dtype=object)


def inv(A) -> np.ndarray:
    """Gauss-Jordan elimination with a nonzero pivot (exact for Fractions)."""
    n = len(A)
    M = np.concatenate([A, eye(n, A[0, 0] * 0 + 1)], axis=1)
    for c in range(n):
        p = next(r for r in range(c, n) if M[r, c] != 0)
        M[[c, p]] = M[[p, c]]
        M[c] = M[c] / M[c, c]
        for r in range(n):
            if r != c and M[r, c] != 0:
                M[r] = M[r] - M[r, c] * M[c]
    return M[:, n:]


def det(A):
    """By elimination (exact for Fractions)."""
    M, d = A.copy(), A[0, 0] * 0 + 1
    for c in range(len(M)):
        p = next((r for r in range(c, len(M)) if M[r, c] != 0), None)
        if p is None:
            return d * 0
        if p != c:
            M[[c, p]], d = M[[p, c]], -d
        d = d * M[c, c]
        for r in range(c + 1, len(M)):
            M[r] = M[r] - M[r, c] / M[c, c] * M[c]
    return d


def log_of(x: Fraction) -> float:
    """log of a positive Fraction of any size."""
    return log(x.numerator) - log(x.denominator)


def pair_objective(Ya, Yb, wa: Fraction, wb: Fraction, criterion: str):
    """The CI objective of a pair at weights (wa, wb), exactly, as a Fraction that orders
    like it: tr P(w) ("trace"), or -det Y(w) ("logdet", where f = -log det Y(w)), for
    exact informations Ya, Yb."""
    Y = wa * Ya + wb * Yb
    return sum(np.diag(inv(Y))) if criterion == "trace" else -det(Y)


def as_objective(value, criterion: str) -> float:
    """The float objective of a `pair_objective` value."""
    return float(value) if criterion == "trace" else -log_of(-value)


def pair_minimum(covs, criterion: str, steps: int = 60) -> float:
    """min over w in [0, 1] of a pair's CI objective, covs (2, n, n), by golden-section
    search on the exact objective (convex in w, compared exactly) and the two vertices:
    the bracket ends 0.618^60 = 3e-13 wide, which misses an interior minimum by at most
    f'' (3e-13)^2 / 2. Its inner points are rounded to floats (their f is still exact),
    which keeps the Fractions short (the n = 6 "trace" search took 3 s without)."""
    Ya, Yb = (inv(exact(P)) for P in covs)

    def at(w):
        return pair_objective(Ya, Yb, w, 1 - w, criterion)

    def point(x):
        return Fraction(float(x))

    ratio = Fraction((5 ** 0.5 - 1) / 2)
    a, b = Fraction(0), Fraction(1)
    c, d = point(b - ratio * (b - a)), point(a + ratio * (b - a))
    fc, fd = at(c), at(d)
    for _ in range(steps):
        if fc <= fd:
            b, d, fd = d, c, fc
            c = point(b - ratio * (b - a))
            fc = at(c)
        else:
            a, c, fc = c, d, fd
            d = point(a + ratio * (b - a))
            fd = at(d)
    return as_objective(min(fc, fd, at(Fraction(0)), at(Fraction(1))), criterion)


def eigh2(A):
    """Eigenvalues (ascending) and orthonormal eigenvectors (columns) of a symmetric 2 x 2
    Decimal matrix, by the closed form without cancellation; call inside a context of
    DIGITS digits."""
    a, b, c = A[0, 0], A[0, 1], A[1, 1]
    h, d = (a + c) / 2, (a - c) / 2
    r = (d * d + b * b).sqrt()
    if r == 0:
        return np.array([h, h], dtype=object), eye(2, Decimal(1))
    x, y = (r + d, b) if d >= 0 else (b, r - d)  # eigenvector of h + r
    norm = (x * x + y * y).sqrt()
    x, y = x / norm, y / norm
    return np.array([h - r, h + r], dtype=object), np.array([[-y, x], [x, y]], dtype=object)


def test_exact_inverse_and_determinant_match_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 2, 4):
        A = rng.standard_normal((n, n)) + n * np.eye(n)
        Ainv = inv(exact(A))
        assert (exact(A) @ Ainv == eye(n)).all()
        np.testing.assert_allclose(to_float(Ainv), np.linalg.inv(A), rtol=1e-12)
        np.testing.assert_allclose(float(det(exact(A))), np.linalg.det(A), rtol=1e-12)


def test_exact_arithmetic_has_no_range():
    A = exact(np.diag([1e300, 1e-300]))
    big = det(A @ A @ A @ A) / Fraction(1e-300) ** 4  # 1e1200
    assert big == Fraction(1e300) ** 4 and abs(log_of(big) - 1200 * log(10)) < 1e-9
    assert inv(A)[1, 1] == 1 / Fraction(1e-300) and to_float(inv(A))[1, 1] == 1 / 1e-300


def test_decimal_eigh2_matches_numpy():
    rng = np.random.default_rng(1)
    G = rng.standard_normal((5, 2, 2))
    cases = [*(G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(2)), np.diag([1.0, 2.0]),
             np.diag([2.0, 1.0]), np.array([[1.0, 1e-300], [1e-300, 1.0]])]
    for A in cases:
        with localcontext() as ctx:
            ctx.prec = DIGITS
            lam, V = eigh2(decimal(A))
            residual = decimal(A) @ V - V * lam
        np.testing.assert_allclose(to_float(lam), np.linalg.eigvalsh(A), rtol=1e-14)
        assert np.abs(to_float(residual)).max() < 1e-50
        np.testing.assert_allclose(to_float(V.T @ V), np.eye(2), atol=1e-50)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_pair_minimum_matches_a_grid_on_a_well_conditioned_pair(criterion):
    rng = np.random.default_rng(2)
    A = rng.standard_normal((2, 3, 3))
    covs = A @ np.swapaxes(A, 1, 2) + 0.5 * np.eye(3)
    grid = np.linspace(0.0, 1.0, 20_001)
    f = objective(covs, np.stack([grid, 1.0 - grid], axis=1), criterion)
    # the grid point nearest the optimum is within f'' h^2 / 8 of it (h = 5e-5)
    scale = abs(f.min()) if criterion == "trace" else 1.0
    assert abs(pair_minimum(covs, criterion) - f.min()) <= 1e-8 * scale
    # and at a vertex optimum, the vertex itself
    assert pair_minimum(np.stack([covs[0], 4 * covs[0]]), criterion) == pytest.approx(
        np.trace(covs[0]) if criterion == "trace" else np.linalg.slogdet(covs[0])[1],
        rel=1e-14)


@pytest.mark.parametrize("method, scale", [("naive", 0.5), ("fast-ci", 1.0), ("ifci", 1.0)])
def test_ci_formula_rules_keep_their_accuracy_at_condition_1e12(method, scale):
    """Regression: naive, fast-ci and ifci inverted each covariance, which at condition
    1e12 lost 1.7e-5 of the fused covariance (the mean came back as [2.00002, 0.50004]).
    Two copies of one node P: in exact arithmetic naive gives P / 2 and the CI rules P,
    the mean the average; now within eps sqrt(cond), as the compiled path."""
    c, s = np.cos(0.5), np.sin(0.5)
    rot = np.array([[c, -s], [s, c]])
    P = rot @ np.diag([1.0, 1e-12]) @ rot.T
    P = 0.5 * (P + P.T)
    r = fo.fuse([[1.0, 2.0], [3.0, -1.0]], np.stack([P, P]), method=method)
    np.testing.assert_allclose(r.cov, scale * P, rtol=0, atol=1e-9 * np.abs(P).max())
    np.testing.assert_allclose(r.mean, [2.0, 0.5], rtol=1e-9)
    if method == "naive":  # known-cross with zero cross is naive
        cross = np.zeros((2, 2, 2, 2))
        cross[0, 0] = cross[1, 1] = P
        kc = fo.fuse([[1.0, 2.0], [3.0, -1.0]], np.stack([P, P]), "known-cross", cross=cross)
        np.testing.assert_allclose(kc.cov, r.cov, rtol=0, atol=1e-9 * np.abs(P).max())
