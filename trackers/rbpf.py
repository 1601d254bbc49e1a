"""Rao-Blackwellised particle filter for one target in clutter (Särkkä et al. 2007; paper §3.1).

Each particle i holds a Gaussian N(m_i, P_i) for the target (a Kalman filter conditional on
the particle's association history) and a log-weight l_i. For a measurement y the
association c is clutter (c = 0, prior pi_0 = clutter_prior, likelihood 1/V =
clutter_density) or the target (c = 1, prior 1 - pi_0, likelihood N(y; H m-_i, S_i)).
c is drawn from its optimal importance distribution

    p(c_i = j | y, past_i)  ∝  p(y | c_i = j, past_i) pi_j,

and then the weight update w_i <- w_i p(y|c) pi_c / p(c|y, past_i) reduces to

    w_i <- w_i * sum_j p(y | c_i = j, past_i) pi_j      (the predictive likelihood),

independent of the sampled c. Particles that drew c = 1 take the Kalman update; the others
keep their predicted moments. When ESS = 1 / sum w_i^2 falls below a threshold (default N/4)
the particles are resampled systematically and the weights reset to 1/N
(``trackers.resampling.end_of_step``). The step's estimate is the mixture's mean and
covariance, taken before resampling.

A measurement whose predictive likelihood is 0 in floating point for every particle (only
possible with clutter_prior = 0, for a squared Mahalanobis distance above ~1e308) cannot be
explained by any hypothesis: the step raises FusionInputError and the particles are
unchanged (the generator has moved on).

Time convention: m0, P0 describe the state at time 0 and the filter's first action is a
prediction to step 0's time (one dt later). With the simulators of ``trackers.scenarios``
(step k at time (k + 1) dt, x0 at time 0) this means m0, P0 is the prior for x0.

Every operation is on stacked arrays (N, n) and (N, n, n); there is no loop over particles.
``filter_step`` is the pure step; the class ``RBPF`` holds the particles between steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fusion_opt import FusionInputError
from fusion_opt.estimates import Estimates
from fusion_opt.validation import safe_repr, wide_float
from trackers import _checks, kalman
from trackers.models import LinearGaussian
from trackers.resampling import end_of_step, logsumexp


@dataclass(frozen=True, eq=False)  # == is identity, as for an Estimates
class RBPFOutput:
    """Per-step output of the RBPF.

    means (T, n): weighted mean sum_i w_i m_i after the step's updates.
    covs (T, n, n): mixture covariance sum_i w_i (P_i + (m_i - m)(m_i - m)^T).
    ess (T,): effective sample size after the step's updates, before any resampling.
    resampled (T,): whether the particles were resampled at the end of the step.
    """

    means: np.ndarray
    covs: np.ndarray
    ess: np.ndarray
    resampled: np.ndarray


class RBPFParams(NamedTuple):
    """Fixed settings of a filter: the model; log_clutter = log(pi_0 / V), the log of the
    clutter association's prior times likelihood; log_target = log(1 - pi_0); threshold:
    resample when ESS < threshold (a particle count)."""

    model: LinearGaussian
    log_clutter: float
    log_target: float
    threshold: float


class RBPFState(NamedTuple):
    """Particles: means m (N, n), covariances P (N, n, n), normalised log-weights logw (N,)."""

    m: np.ndarray
    P: np.ndarray
    logw: np.ndarray


class RBPFReport(NamedTuple):
    """One step's estimate, mean (n,) and cov (n, n), its ESS, and whether it resampled."""

    mean: np.ndarray
    cov: np.ndarray
    ess: float
    resampled: bool


def mixture_moments(w: np.ndarray, m: np.ndarray, P: np.ndarray):
    """Means (..., n) and covariances (..., n, n) of the Gaussian mixtures
    sum_i w_i N(m_i, P_i), one per row of weights.

    w (..., K) normalised weights (a zero weight ignores component i), m (K, n), P (K, n, n).
    """
    K, n = m.shape
    mean = w @ m
    dm = m - mean[..., None, :]  # (..., K, n)
    cov = (w @ P.reshape(K, n * n)).reshape(*w.shape[:-1], n, n)
    cov = cov + (dm * w[..., None]).swapaxes(-1, -2) @ dm
    return mean, 0.5 * (cov + cov.swapaxes(-1, -2))


def associate_step(m, P, logw, y, params: RBPFParams, rng):
    """Process one measurement y (d,) for all particles; returns (m, P, logw).

    Draws each particle's association from its optimal importance distribution and
    multiplies the weight by the predictive likelihood (see the module docstring).
    A particle for which y is impossible (predictive likelihood 0) gets weight 0.
    """
    model = params.model
    m_upd, P_upd, ll_target = kalman.update_with_loglik(m, P, y, model.H, model.R)
    log_joint = np.stack([np.full_like(ll_target, params.log_clutter),
                          ll_target + params.log_target])  # (2, N): clutter, target
    log_pred = logsumexp(log_joint, axis=0)
    with np.errstate(invalid="ignore"):  # NaN where log_pred = -inf: a weight-0 particle
        p_target = np.exp(log_joint[1] - log_pred)
    is_target = rng.random(p_target.shape[0]) < p_target
    m = np.where(is_target[:, None], m_upd, m)
    P = np.where(is_target[:, None, None], P_upd, P)
    return m, P, logw + log_pred


def filter_step(state: RBPFState, scan: np.ndarray, params: RBPFParams, rng):
    """One RBPF step: predict, associate each measurement of ``scan`` (k, d) in turn,
    report the mixture moments, resample if the ESS is low. Returns (RBPFState, RBPFReport).
    """
    model = params.model
    m, P = kalman.predict(state.m, state.P, model.A, model.Q)
    logw = state.logw
    for j, y in enumerate(scan):
        m, P, logw = associate_step(m, P, logw, y, params, rng)
        if logw.max() == -np.inf:
            raise FusionInputError(
                f"scan[{j}] = {y.tolist()} has likelihood 0 under every particle and "
                "clutter_prior = 0 rules out clutter: no hypothesis explains it")
    if np.isnan(logw).any() or np.isposinf(logw).any():  # fuzz K13: "logw must be finite"
        raise FusionInputError(
            "the particles' weights are not finite after this step: float64 cannot represent "
            "it (a measurement far beyond the model's scale, or a model and prior at "
            "float64's limits); the filter's state is the one before it")
    end = end_of_step(logw, params.threshold, rng)
    mean, cov = mixture_moments(end.weights, m, P)
    if end.ancestors is not None:
        m, P = m[end.ancestors], P[end.ancestors]
    return RBPFState(m, P, end.logw), RBPFReport(mean, cov, end.ess, end.ancestors is not None)


class RBPF:
    """The Rao-Blackwellised particle filter of the module docstring, one step at a time.

    RBPF(model, m0, P0, *, rng, n_particles=20, clutter_prior=0.5, clutter_density=1/80,
    resample_threshold=0.25, name=None): model the filter's LinearGaussian; m0 (n,), P0
    (n, n) the prior at time 0 (all particles start there); rng a numpy Generator;
    clutter_prior the prior probability that a measurement is clutter; clutter_density the
    clutter likelihood 1/V (> 0); resample when ESS < resample_threshold * n_particles.

    ``step(scan, time=None)`` takes the measurements (k, d) of one step (k may be 0) and
    returns an Estimates with one estimate, the mixture mean (1, n) and covariance
    (1, n, n), whose id is always 0: the one target, for as long as the filter runs.
    ``time`` is stamped on it as given (None by default) and ``name`` as its node.
    Read-only state: ``means`` (N, n), ``covs`` (N, n, n), ``log_weights`` (N,,
    normalised), ``steps``, and of the last step ``ess`` (before resampling) and
    ``resampled``.
    """

    def __init__(self, model: LinearGaussian, m0, P0, *, rng: np.random.Generator,
                 n_particles: int = 20, clutter_prior: float = 0.5,
                 clutter_density: float = 1 / 80, resample_threshold: float = 0.25,
                 name=None):
        m0, P0 = kalman.check_prior(model, m0, P0)
        self._rng = _checks.generator("rng", rng)
        N = _checks.positive_int("n_particles", n_particles)
        _checks.fits(f"n_particles = {safe_repr(N)}",
                     8.0 * 8 * wide_float(N) * (model.n**2 + model.n + 1))
        cp = _checks.probability("clutter_prior", clutter_prior)
        cd = _checks.positive("clutter_density", clutter_density)
        thr = _checks.probability("resample_threshold", resample_threshold) * N
        with np.errstate(divide="ignore"):  # log(0) = -inf removes that association exactly
            self.params = RBPFParams(model, np.log(cp) + np.log(cd), np.log1p(-cp), thr)
        self.name = _checks.node_name(name)
        self._state = RBPFState(np.broadcast_to(m0, (N, model.n)).copy(),
                                np.broadcast_to(P0, (N, model.n, model.n)).copy(),
                                np.full(N, -np.log(N)))
        self._steps, self._ess, self._resampled = 0, float(N), False
        self._time = None  # stamped on the last step

    @property
    def means(self) -> np.ndarray:
        """(N, n) particle means (after the last step's resampling, if any)."""
        return _checks.read_only(self._state.m)

    @property
    def covs(self) -> np.ndarray:
        """(N, n, n) particle covariances."""
        return _checks.read_only(self._state.P)

    @property
    def log_weights(self) -> np.ndarray:
        """(N,) normalised log-weights."""
        return _checks.read_only(self._state.logw)

    @property
    def steps(self) -> int:
        """Number of steps taken."""
        return self._steps

    @property
    def ess(self) -> float:
        """Effective sample size of the last step, before its resampling (N before any)."""
        return self._ess

    @property
    def resampled(self) -> bool:
        """Whether the last step resampled."""
        return self._resampled

    def _advance(self, scan: np.ndarray, name: str = "scan") -> RBPFReport:
        """One step on a checked scan (k, d); the state changes only if it succeeds."""
        with np.errstate(over="ignore", invalid="ignore"):  # refused just below
            state, report = filter_step(self._state, scan, self.params, self._rng)
        report = report._replace(
            cov=_checks.step_estimates(name, self._steps, report.mean, report.cov))
        self._state = state
        self._steps += 1
        self._ess, self._resampled = report.ess, report.resampled
        return report

    def step(self, scan, time=None) -> Estimates:
        """Predict, associate every measurement of ``scan`` (k, d), report (id 0)."""
        time = _checks.step_time(time, self._time)
        r = self._advance(_checks.scan("scan", scan, self.params.model.d))
        self._time = self._time if time is None else time
        return _checks.report(r.mean[None], r.cov[None], None, time, self.name)


def run(scans: Sequence, model: LinearGaussian, m0, P0, *, rng: np.random.Generator,
        n_particles: int = 20, clutter_prior: float = 0.5, clutter_density: float = 1 / 80,
        resample_threshold: float = 0.25) -> RBPFOutput:
    """Run the RBPF over ``scans`` (sequence of T arrays (k_t, d), k_t may be 0): a loop
    over ``RBPF.step`` (the moments without the Estimates wrapper). The arguments are those
    of ``RBPF``.
    """
    pf = RBPF(model, m0, P0, rng=rng, n_particles=n_particles, clutter_prior=clutter_prior,
              clutter_density=clutter_density, resample_threshold=resample_threshold)
    scans = _checks.scans(scans, model.d)
    T, n = len(scans), model.n
    means, covs = np.empty((T, n)), np.empty((T, n, n))
    ess, resampled = np.empty(T), np.zeros(T, dtype=bool)
    for t, scan in enumerate(scans):
        means[t], covs[t], ess[t], resampled[t] = pf._advance(scan, f"scans[{t}]")
    return RBPFOutput(means, covs, ess, resampled)
