"""Kalman filter: pure, batched predict/update steps, the measurement likelihood, the
paper's baseline filter that takes every measurement as the target's, and the joint error
covariance of N such filters tracking one target.

For a model x_k = A x_{k-1} + q, y_k = H x_k + r (q ~ N(0, Q), r ~ N(0, R)):

    predict:  m- = A m,  P- = A P A^T + Q
    update:   v = y - H m-,  S = H P- H^T + R,  K = P- H^T S^-1,
              m = m- + K v,  P = (I - K H) P- (I - K H)^T + K R K^T
    likelihood:  p(y | past) = N(y; H m-, S).

P is updated in Joseph's form (Bucy & Joseph 1968), a sum of two positive semidefinite
terms, not as P- - K S K^T: where P- is far above R (a vague prior, a long run of misses)
that difference cancels to rounding; at P- = 1e16 R it left P indefinite and a Table 1 run
with prior_cov = 1e16 failed at its second step. Joseph's form matches the exact update
there (tests/test_trackers_kalman.py) for two more small products per update. The updated
P then has a condition of about P- / R (velocities at P-, positions at R), which float64
holds positive definite only up to about 1/eps and a fusion accepts up to 7e13: the
scenario configurations refuse a prior beyond that (scenarios._check_prior_ratio).

The step functions take means (..., n) and covariances (..., n, n) with any leading batch
axes (e.g. one per particle), so a particle filter calls them once for all particles.
They are the unchecked numerical core, as in dynamax: they trust their inputs (finite,
shapes that match, S positive definite), which the filters check once per step at their
entry (``KalmanFilter``, ``run``, ``rbpf.RBPF``, ``rbmcda.RBMCDA``) and whose results they
check before keeping them; called directly, a NaN measurement gives a NaN mean and a
singular S numpy's LinAlgError. Data from outside goes through a filter.

N filters of one target with a common model (nodes i = 1..N, each with its own measurement
y_i = H x + r_i, the r_i independent) have errors e_i = x - m_i that are correlated through
the common process noise and prior. Their joint covariance C_ij = E[e_i e_j^T] follows

    C_ij <- (I - K_i H)(A C_ij A^T + Q)(I - K_j H)^T + [i = j] K_i R K_i^T,

with K_i node i's gain (0 when it missed); C_ii is node i's own P (``cross_covariance_step``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fusion_opt import FusionInputError
from fusion_opt.estimates import Estimates
from trackers import _checks
from trackers.models import LinearGaussian

_LOG_2PI = np.log(2.0 * np.pi)


def predict(m: np.ndarray, P: np.ndarray, A: np.ndarray, Q: np.ndarray):
    """Kalman prediction. m (..., n), P (..., n, n), A (n, n), Q (n, n) -> (m-, P-)."""
    m_pred = m @ A.T
    P_pred = A @ P @ A.T + Q
    return m_pred, P_pred


def innovation(m, P, y, H, R):
    """Innovation v = y - H m (..., d), its covariance S = H P H^T + R (..., d, d) and the
    cross term P H^T (..., n, d), for m (..., n), P (..., n, n), y (d,) or (..., d)."""
    PHt = P @ H.T
    S = H @ PHt + R
    v = y - m @ H.T
    return v, S, PHt


def innovation_loglik(v, S):
    """log N(v; 0, S) batched, via Cholesky (S is positive definite); -inf where the squared
    Mahalanobis distance overflows."""
    C = np.linalg.cholesky(S)
    # Solve C z = v; maha = |z|^2. np.linalg.solve on the triangular factor is batched.
    z = np.linalg.solve(C, v[..., None])[..., 0]
    logdet = 2.0 * np.log(np.diagonal(C, axis1=-2, axis2=-1)).sum(axis=-1)
    with np.errstate(over="ignore"):  # |z| > 1e154: the density is 0 in floating point
        maha = (z * z).sum(axis=-1)
    return -0.5 * (maha + logdet + v.shape[-1] * _LOG_2PI)


def _gain_t(S, PHt):
    """K^T = S^-1 (P H^T)^T (..., d, n), since S is symmetric; one batched solve."""
    return np.linalg.solve(S, PHt.swapaxes(-1, -2))


def update_innovation(m, P, v, S, PHt, H, R):
    """Kalman update from the innovation (v, S, PHt) of ``innovation``: (m+, P+), P+ in
    Joseph's form (module docstring)."""
    Kt = _gain_t(S, PHt)
    m_new = m + (v[..., None, :] @ Kt)[..., 0, :]  # m + K v
    K = Kt.swapaxes(-1, -2)
    I_KH = np.eye(P.shape[-1]) - K @ H
    P_new = I_KH @ P @ I_KH.swapaxes(-1, -2) + K @ R @ Kt
    return m_new, 0.5 * (P_new + P_new.swapaxes(-1, -2))


def update_with_loglik(m, P, y, H, R):
    """Kalman update plus the log-likelihood log N(y; H m, H P H^T + R) of the measurement.

    m (..., n), P (..., n, n), y (d,) or (..., d), H (d, n), R (d, d).
    Returns (m+, P+, loglik) with loglik of shape (...).
    """
    v, S, PHt = innovation(m, P, y, H, R)
    return *update_innovation(m, P, v, S, PHt, H, R), innovation_loglik(v, S)


def update(m, P, y, H, R):
    """Kalman update. m (..., n), P (..., n, n), y (d,) or (..., d) -> (m+, P+)."""
    return update_innovation(m, P, *innovation(m, P, y, H, R), H, R)


def log_likelihood(m, P, y, H, R):
    """log N(y; H m, H P H^T + R) for predicted moments m (..., n), P (..., n, n)."""
    v, S, _ = innovation(m, P, y, H, R)
    return innovation_loglik(v, S)


def filter_step(m, P, scan, model: LinearGaussian):
    """One step of the baseline filter: predict, then update with every measurement of
    ``scan`` (k, d) in turn, as if each came from the target (k = 0: predict only).

    m (n,), P (n, n) -> (m, P) after the step; P is symmetrised (the prediction alone leaves
    a rounding asymmetry).
    """
    m, P = predict(m, P, model.A, model.Q)
    for y in scan:
        m, P = update(m, P, y, model.H, model.R)
    return m, 0.5 * (P + P.T)


def cross_covariance_step(C, detected, model: LinearGaussian):
    """One step of the joint error covariance of N Kalman filters of one target.

    C (N, N, n, n): C[i, j] = E[e_i e_j^T] of the filters' errors e_i = x - m_i after the
    previous step (C[i, i] is filter i's P; a common prior gives C[i, j] = P0 for all i, j).
    detected (N,) bool: whether node i updates with a measurement y_i = H x + r_i this step
    (r_i ~ N(0, R), independent across nodes and of everything else); a node that missed
    only predicts.

    Returns (C, K): C (N, N, n, n) after the step,
        C_ij = (I - K_i H)(A C_ij A^T + Q)(I - K_j H)^T + [i = j] K_i R K_i^T,
    and K (N, n, d) the gains, K_i = P-_i H^T (H P-_i H^T + R)^-1 from node i's predicted
    covariance P-_i = A C_ii A^T + Q, and 0 for a node that missed. They are each filter's
    own gain, so m_i <- A m_i + K_i (y_i - H A m_i) updates the means that go with C.
    """
    if not isinstance(model, LinearGaussian):
        raise FusionInputError(
            f"model must be a trackers.models.LinearGaussian, got {type(model).__name__}")
    C = _checks.finite_array("C", C, ndim=4)
    N, n = C.shape[0], model.n
    if C.shape != (N, N, n, n) or N == 0:
        raise FusionInputError(f"C must have shape (N, N, {n}, {n}) with N >= 1, got {C.shape}")
    detected = np.asarray(detected)
    if detected.dtype != bool or detected.shape != (N,):
        raise FusionInputError(f"detected must be a boolean array of shape ({N},), got "
                               f"{detected.dtype} {detected.shape}")
    _check_joint(C)
    A, Q, H, R = model.A, model.Q, model.H, model.R
    C = A @ C @ A.T + Q  # e-_i = A e_i + q with the same q for every node
    P = C[np.arange(N), np.arange(N)]
    S = H @ P @ H.T + R
    K = np.swapaxes(_gain_t(S, P @ H.T), -1, -2) * detected[:, None, None]  # (N, n, d)
    M = np.eye(n) - K @ H  # e+_i = M_i e-_i - K_i r_i
    C = M[:, None] @ C @ np.swapaxes(M, -1, -2)[None, :]
    C[np.arange(N), np.arange(N)] += K @ R @ np.swapaxes(K, -1, -2)
    with np.errstate(over="ignore", invalid="ignore"):  # refused just below
        C = 0.5 * (C + np.swapaxes(np.swapaxes(C, 0, 1), -1, -2))
    if not np.isfinite(C).all():
        raise FusionInputError("C: the step's joint covariance overflows float64")
    return C, K


def _check_joint(C: np.ndarray) -> None:
    """C (N, N, n, n) symmetric as a joint covariance (C[i, j] = C[j, i]^T, within 1e-8 of
    its largest entry) with positive semidefinite diagonal blocks (a covariance's own)."""
    scale = np.abs(C).max()
    if np.abs(C - np.swapaxes(np.swapaxes(C, 0, 1), -1, -2)).max() > 1e-8 * scale:
        raise FusionInputError("C must be symmetric: C[i, j] = C[j, i]^T")
    N = C.shape[0]
    low = np.linalg.eigvalsh(C[np.arange(N), np.arange(N)])[:, 0]
    if (low < -1e-10 * scale).any():
        i = int(np.flatnonzero(low < -1e-10 * scale)[0])
        raise FusionInputError(f"C[{i}, {i}], filter {i}'s covariance, is not positive "
                               f"semidefinite (smallest eigenvalue {low[i]:.3g})")


@dataclass(frozen=True, eq=False)  # == is identity, as for an Estimates
class FilterOutput:
    """Per-step filtered moments: means (T, n), covs (T, n, n)."""

    means: np.ndarray
    covs: np.ndarray


def check_prior(model: LinearGaussian, m0, P0):
    """The checked prior m0 (n,), P0 (n, n) of a filter of `model`, as copies: a filter
    keeps its own (fuzz8 2: KalmanFilter started from, and RBMCDA gave each new target,
    whatever the caller's m0 and P0 held at the time, a caller reusing its buffers)."""
    if not isinstance(model, LinearGaussian):
        raise FusionInputError(
            f"model must be a trackers.models.LinearGaussian, got {type(model).__name__}")
    m0 = _checks.finite_array("m0", m0, shape=(model.n,))
    P0 = _checks.covariance("P0", P0, model.n)
    return m0.copy(), P0.copy()


class KalmanFilter:
    """The paper's baseline Kalman filter (no data association), one step at a time.

    KalmanFilter(model, m0, P0, *, name=None): model a LinearGaussian; m0 (n,), P0 (n, n) the
    prior at time 0, so the first step predicts to step 0's time. ``step(scan, time=None)``
    takes the measurements (k, d) of one step (k may be 0) and returns an Estimates with one
    estimate (mean (1, n), cov (1, n, n)) whose id is always 0: the one target, for as long as
    the filter runs. ``time`` is stamped on it as given (None by default) and ``name`` as
    its node. ``mean``, ``cov`` (read-only) and ``steps`` show the current state.
    """

    def __init__(self, model: LinearGaussian, m0, P0, *, name=None):
        self._m, self._P = check_prior(model, m0, P0)
        self.model = model
        self.name = _checks.node_name(name)
        self._steps, self._time = 0, None

    @property
    def mean(self) -> np.ndarray:
        """(n,) filtered mean after the last step (the prior m0 before the first)."""
        return _checks.read_only(self._m)

    @property
    def cov(self) -> np.ndarray:
        """(n, n) filtered covariance after the last step (the prior P0 before the first)."""
        return _checks.read_only(self._P)

    @property
    def steps(self) -> int:
        """Number of steps taken."""
        return self._steps

    def _advance(self, scan: np.ndarray, name: str = "scan") -> np.ndarray:
        """One step on a checked scan (k, d); the state changes only if it succeeds.
        Returns the checked covariance (n, n) (`_checks.step_estimates`)."""
        with np.errstate(over="ignore", invalid="ignore"):  # refused just below
            m, P = filter_step(self._m, self._P, scan, self.model)
        checked = _checks.step_estimates(name, self._steps, m, P)
        self._m, self._P = m, P
        self._steps += 1
        return checked

    def step(self, scan, time=None) -> Estimates:
        """Predict, update with every measurement of ``scan`` (k, d), report (id 0)."""
        time = _checks.step_time(time, self._time)
        cov = self._advance(_checks.scan("scan", scan, self.model.d))
        self._time = self._time if time is None else time
        return _checks.report(self._m[None].copy(), cov[None], None, time, self.name)


def run(scans: Sequence, model: LinearGaussian, m0, P0) -> FilterOutput:
    """The paper's baseline over ``scans`` (T arrays (k_t, d)): a loop over
    ``KalmanFilter.step`` (the moments without the Estimates wrapper).

    Each step predicts once (from the prior m0, P0 at time 0 to step 0's time, then step to
    step) and then updates with every measurement of the step, one at a time, as if each
    came from the target; a step with no measurement only predicts.
    """
    kf = KalmanFilter(model, m0, P0)
    scans = _checks.scans(scans, model.d)
    means = np.empty((len(scans), model.n))
    covs = np.empty((len(scans), model.n, model.n))
    for t, scan in enumerate(scans):  # step() less the Estimates it wraps the moments in
        kf._advance(scan, f"scans[{t}]")
        means[t], covs[t] = kf.mean, kf.cov
    return FilterOutput(means, covs)
