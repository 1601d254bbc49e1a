"""svec: the order and scaling of Clarabel's PSD triangle, and the basis T."""

import numpy as np

from fusion_opt import svec


def test_order_is_the_upper_triangle_column_by_column():
    i, j = svec.upper(3)
    assert list(zip(i, j, strict=True)) == [(0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2)]
    assert list(svec.index(i, j)) == list(range(6))


def test_basis_and_scale_preserve_the_trace_inner_product():
    rng = np.random.default_rng(0)
    X, Z = (A + A.T for A in rng.standard_normal((2, 4, 4)))
    T, (i, j) = svec.basis(4), svec.upper(4)
    sx, sz = (A[i, j] * svec.scale(4) for A in (X, Z))
    assert np.allclose(T @ sx, X.ravel()) and np.allclose(T.T @ T, np.eye(10))
    assert np.isclose(sx @ sz, np.trace(X @ Z))


def test_kronecker_maps_act_in_svec_coordinates():
    rng = np.random.default_rng(1)
    R = rng.standard_normal((3, 3))
    X = rng.standard_normal((3, 3))
    X = X + X.T
    T, (i, j) = svec.basis(3), svec.upper(3)
    C = T.T @ np.kron(R.T, R.T) @ T
    assert np.allclose(C @ (X[i, j] * svec.scale(3)), (R.T @ X @ R)[i, j] * svec.scale(3))
