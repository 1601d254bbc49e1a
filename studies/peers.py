"""The peers of the backend benchmark (studies/backends.py): the solvers a user would
otherwise write or call, named in PEERS. Each returns a PeerResult (fast-ci: fusion-opt's
own result)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.optimize import minimize, minimize_scalar

import fusion_opt as fo

PEERS = ("minimize_scalar", "scipy-slsqp", "fixed-weights", "fast-ci")


class PeerResult(NamedTuple):
    """What a peer gives: weights (N,), fused mean (n,) and cov (n, n), and whether its
    optimiser reported success."""

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    ok: bool


def _user_objective(criterion: str) -> Callable:
    """f(Y) of the fused information Y, written the way a user writes it: the inverse,
    then its trace or log det."""
    if criterion == "trace":
        return lambda Y: np.trace(np.linalg.inv(Y))
    return lambda Y: np.linalg.slogdet(np.linalg.inv(Y))[1]


def _peer_result(w, Ys, means, ok) -> PeerResult:
    """The fused estimate at weights w (N,) of informations Ys (N, n, n), means (N, n)."""
    P = np.linalg.inv(np.tensordot(w, Ys, 1))
    return PeerResult(w, P @ np.einsum("i,ijk,ik->j", w, Ys, means), P, ok)


def minimize_scalar_peer(m_a, P_a, m_b, P_b, criterion) -> PeerResult:
    """Pairwise CI by scipy's bounded scalar minimiser on w in [0, 1] (default tolerance)."""
    Y_a, Y_b = np.linalg.inv(P_a), np.linalg.inv(P_b)
    f = _user_objective(criterion)
    res = minimize_scalar(lambda w: f(w * Y_a + (1 - w) * Y_b), bounds=(0, 1),
                          method="bounded")
    return _peer_result(np.array([res.x, 1 - res.x]), np.stack([Y_a, Y_b]),
                        np.stack([m_a, m_b]), bool(res.success))


def slsqp_peer(means, covs, criterion) -> PeerResult:
    """BCI by scipy's SLSQP from uniform weights, sum w = 1 and 0 <= w_i <= 1, default
    options, finite-difference gradient."""
    Ys = np.linalg.inv(covs)
    N, f = len(covs), _user_objective(criterion)
    res = minimize(lambda w: f(np.tensordot(w, Ys, 1)), np.full(N, 1.0 / N),
                   method="SLSQP", bounds=[(0.0, 1.0)] * N,
                   constraints={"type": "eq", "fun": lambda w: w.sum() - 1.0})
    return _peer_result(res.x, Ys, means, bool(res.success))


def fixed_weights_peer(means, covs, criterion) -> PeerResult:
    """CI with w_i = 1/N (for a pair, Stone Soup's default omega = 0.5)."""
    return _peer_result(np.full(len(covs), 1.0 / len(covs)), np.linalg.inv(covs), means,
                        True)


def fast_ci_peer(means, covs, criterion):
    """Fast CI (Niehsen 2002) as fusion-opt offers it."""
    return fo.fuse(means, covs, "fast-ci", criterion)
