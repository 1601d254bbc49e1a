"""Fusion rules other than optimised CI, for comparison, through `fuse(method=...)`.

Each rule gives gains K_i (N, n, n) with sum_i K_i = I and a covariance P (n, n), and
m = sum_i K_i m_i. What each assumes, and whether its P is consistent (>= the true error
covariance) when the cross-correlation of the inputs is unknown:

- "naive" (independent / Kalman): P = (sum Y_i)^-1, K_i = P Y_i. Assumes independent errors;
  optimal then, overconfident (inconsistent) under correlation.
- "known-cross" (BLUE, Bar-Shalom–Campo for N = 2): given the joint covariance S (N n, N n)
  with blocks cross[i, j] = cov(e_i, e_j), P = (H^T S^-1 H)^-1 and K = P H^T S^-1 with
  H = [I; ...; I]. Exact and the smallest error covariance of all linear unbiased rules, if S
  is right; it does not apply when S is unknown.
- "fast-ci" (Niehsen 2002): CI with w_i proportional to 1 / tr(P_i). Consistent under any
  correlation (every CI weight is), not optimal in any criterion.
- "ifci" (improved fast CI, Franken & Hupper 2005): CI with, for Y = sum Y_i,
  w_i = (det Y - det(Y - Y_i) + det Y_i) / sum_j (det Y - det(Y - Y_j) + det Y_j).
  Consistent under any correlation, like fast-ci.
- "ici" (inverse CI, Noack et al. 2017; N = 2): with G = w P_a + (1 - w) P_b,
  P^-1 = Y_a + Y_b - G^-1, K_a = P (Y_a - w G^-1), K_b = P (Y_b - (1 - w) G^-1), w in [0, 1]
  minimising the criterion (grid then bounded Brent). Assumes the correlation comes from
  common information of unknown amount: consistent for that model, not for arbitrary
  correlation; never worse than the better input (w = 0 or 1 give P_a or P_b).
- "ei" (ellipsoidal intersection, Sijs & Lazar 2012; N = 2): with the mutual covariance
  Gam = T diag(max(mu_k, 1)) T^T (P_b = T T^T, P_a = T diag(mu) T^T),
  P^-1 = Y_a + Y_b - Gam^-1 (per axis of T, the larger information) and the mutual mean
  gam = Q^-1 ((Y_b - Gam^-1 + eta I) m_a + (Y_a - Gam^-1 + eta I) m_b),
  Q = Y_a + Y_b - 2 Gam^-1 + 2 eta I, m = P (Y_a m_a + Y_b m_b - Gam^-1 gam); eta > 0 only
  when some mu_k is within 10 EI_EPS of 1. A heuristic: no consistency guarantee.

Results are `FusionResult`s with status "closed-form" (ICI: "optimal" for its 1-D search),
gap 0 (no CI optimisation to certify) and objective tr P or log det P. Their `weights` are
the CI weights for fast-ci and ifci, w and 1 - w for ici, and the gain shares tr(K_i) / n
(summing to 1, negative for known-cross when a gain is) for naive, known-cross and ei.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import minimize_scalar

from typing import NamedTuple

from .results import FusionInputError, Status
from .validation import SYMMETRY_RTOL


class RuleOutput(NamedTuple):
    """weights (N,), mean (n,), cov (n, n), status, and what the weights are."""

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    status: Status
    weights_are: str


def diagonalise_covariances(Pa, Pb):
    """lam (n,), T (n, n) with Pa = T diag(1/lam) T^T, Pb = T T^T."""
    L = np.linalg.cholesky(Pa + Pb)
    Li = np.linalg.inv(L)
    nu, U = np.linalg.eigh(Li @ Pa @ Li.T)
    nu = np.clip(nu, np.finfo(float).eps, 1 - np.finfo(float).eps)
    return (1.0 - nu) / nu, (L @ U) * np.sqrt(1.0 - nu)

EI_EPS = 1e-8
_ICI_GRID = 21


def naive(means, covs, criterion="trace") -> FusionResult:
    """Independent (Kalman) fusion of means (N, n), covs (N, n, n)."""
    means, covs, t0 = _start(means, covs, criterion)
    Ys = np.linalg.inv(covs)
    P = np.linalg.inv(Ys.sum(0))
    return _result(means, P @ Ys, P, None, criterion, "naive", t0)


def known_cross(means, covs, criterion="trace", *, cross=None) -> FusionResult:
    """BLUE given the joint covariance: cross (N, N, n, n), cross[i, j] = cov(e_i, e_j), with
    cross[i, i] equal to covs[i]."""
    means, covs, t0 = _start(means, covs, criterion)
    N, n = means.shape
    S = _joint(cross, covs)
    X = np.linalg.solve(S, np.tile(np.eye(n), (N, 1)))  # S^-1 H, (N n, n)
    P = np.linalg.inv(X.reshape(N, n, n).sum(0))
    P = 0.5 * (P + P.T)
    gains = P @ np.swapaxes(X.reshape(N, n, n), -1, -2)  # K_i = P (S^-1 H)_i^T
    return _result(means, gains, P, None, criterion, "known-cross", t0)


def fast_ci(means, covs, criterion="trace") -> FusionResult:
    """CI with w_i = (1 / tr P_i) / sum_j (1 / tr P_j) (Niehsen 2002)."""
    means, covs, t0 = _start(means, covs, criterion)
    inv_tr = 1.0 / np.trace(covs, axis1=-2, axis2=-1)
    return _ci_with(means, covs, inv_tr / inv_tr.sum(), criterion, "fast-ci", t0)


def ifci(means, covs, criterion="trace") -> FusionResult:
    """CI with the determinant weights of Franken & Hupper (2005) (module docstring)."""
    means, covs, t0 = _start(means, covs, criterion)
    Ys = np.linalg.inv(covs)
    Y = Ys.sum(0)
    num = np.linalg.det(Y) - np.linalg.det(Y - Ys) + np.linalg.det(Ys)
    return _ci_with(means, covs, num / num.sum(), criterion, "ifci", t0)


def ici(means, covs, criterion="trace") -> FusionResult:
    """Inverse covariance intersection of N = 2 estimates (module docstring)."""
    means, covs, t0 = _start(means, covs, criterion, pair="ici")
    Pa, Pb = covs
    Ya, Yb = np.linalg.inv(covs)

    def fused(w):
        Ginv = np.linalg.inv(w * Pa + (1.0 - w) * Pb)
        return np.linalg.inv(Ya + Yb - Ginv), Ginv

    def f(w):
        return _objective(fused(w)[0], criterion)

    grid = np.linspace(0.0, 1.0, _ICI_GRID)
    k = int(np.argmin([f(w) for w in grid]))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, _ICI_GRID - 1)]
    res = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
    w = res.x if res.fun <= f(grid[k]) else grid[k]
    P, Ginv = fused(w)
    P = 0.5 * (P + P.T)
    gains = np.stack([P @ (Ya - w * Ginv), P @ (Yb - (1.0 - w) * Ginv)])
    return _result(means, gains, P, np.array([w, 1.0 - w]), criterion, "ici", t0,
                   status=Status.OPTIMAL)


def ei(means, covs, criterion="trace") -> FusionResult:
    """Ellipsoidal intersection of N = 2 estimates (module docstring)."""
    means, covs, t0 = _start(means, covs, criterion, pair="ei")
    lam, T = diagonalise_covariances(covs[0], covs[1])  # P_a = T diag(1/lam) T^T
    Tinv = np.linalg.inv(T)
    Ya, Yb = np.linalg.inv(covs)
    Gam_inv = Tinv.T @ (np.minimum(lam, 1.0)[:, None] * Tinv)
    n = len(lam)
    near = np.abs(1.0 / lam - 1.0).min() < 10 * EI_EPS
    eta = EI_EPS * np.trace(Ya + Yb) / n if near else 0.0
    Ra, Rb = Yb - Gam_inv + eta * np.eye(n), Ya - Gam_inv + eta * np.eye(n)
    QR = np.linalg.solve(Ra + Rb, np.stack([Ra, Rb]))  # Q^-1 R_a, Q^-1 R_b
    P = np.linalg.inv(Ya + Yb - Gam_inv)
    P = 0.5 * (P + P.T)
    gains = P @ (np.stack([Ya, Yb]) - Gam_inv @ QR)
    return _result(means, gains, P, None, criterion, "ei", t0)


RULES = {"naive": naive, "known-cross": known_cross, "fast-ci": fast_ci, "ifci": ifci,
         "ici": ici, "ei": ei}
RULE_ARGS = {name: frozenset({"cross"} if name == "known-cross" else ()) for name in RULES}
PAIR_ONLY = frozenset({"ici", "ei"})


def _start(means, covs, criterion, pair=None):
    return means, covs, time.perf_counter()


def _joint(cross, covs) -> np.ndarray:
    """The joint covariance (N n, N n) from cross (N, N, n, n), checked."""
    N, n = covs.shape[:2]
    if cross is None:
        raise FusionInputError("method 'known-cross' needs cross (N, N, n, n)")
    cross = np.asarray(cross, dtype=float)
    if cross.shape != (N, N, n, n):
        raise FusionInputError(f"cross must have shape {(N, N, n, n)}, got {cross.shape}")
    if not np.all(np.isfinite(cross)):
        raise FusionInputError("cross has a non-finite value")
    S = cross.transpose(0, 2, 1, 3).reshape(N * n, N * n)
    tol = SYMMETRY_RTOL * np.abs(S).max()
    if np.abs(S - S.T).max() > tol:
        raise FusionInputError("cross is not symmetric: cross[i, j] must equal cross[j, i]^T")
    diag = cross[np.arange(N), np.arange(N)]
    bad = np.abs(diag - covs).max(axis=(-2, -1)) > tol
    if bad.any():
        raise FusionInputError(f"cross[{np.argmax(bad)}, {np.argmax(bad)}] differs from covs "
                               f"of node {np.argmax(bad)}")
    S = 0.5 * (S + S.T)
    try:
        np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise FusionInputError("cross: the joint covariance is not positive definite") from None
    return S


def _ci_with(means, covs, w, criterion, method, t0) -> FusionResult:
    """CI with given weights w (N,): P = (sum w_i Y_i)^-1, K_i = P w_i Y_i."""
    wY = w[:, None, None] * np.linalg.inv(covs)
    P = np.linalg.inv(wY.sum(0))
    return _result(means, P @ wY, 0.5 * (P + P.T), w, criterion, method, t0)


def _objective(P, criterion) -> float:
    return float(np.trace(P)) if criterion == "trace" else float(np.linalg.slogdet(P)[1])


def _result(means, gains, P, weights, criterion, method, t0, status=Status.CLOSED_FORM):
    are = "gain_shares" if weights is None else "ci_weights"
    if weights is None:
        weights = np.trace(gains, axis1=-2, axis2=-1) / P.shape[0]
    mean = np.einsum("ijk,ik->j", gains, means)
    return RuleOutput(weights, mean, 0.5 * (P + P.T), status, are)
