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
the particles are resampled systematically and the weights reset to 1/N.

Time convention: m0, P0 describe the state at time 0 and the filter's first action is a
prediction to step 0's time (one dt later). With the simulators of ``trackers.scenarios``
(step k at time (k + 1) dt, x0 at time 0) this means m0, P0 is the prior for x0.

Every operation is on stacked arrays (N, n) and (N, n, n); there is no loop over particles.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from trackers import _checks, kalman
from trackers.models import LinearGaussian
from trackers.resampling import logsumexp, systematic_resample


@dataclass(frozen=True)
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


def mixture_moments(w: np.ndarray, m: np.ndarray, P: np.ndarray):
    """Mean (n,) and covariance (n, n) of the Gaussian mixture sum_i w_i N(m_i, P_i).

    w (N,) normalised weights, m (N, n), P (N, n, n).
    """
    mean = w @ m
    dm = m - mean
    cov = np.einsum("i,ijk->jk", w, P) + np.einsum("i,ij,ik->jk", w, dm, dm)
    return mean, 0.5 * (cov + cov.T)


def associate_step(m, P, logw, y, model: LinearGaussian, log_prior_clutter, log_prior_target,
                   log_density, rng):
    """Process one measurement y (d,) for all particles; returns (m, P, logw).

    Draws each particle's association from its optimal importance distribution and
    multiplies the weight by the predictive likelihood (see the module docstring).
    """
    m_upd, P_upd, ll_target = kalman.update_with_loglik(m, P, y, model.H, model.R)
    log_joint = np.stack(
        [np.full_like(ll_target, log_prior_clutter + log_density), ll_target + log_prior_target]
    )  # (2, N): row 0 clutter, row 1 target
    log_pred = logsumexp(log_joint, axis=0)
    p_target = np.exp(log_joint[1] - log_pred)
    is_target = rng.random(p_target.shape[0]) < p_target
    m = np.where(is_target[:, None], m_upd, m)
    P = np.where(is_target[:, None, None], P_upd, P)
    return m, P, logw + log_pred


def run(
    scans: Sequence,
    model: LinearGaussian,
    m0,
    P0,
    *,
    rng: np.random.Generator,
    n_particles: int = 20,
    clutter_prior: float = 0.5,
    clutter_density: float = 1 / 80,
    resample_threshold: float = 0.25,
) -> RBPFOutput:
    """Run the RBPF over ``scans`` (sequence of T arrays (k_t, d), k_t may be 0).

    model: the filter's LinearGaussian model; m0 (n,), P0 (n, n): prior at time 0 (all
    particles start there). rng: numpy Generator. clutter_prior: prior probability that a
    measurement is clutter; clutter_density: clutter likelihood 1/V (> 0).
    resample_threshold: resample when ESS < resample_threshold * n_particles.
    """
    m0, P0 = kalman.check_prior(model, m0, P0)
    scans = _checks.scans(scans, model.d)
    rng = _checks.generator("rng", rng)
    N = _checks.positive_int("n_particles", n_particles)
    cp = _checks.probability("clutter_prior", clutter_prior)
    cd = _checks.positive("clutter_density", clutter_density)
    thr = _checks.probability("resample_threshold", resample_threshold) * N

    # log(0) = -inf is intended: a zero prior removes that association exactly.
    with np.errstate(divide="ignore"):
        log_pc, log_pt = np.log(cp), np.log1p(-cp)
    log_cd = np.log(cd)

    T, n = len(scans), model.n
    m = np.broadcast_to(m0, (N, n)).copy()
    P = np.broadcast_to(P0, (N, n, n)).copy()
    logw = np.full(N, -np.log(N))
    means = np.empty((T, n))
    covs = np.empty((T, n, n))
    ess = np.empty(T)
    resampled = np.zeros(T, dtype=bool)

    for t, ys in enumerate(scans):
        m, P = kalman.predict(m, P, model.A, model.Q)
        for y in ys:
            m, P, logw = associate_step(m, P, logw, y, model, log_pc, log_pt, log_cd, rng)
        logw = logw - logsumexp(logw)
        w = np.exp(logw)
        means[t], covs[t] = mixture_moments(w, m, P)
        ess[t] = 1.0 / np.sum(w * w)
        if ess[t] < thr:
            idx = systematic_resample(logw, rng)
            m, P = m[idx], P[idx]
            logw = np.full(N, -np.log(N))
            resampled[t] = True
    return RBPFOutput(means, covs, ess, resampled)
