"""Symmetric matrices as vectors (the "svec" of conic solvers).

For X symmetric (n, n), svec(X) (m,), m = n(n+1)/2, lists the upper triangle (i <= j) column
by column, (0,0), (0,1), (1,1), (0,2), ..., with off-diagonal entries times sqrt(2), so that
svec(X) . svec(Z) = tr(X Z). Clarabel's PSD triangle cone uses this convention. `basis(n)` is
T (n*n, m) with vec(X) = T svec(X) and T^T T = I, so svec(X) = T^T vec(X) and a linear map
of symmetric matrices with Kronecker matrix K (n*n, n*n) is T^T K T in svec coordinates.
"""

from __future__ import annotations

from functools import cache

import numpy as np


def _frozen(*arrays):
    """The arrays made read-only: cached, so shared by every caller."""
    for a in arrays:
        a.setflags(write=False)
    return arrays if len(arrays) > 1 else arrays[0]


@cache
def upper(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows i and columns j (i <= j) of the upper triangle of an (n, n) matrix in svec order."""
    j, i = np.tril_indices(n)
    return _frozen(i, j)


def index(i, j):
    """Position of entry (i, j), i <= j, in svec order."""
    return j * (j + 1) // 2 + i


@cache
def scale(n: int) -> np.ndarray:
    """The factor (m,) of each svec entry: 1 on the diagonal, sqrt(2) off it."""
    i, j = upper(n)
    return _frozen(np.where(i < j, np.sqrt(2.0), 1.0))


@cache
def basis(n: int) -> np.ndarray:
    """T (n*n, m): vec(X) = T svec(X) for symmetric X (row-major vec; X is symmetric)."""
    i, j = upper(n)
    cols = np.arange(len(i))
    T = np.zeros((n * n, len(i)))
    T[i * n + j, cols] = T[j * n + i, cols] = 1.0 / scale(n)
    return _frozen(T)
