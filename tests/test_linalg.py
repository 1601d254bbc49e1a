"""The compiled dense kernels of linalg.py against numpy, and the exactness their speed-ups
rely on: scaling by pow2 is ldexp, and the blocked loops sum in the same order as one
entry at a time (so the batch results stay bit for bit those of the plain loops)."""

import numpy as np
import pytest

from fusion_opt import linalg


def test_multiplying_by_pow2_is_ldexp_also_into_subnormals():
    rng = np.random.default_rng(120)
    x = rng.standard_normal(2000) * 10.0 ** rng.uniform(-300, 300, 2000)
    for e in (-1100, -1074, -1060, -1022, -600, -1, 0, 1, 600, 1023, 1100):
        factor = linalg.pow2(e)
        if -1022 <= e <= 1023:
            assert factor == np.ldexp(1.0, e)
            with np.errstate(over="ignore"):
                np.testing.assert_array_equal(x * factor, np.ldexp(x, e))
        else:
            assert factor == 0.0


def _one_at_a_time(A, B):
    """A @ B summed entry by entry in the order of k, in float64 (the unblocked loops)."""
    C = np.zeros((A.shape[0], B.shape[1]))
    for k in range(A.shape[1]):
        C += A[:, k:k + 1] * B[k:k + 1, :]
    return C


@pytest.mark.parametrize("n,m", [(1, 1), (3, 3), (4, 4), (5, 7), (6, 6), (12, 12), (16, 9)])
def test_small_products_sum_in_the_order_of_k(n, m):
    rng = np.random.default_rng([121, n, m])
    A, B = rng.standard_normal((n, m)), rng.standard_normal((m, n + 1))
    C = np.empty((n, n + 1))
    linalg.small_mul(A, B, C, False)
    np.testing.assert_array_equal(C, _one_at_a_time(A, B))
    Bt = np.ascontiguousarray(B.T)
    linalg.small_mul_t(A, Bt, C)
    np.testing.assert_array_equal(C, _one_at_a_time(A, B))
    G = np.empty((m, m))
    linalg.small_gram(A, G)
    np.testing.assert_array_equal(G, _one_at_a_time(A.T, A))


@pytest.mark.parametrize("m,cols", [(1, 1), (3, 3), (4, 4), (5, 7), (6, 6), (7, 5), (12, 12),
                                    (16, 9)])
def test_triangular_products_skip_zeros_and_no_bit(m, cols):
    """The products with a triangular factor skip its zeros and give, bit for bit, the full
    product summed in the order of k (zeros included), also where sums cancel to 0."""
    rng = np.random.default_rng([123, m, cols])
    F = np.tril(rng.integers(-2, 3, (3, m, m)).astype(float))  # small integers: exact 0 sums
    F[1] = np.tril(rng.standard_normal((m, m)))
    for D in (rng.standard_normal((m, cols)), rng.integers(-2, 3, (m, cols)).astype(float)):
        E = np.full((m, cols), np.nan)
        for i in range(3):
            linalg.node_mul(F, i, D, E, False)
            np.testing.assert_array_equal(E, _one_at_a_time(F[i], D))
            linalg.node_tmul(F, i, D, E)
            np.testing.assert_array_equal(E, _one_at_a_time(F[i].T, D))
        U = np.triu(D[:, :m]) if cols >= m else None
        if U is not None:
            Em, Sq = np.full((m, m), np.nan), np.full((m, m), np.nan)
            for i in range(3):
                linalg.node_mul(F, i, U, Em, True)
                np.testing.assert_array_equal(Em, _one_at_a_time(F[i], U))
            linalg.small_mul(U, D[:, :m], Sq, True)
            np.testing.assert_array_equal(Sq, _one_at_a_time(U, D[:, :m]))
            np.testing.assert_array_equal(np.signbit(Sq), np.signbit(_one_at_a_time(U, D[:, :m])))


@pytest.mark.parametrize("n,rows", [(1, 3), (2, 4), (3, 17), (4, 12), (5, 17), (6, 30),
                                    (9, 40), (12, 96)])
def test_householder_is_a_qr_and_blocks_like_one_column_at_a_time(n, rows):
    rng = np.random.default_rng([122, n, rows])
    A = rng.standard_normal((rows, n))
    At, Vt, R = np.ascontiguousarray(A.T), np.zeros((n, rows)), np.empty((n, n))
    linalg.householder(At, n, rows, Vt, R)
    Q = np.eye(rows)
    for k in range(n):
        Q = Q @ (np.eye(rows) - 2.0 * np.outer(Vt[k], Vt[k]))
    np.testing.assert_allclose(Q[:, :n] @ R, A, atol=1e-13 * np.abs(A).max())
    # the same reflections column by column with numpy, in the same order of summation
    X = np.ascontiguousarray(A.T)
    for k in range(n):
        for j in range(k + 1, n):
            t = 0.0
            for i in range(k, rows):
                t += Vt[k, i] * X[j, i]
            X[j, k:] -= 2.0 * t * Vt[k, k:]
        np.testing.assert_array_equal(R[k, k + 1:], X[k + 1:, k])


@pytest.mark.parametrize("n,rows", [(1, 2), (3, 6), (5, 10), (9, 23), (30, 60)])
def test_thin_qt_is_q_and_gives_the_bits_of_one_column_at_a_time(n, rows):
    """thin_qt takes four columns at a time through each reflector: the same bits as
    H_j ... H_0 e_j column by column with sums in the order of i, and Q^T Q = I, Q R = A."""
    rng = np.random.default_rng([126, n, rows])
    A = rng.standard_normal((rows, n))
    At, Vt, R = np.ascontiguousarray(A.T), np.zeros((n, rows)), np.empty((n, n))
    linalg.householder(At, n, rows, Vt, R)
    Qt = np.full((n, rows), np.nan)
    linalg.thin_qt(Vt, n, rows, Qt)
    for j in range(n):
        x = np.eye(rows)[j]
        for k in range(j, -1, -1):
            t = 0.0
            for i in range(k, rows):
                t += Vt[k, i] * x[i]
            x[k:] -= 2.0 * t * Vt[k, k:]
        np.testing.assert_array_equal(Qt[j], x)
    assert np.abs(Qt @ Qt.T - np.eye(n)).max() <= 1e-14 * n
    assert np.abs(Qt.T @ R - A).max() <= 1e-14 * n * np.abs(A).max()


def _padded(A, pad=3):
    """A (rows, n) as At (n, rows + pad), C order, the last pad columns NaN: a buffer
    wider than the matrix, as the work arrays are (LAPACK's leading dimension)."""
    rows, n = A.shape
    At = np.full((n, rows + pad), np.nan)
    At[:, :rows] = A.T
    return At


@pytest.mark.parametrize("n,rows", [(3, 6), (16, 48), (17, 34), (40, 120), (150, 300)])
def test_qr_is_householders_qr_through_lapack_above_small(n, rows):
    """`qr` (LAPACK's dgeqrf above SMALL, its reflectors converted to unit ones) is a QR:
    R upper with Q R = A for the Q its reflectors make, and R is householder's up to the
    signs of its rows (to rounding; the same bits at n <= SMALL), a zero column included
    (its reflector is 0, H = I)."""
    rng = np.random.default_rng([127, n, rows])
    A = rng.standard_normal((rows, n)) * np.exp(rng.uniform(-5, 5, n))
    A[:, n // 2] = 0.0
    At, Vt, R = _padded(A), np.zeros((n, rows + 3)), np.full((n, n), np.nan)
    linalg.qr(At, n, rows, Vt, R)
    Q = np.eye(rows)
    for k in range(n):
        Q = Q @ (np.eye(rows) - 2.0 * np.outer(Vt[k, :rows], Vt[k, :rows]))
    assert np.abs(Q.T @ Q - np.eye(rows)).max() <= 1e-14 * n
    assert np.abs(Q[:, :n] @ R - A).max() <= 1e-14 * n * np.abs(A).max()
    np.testing.assert_array_equal(np.tril(R, -1), 0.0)
    At2, Vt2, R2 = _padded(A), np.zeros((n, rows + 3)), np.empty((n, n))
    linalg.householder(At2, n, rows, Vt2, R2)
    signs = np.where(np.sign(np.diag(R)) == np.sign(np.diag(R2)), 1.0, -1.0)
    if n <= linalg.SMALL:
        np.testing.assert_array_equal(R, R2)
    else:
        assert np.abs(signs[:, None] * R - R2).max() <= 1e-14 * n * np.abs(A).max()


@pytest.mark.parametrize("n,rows", [(3, 6), (17, 34), (40, 80), (150, 300)])
def test_qr_thin_is_the_thin_q_and_r(n, rows):
    """`qr_thin` leaves Q^T (n, rows) in At and R: Q^T Q = I, Q R = A; at n <= SMALL the
    bits of householder then thin_qt, above it LAPACK's dgeqrf and dorgqr (whose R is
    `qr`'s)."""
    rng = np.random.default_rng([128, n, rows])
    A = rng.standard_normal((rows, n))
    At, Vt, R = _padded(A), np.zeros((n, rows + 3)), np.empty((n, n))
    linalg.qr_thin(At, n, rows, Vt, R)
    Qt = At[:, :rows]
    assert np.abs(Qt @ Qt.T - np.eye(n)).max() <= 1e-14 * n
    assert np.abs(Qt.T @ R - A).max() <= 1e-14 * n * np.abs(A).max()
    At2, Vt2, R2 = _padded(A), np.zeros((n, rows + 3)), np.empty((n, n))
    linalg.qr(At2, n, rows, Vt2, R2)
    np.testing.assert_array_equal(R, R2)
    if n <= linalg.SMALL:
        linalg.thin_qt(Vt2, n, rows, At2)
        np.testing.assert_array_equal(At[:, :rows], At2[:, :rows])


@pytest.mark.parametrize("n", [3, 16, 17, 60, 200])
def test_cholesky_is_numpys_and_refuses_what_is_not_positive_definite(n):
    """`cholesky` (loops up to SMALL, LAPACK's dpotrf above): L lower with L L^T = A, to
    rounding of numpy's factor; False for an indefinite matrix (a negative last pivot)
    and one with an inf on its diagonal; L's upper triangle is zero."""
    rng = np.random.default_rng([129, n])
    G = rng.standard_normal((n, n))
    A = G @ G.T + n * np.eye(n)
    L = np.full((n, n), np.nan)
    assert linalg.cholesky(A, L)
    np.testing.assert_array_equal(np.triu(L, 1), 0.0)
    assert np.abs(L - np.linalg.cholesky(A)).max() <= 1e-13 * np.sqrt(np.abs(A).max())
    V = np.linalg.qr(G)[0]
    assert not linalg.cholesky((V * np.r_[np.ones(n - 1), -1e-3]) @ V.T, np.empty((n, n)))
    B = A.copy()
    B[n - 1, n - 1] = np.inf
    assert not linalg.cholesky(B, np.empty((n, n)))


@pytest.mark.parametrize("n,rows", [(1, 3), (3, 17), (5, 17), (9, 40), (37, 37)])
def test_householder_column_appends_the_columns_of_householder_bit_for_bit(n, rows):
    """Columns added one at a time (the NNLS of backends/newton.py keeps its QR so) give
    the reflectors and R of the whole QR exactly, and so a QR of A."""
    rng = np.random.default_rng([123, n, rows])
    A = rng.standard_normal((rows, n)) * 10.0 ** rng.uniform(-3, 3, n)
    At, Vt, R = np.ascontiguousarray(A.T), np.zeros((n, rows)), np.empty((n, n))
    linalg.householder(At, n, rows, Vt, R)
    Bt, Wt, S = np.ascontiguousarray(A.T), np.zeros((n, rows)), np.full((n, n), np.nan)
    for k in range(n):
        linalg.householder_column(Bt, k, rows, Wt, S)
    np.testing.assert_array_equal(Wt, Vt)
    np.testing.assert_array_equal(S, R)
    Q, R_np = np.linalg.qr(A)
    np.testing.assert_allclose(np.abs(S), np.abs(R_np), atol=1e-12 * np.abs(R_np).max())


@pytest.mark.parametrize("n, k", [(1, 1), (4, 4), (7, 3), (60, 30)])
def test_lower_solve_is_forward_substitution_summed_in_the_order_of_p(n, k):
    """lower_solve against scipy's triangular solve, against the plain loop it reorders (by
    rows of X: every entry's sum in the order p = 0, 1, ... as by columns, bit for bit),
    and exact where B = L: the identity, as LAPACK's dtrtrs gives (EI's tie rule needs
    it)."""
    import scipy.linalg

    rng = np.random.default_rng(n * k)
    L = np.tril(rng.standard_normal((n, n))) + 3.0 * np.eye(n)
    B = rng.standard_normal((n, k))
    X = np.empty((n, k))
    linalg.lower_solve(L, B, X)
    ref = scipy.linalg.solve_triangular(L, B, lower=True)
    assert np.abs(X - ref).max() <= 1e-13 * np.abs(ref).max()
    loop = np.empty((n, k))
    for j in range(k):
        for i in range(n):
            t = B[i, j]
            for p in range(i):
                t -= L[i, p] * loop[p, j]
            loop[i, j] = t / L[i, i]
    np.testing.assert_array_equal(X, loop)
    eye = np.empty((n, n))
    linalg.lower_solve(L, L, eye)
    np.testing.assert_array_equal(eye, np.eye(n))


@pytest.mark.parametrize("n", [1, 3, 8, 9, 40])
def test_lower_inverse_by_rows_gives_the_bits_of_the_column_loop(n):
    """Above order 8 lower_inverse runs by rows of X (the columns' stride made it 4.5
    times slower at 256); every entry's sum in the same order, so the same bits as the
    plain column loop, and the inverse to rounding."""
    rng = np.random.default_rng(n)
    L = np.tril(rng.standard_normal((n, n))) + 3.0 * np.eye(n)
    X = np.empty((n, n))
    linalg.lower_inverse(L, X)
    loop = np.zeros((n, n))
    for j in range(n):
        loop[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            t = 0.0
            for p in range(j, i):
                t -= L[i, p] * loop[p, j]
            loop[i, j] = t / L[i, i]
    np.testing.assert_array_equal(X, loop)
    assert np.abs(X @ L - np.eye(n)).max() <= 1e-12


@pytest.mark.parametrize("n", [1, 3, 8, 9, 40])
def test_upper_inverse_by_rows_gives_the_bits_of_the_column_loop(n):
    """Above order 8 upper_inverse runs by rows of X, from the last (by columns it took
    0.10 s at 800): the same bits as the plain column loop, and the inverse to rounding."""
    rng = np.random.default_rng(n)
    R = np.triu(rng.standard_normal((n, n))) + 3.0 * np.eye(n)
    X = np.empty((n, n))
    linalg.upper_inverse(R, X)
    loop = np.zeros((n, n))
    for j in range(n):
        loop[j, j] = 1.0 / R[j, j]
        for i in range(j - 1, -1, -1):
            t = 0.0
            for p in range(i + 1, j + 1):
                t -= R[i, p] * loop[p, j]
            loop[i, j] = t / R[i, i]
    np.testing.assert_array_equal(X, loop)
    assert np.abs(X @ R - np.eye(n)).max() <= 1e-12


@pytest.mark.parametrize("m, k", [(1, 1), (5, 2), (70, 4)])
def test_lower_t_solve_is_the_transposed_solve(m, k):
    """lower_t_solve(L, B^T) = L^-T B against scipy's triangular solve."""
    import scipy.linalg

    rng = np.random.default_rng(m + k)
    L = np.tril(rng.standard_normal((m, m))) + 3.0 * np.eye(m)
    B = rng.standard_normal((m, k))
    X = np.empty((m, k))
    linalg.lower_t_solve(L, np.ascontiguousarray(B.T), X)
    ref = scipy.linalg.solve_triangular(L, B, lower=True, trans="T")
    assert np.abs(X - ref).max() <= 1e-13 * np.abs(ref).max()


def test_row_norms_hold_any_scale_without_squares_that_overflow():
    """`row_norms` against math.hypot (exact to rounding, no overflow) at scales 1e-300 to
    1e300: np.linalg.norm's squares made 2e200 inf and 2e-170 zero (fuzz N1); inf where a
    component is; empty vectors have norm 0."""
    import math

    rng = np.random.default_rng(8)
    for scale in (1e-300, 1e-170, 1.0, 1e200, 1e300):
        d = rng.standard_normal((5, 3)) * scale
        np.testing.assert_allclose(linalg.row_norms(d), [math.hypot(*v) for v in d],
                                   rtol=4e-16)
    assert linalg.row_norms(np.array([[np.inf, 0.0], [-np.inf, 1.0]])).tolist() == [np.inf] * 2
    assert linalg.row_norms(np.zeros((2, 0))).tolist() == [0.0, 0.0]
    assert linalg.row_norms(np.zeros((3, 2))).tolist() == [0.0, 0.0, 0.0]

