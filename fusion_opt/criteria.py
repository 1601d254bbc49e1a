"""Objective, gradient, Hessian and optimality certificate of the CI weight problem.

For information matrices Y_i (N, n, n) and weights w on the simplex, Y(w) = sum_i w_i Y_i
and P(w) = inv(Y(w)). With a weight matrix M (n, n) (M = I in DESIGN §1; a general M comes
from the congruence scaling of `scaling.py`):

    trace:   f = tr(M P),        g_i = -tr(M P Y_i P),   H_ij = 2 tr(M P Y_i P Y_j P)
    logdet:  f = -log det Y,     g_i = -tr(P Y_i),       H_ij = tr(P Y_i P Y_j)

Both are convex in w. On the simplex, gap(w) = g(w).w - min_i g_i(w) >= 0 bounds the
suboptimality f(w) - f* (first-order convexity bound with the best vertex direction).
Every function broadcasts over leading batch axes: Ys (..., N, n, n), w (..., N).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Evaluation(NamedTuple):
    """f (...), g (..., N) and H (..., N, N) (H is None unless asked for)."""

    f: np.ndarray
    g: np.ndarray
    H: np.ndarray | None


def fused_information(Ys: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Y(w) = sum_i w_i Y_i, shape (..., n, n)."""
    return np.einsum("...i,...ijk->...jk", w, Ys)


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def evaluate(Ys, w, criterion: str, M=None, hessian: bool = False, nodes=None) -> Evaluation:
    """f, g (and H) of `criterion` at w. M (..., n, n) weights the trace; None means I.

    With `nodes` (..., k) integer indices, H is the (..., k, k) block of those nodes only
    (a solver needs H on the support alone, which is much smaller than N).
    """
    Y = fused_information(Ys, w)
    chol = np.linalg.cholesky(Y)
    P = _sym(np.linalg.inv(Y))
    A = P[..., None, :, :] @ Ys  # A_i = P Y_i, (..., N, n, n)
    if criterion == "logdet":
        f = -2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
        g = -np.trace(A, axis1=-2, axis2=-1)
        if hessian:
            A_s = _select(A, nodes)
            H = _trace_products(A_s, A_s)
        return Evaluation(f, g, H if hessian else None)
    PM = P if M is None else P @ M
    f = np.trace(PM, axis1=-2, axis2=-1)
    G = _sym(PM @ P)  # P M P
    B = G[..., None, :, :] @ Ys  # B_i = P M P Y_i
    g = -np.trace(B, axis1=-2, axis2=-1)
    H = 2.0 * _sym(_trace_products(_select(B, nodes), _select(A, nodes))) if hessian else None
    return Evaluation(f, g, H)


def _select(stack: np.ndarray, nodes) -> np.ndarray:
    """stack (..., N, n, n) restricted to nodes (..., k) along the node axis."""
    if nodes is None:
        return stack
    return np.take_along_axis(stack, nodes[..., None, None], axis=-3)


def _trace_products(B: np.ndarray, A: np.ndarray) -> np.ndarray:
    """T_ij = tr(B_i A_j) for stacks (..., N, n, n), as one matrix product."""
    n2 = B.shape[-1] * B.shape[-2]
    Bf = B.reshape(*B.shape[:-2], n2)
    At = np.swapaxes(A, -1, -2).reshape(*A.shape[:-2], n2)
    return Bf @ np.swapaxes(At, -1, -2)


def gap(g: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The certificate g.w - min_i g_i, clipped at 0 against rounding, shape (...)."""
    return np.maximum((g * w).sum(-1) - g.min(-1), 0.0)
