"""Congruence scaling that makes a CI weight problem well conditioned for any solver.

With Ybar = mean_i Y_i = L L^T, put Y'_i = L^-1 Y_i L^-T so that Y'(uniform) = I. Then
P(w) = L^-T P'(w) L^-1 and

    trace:   tr P(w)       = c tr(M P'(w)),  M = L^-1 L^-T / c,  c = tr(Ybar^-1)
    logdet:  -log det Y(w) = -log det Y'(w) - log det Ybar

so the weights are unchanged, the trace objective is 1 at uniform weights, and covariances
spanning 1e-6 to 1e6 reach the solver as matrices of order one. Broadcasts over leading
batch axes: Ys (..., N, n, n).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScaledProblem:
    """Ys (..., N, n, n) scaled information; M (..., n, n) unit-trace weight of the trace
    criterion; L (..., n, n) Cholesky factor of Ybar; c (...) = tr(Ybar^-1)."""

    Ys: np.ndarray
    M: np.ndarray
    L: np.ndarray
    c: np.ndarray
    criterion: str

    def problem(self, b: int) -> ScaledProblem:
        """Problem b of a batch (leading axis), as its own ScaledProblem."""
        return ScaledProblem(self.Ys[b], self.M[b], self.L[b], self.c[b], self.criterion)

    def unscale_objective(self, f_scaled):
        """Objective in the original units from the scaled one."""
        if self.criterion == "trace":
            return self.c * f_scaled
        logdet_ybar = 2.0 * np.log(np.diagonal(self.L, axis1=-2, axis2=-1)).sum(-1)
        return f_scaled - logdet_ybar

    def unscale_gap(self, gap_scaled):
        return self.c * gap_scaled if self.criterion == "trace" else gap_scaled

    def covariance(self, P_scaled):
        """P = L^-T P' L^-1 in the original units."""
        Linv = np.linalg.inv(self.L)
        P = np.swapaxes(Linv, -1, -2) @ P_scaled @ Linv
        return 0.5 * (P + np.swapaxes(P, -1, -2))


def scale(Ys: np.ndarray, criterion: str) -> ScaledProblem:
    """Scale information matrices Ys (..., N, n, n) as the module docstring says."""
    L = np.linalg.cholesky(Ys.mean(axis=-3))
    Linv = np.linalg.inv(L)
    Linv_b = Linv[..., None, :, :]
    Ys_scaled = Linv_b @ Ys @ np.swapaxes(Linv_b, -1, -2)
    Ys_scaled = 0.5 * (Ys_scaled + np.swapaxes(Ys_scaled, -1, -2))
    # tr(P) = tr(L^-T P' L^-1) = tr(P' L^-1 L^-T): the weight is L^-1 L^-T; its trace
    # equals tr(L^-T L^-1) = tr(Ybar^-1).
    W = Linv @ np.swapaxes(Linv, -1, -2)
    c = np.trace(W, axis1=-2, axis2=-1)
    return ScaledProblem(Ys_scaled, W / c[..., None, None], L, c, criterion)
