"""Kalman filter: pure, batched predict/update steps, the measurement likelihood, and the
paper's baseline filter that takes every measurement as the target's.

For a model x_k = A x_{k-1} + q, y_k = H x_k + r (q ~ N(0, Q), r ~ N(0, R)):

    predict:  m- = A m,  P- = A P A^T + Q
    update:   v = y - H m-,  S = H P- H^T + R,  K = P- H^T S^-1,
              m = m- + K v,  P = P- - K S K^T
    likelihood:  p(y | past) = N(y; H m-, S).

The step functions take means (..., n) and covariances (..., n, n) with any leading batch
axes (e.g. one per particle), so a particle filter calls them once for all particles.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from trackers import _checks
from trackers.models import LinearGaussian

_LOG_2PI = np.log(2.0 * np.pi)


def predict(m: np.ndarray, P: np.ndarray, A: np.ndarray, Q: np.ndarray):
    """Kalman prediction. m (..., n), P (..., n, n), A (n, n), Q (n, n) -> (m-, P-)."""
    m_pred = m @ A.T
    P_pred = A @ P @ A.T + Q
    return m_pred, P_pred


def _innovation(m, P, y, H, R):
    """Innovation v (..., d), its covariance S (..., d, d) and the cross term P H^T."""
    PHt = P @ H.T
    S = H @ PHt + R
    v = y - m @ H.T
    return v, S, PHt


def _loglik_from(v, S):
    """log N(v; 0, S) batched, via Cholesky (S is positive definite)."""
    C = np.linalg.cholesky(S)
    # Solve C z = v; maha = |z|^2. np.linalg.solve on the triangular factor is batched.
    z = np.linalg.solve(C, v[..., None])[..., 0]
    logdet = 2.0 * np.sum(np.log(np.diagonal(C, axis1=-2, axis2=-1)), axis=-1)
    d = v.shape[-1]
    return -0.5 * (np.sum(z * z, axis=-1) + logdet + d * _LOG_2PI)


def update_with_loglik(m, P, y, H, R):
    """Kalman update plus the log-likelihood log N(y; H m, H P H^T + R) of the measurement.

    m (..., n), P (..., n, n), y (d,) or (..., d), H (d, n), R (d, d).
    Returns (m+, P+, loglik) with loglik of shape (...).
    """
    v, S, PHt = _innovation(m, P, y, H, R)
    # K^T = S^-1 (P H^T)^T, since S is symmetric; one batched solve for the gain.
    Kt = np.linalg.solve(S, np.swapaxes(PHt, -1, -2))
    K = np.swapaxes(Kt, -1, -2)
    m_new = m + (K @ v[..., None])[..., 0]
    P_new = P - PHt @ Kt  # = P - K S K^T
    P_new = 0.5 * (P_new + np.swapaxes(P_new, -1, -2))
    return m_new, P_new, _loglik_from(v, S)


def update(m, P, y, H, R):
    """Kalman update. m (..., n), P (..., n, n), y (d,) or (..., d) -> (m+, P+)."""
    m_new, P_new, _ = update_with_loglik(m, P, y, H, R)
    return m_new, P_new


def log_likelihood(m, P, y, H, R):
    """log N(y; H m, H P H^T + R) for predicted moments m (..., n), P (..., n, n)."""
    v, S, _ = _innovation(m, P, y, H, R)
    return _loglik_from(v, S)


@dataclass(frozen=True)
class FilterOutput:
    """Per-step filtered moments: means (T, n), covs (T, n, n)."""

    means: np.ndarray
    covs: np.ndarray


def check_prior(model: LinearGaussian, m0, P0):
    if not isinstance(model, LinearGaussian):
        raise ValueError(f"model must be a trackers.models.LinearGaussian, got {type(model)}")
    m0 = _checks.finite_array("m0", m0, shape=(model.n,))
    P0 = _checks.covariance("P0", P0, model.n)
    return m0, P0


def run(scans: Sequence, model: LinearGaussian, m0, P0) -> FilterOutput:
    """The paper's baseline: a Kalman filter with no data association.

    Each step predicts once (from the prior m0, P0 at time 0 to step 0's time, then step to
    step) and then updates with every measurement of the step, one at a time, as if each
    came from the target; a step with no measurement only predicts.
    """
    m, P = check_prior(model, m0, P0)
    scans = _checks.scans(scans, model.d)
    T = len(scans)
    means = np.empty((T, model.n))
    covs = np.empty((T, model.n, model.n))
    for t, ys in enumerate(scans):
        m, P = predict(m, P, model.A, model.Q)
        for y in ys:
            m, P = update(m, P, y, model.H, model.R)
        means[t], covs[t] = m, P
    return FilterOutput(means, covs)
