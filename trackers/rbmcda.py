"""Rao-Blackwellised Monte Carlo data association (RBMCDA) for an unknown number of targets
(Särkkä, Vehtari & Lampinen 2007; paper §3.2).

Each particle i holds a list of alive targets, each a Kalman filter N(m_ij, P_ij) with a
unique id (unique over all particles, assigned at birth and inherited through resampling)
and the time tau_ij of its last associated measurement, plus a log-weight l_i.

Per step (time t_k = (k + 1) dt; the prior state is at time 0):

1. Predict every target with the Kalman prediction.
2. Deaths, drawn from their prior (independent of the measurements): target j of particle
   i, alive at t_{k-1}, dies before t_k with probability
       1 - S(t_k - tau_ij) / S(t_{k-1} - tau_ij),
   S the survival function of the Gamma(lifetime_shape, scale=lifetime_scale) lifetime.
3. Each measurement y of the step, one at a time. With T_i alive targets the joint prior of
   (birth, association) is
       birth (new target):         p_b
       clutter:                    (1 - p_b) pi_c
       existing target j:          (1 - p_b) (1 - pi_c) / T_i,
   and when T_i = 0 it is conditioned on there being no existing target to pick, i.e. birth
   and clutter keep the odds p_b : (1 - p_b) pi_c (as the RBMCDA toolbox does by
   normalising its event priors),
   with likelihoods N(y; H m0, H P0 H^T + R) (birth, from the new-target prior),
   clutter_density (clutter) and N(y; H m-_ij, S_ij) (target j). The association is drawn
   from its optimal importance distribution (prior x likelihood, normalised) and the weight
   is multiplied by the predictive likelihood sum_c prior_c lik_c, as in ``trackers.rbpf``.
   The chosen target takes the Kalman update and tau_ij = t_k; a birth adds a target
   initialised by updating the prior (m0, P0) with y.
4. Resample systematically when ESS < resample_threshold * N.

Vectorisation: targets are padded into arrays (N, C, n), (N, C, n, n) with an alive mask
(N, C); C grows (doubles) when a particle needs a new slot. All steps above are array
operations over particles and slots; there is no Python loop over particles.

Track extraction (the per-step output): take the particle with the largest weight after
the step's updates (the MAP association hypothesis); its alive targets are the reported
targets. For each reported id u, its mean and covariance are the moments of the mixture
over all particles in which u is alive, with their weights renormalised:
    m_u = sum_i w_i m_iu / W_u,   P_u = sum_i w_i (P_iu + (m_iu - m_u)(.)^T) / W_u.
So the number of targets and their ids follow the most probable hypothesis, and each
target's moments use every particle that shares that target (after resampling, usually all).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.stats import gamma

from trackers import _checks, kalman
from trackers.models import LinearGaussian
from trackers.rbpf import mixture_moments
from trackers.resampling import logsumexp, systematic_resample


class Track(NamedTuple):
    """One reported target: id, mean (n,), covariance (n, n)."""

    target_id: int
    mean: np.ndarray
    cov: np.ndarray


@dataclass(frozen=True)
class RBMCDAOutput:
    """Per-step output of RBMCDA; indexing it gives ``tracks[t]``.

    tracks: T tuples of Track (the extraction rule is in the module docstring).
    ess (T,): effective sample size after the step's updates, before any resampling.
    expected_n_targets (T,): sum_i w_i T_i, the posterior mean number of targets.
    resampled (T,): whether the particles were resampled at the end of the step.
    """

    tracks: tuple
    ess: np.ndarray
    expected_n_targets: np.ndarray
    resampled: np.ndarray

    def __getitem__(self, t):
        return self.tracks[t]

    def __len__(self) -> int:
        return len(self.tracks)

    def __iter__(self):
        return iter(self.tracks)

    @property
    def n_targets(self) -> np.ndarray:
        """(T,) number of reported targets at each step."""
        return np.array([len(tr) for tr in self.tracks])


class _Particles:
    """Padded per-particle target arrays. Mutable working state of one ``run`` call."""

    def __init__(self, N: int, m0: np.ndarray, P0: np.ndarray, capacity: int = 4):
        n = m0.shape[0]
        self.m0, self.P0 = m0, P0
        self.M = np.broadcast_to(m0, (N, capacity, n)).copy()
        self.P = np.broadcast_to(P0, (N, capacity, n, n)).copy()
        self.alive = np.zeros((N, capacity), dtype=bool)
        self.ids = np.full((N, capacity), -1, dtype=np.int64)
        self.tau = np.zeros((N, capacity))

    def grow(self) -> None:
        """Double the number of slots (new slots are dead and hold the prior)."""
        N, C, n = self.M.shape
        self.M = np.concatenate([self.M, np.broadcast_to(self.m0, (N, C, n))], axis=1)
        self.P = np.concatenate([self.P, np.broadcast_to(self.P0, (N, C, n, n))], axis=1)
        self.alive = np.concatenate([self.alive, np.zeros((N, C), dtype=bool)], axis=1)
        self.ids = np.concatenate([self.ids, np.full((N, C), -1, dtype=np.int64)], axis=1)
        self.tau = np.concatenate([self.tau, np.zeros((N, C))], axis=1)

    def kill(self, dead: np.ndarray) -> None:
        """Remove the targets in mask ``dead`` (N, C); their slots return to the prior, which
        keeps the (ignored) dead slots finite and well conditioned."""
        self.alive &= ~dead
        self.ids[dead] = -1
        self.M[dead] = self.m0
        self.P[dead] = self.P0

    def take(self, idx: np.ndarray) -> None:
        for name in ("M", "P", "alive", "ids", "tau"):
            setattr(self, name, getattr(self, name)[idx])


def _extract(parts: _Particles, w: np.ndarray) -> tuple:
    """Tracks of the MAP particle, each with mixture moments over the particles sharing it."""
    best = int(np.argmax(w))
    tracks = []
    for slot in np.flatnonzero(parts.alive[best]):
        uid = parts.ids[best, slot]
        rows, cols = np.nonzero(parts.ids == uid)  # at most one slot per particle
        wu = w[rows] / w[rows].sum()
        mean, cov = mixture_moments(wu, parts.M[rows, cols], parts.P[rows, cols])
        tracks.append(Track(int(uid), mean, cov))
    return tuple(tracks)


def run(
    scans: Sequence,
    model: LinearGaussian,
    m0,
    P0,
    *,
    rng: np.random.Generator,
    dt: float,
    n_particles: int = 20,
    birth_prob: float = 0.01,
    lifetime_shape: float = 2.0,
    lifetime_scale: float = 0.5,
    clutter_prior: float = 0.05,
    clutter_density: float = 1 / 16,
    resample_threshold: float = 0.25,
) -> RBMCDAOutput:
    """Run RBMCDA over ``scans`` (sequence of T arrays (k_t, d), k_t may be 0).

    model: LinearGaussian with step dt; m0 (n,), P0 (n, n): the prior of a new-born target;
    dt: the step length (s), used for the lifetimes (step k is at time (k + 1) dt);
    birth_prob: prior probability that a measurement comes from a new target;
    lifetime_shape, lifetime_scale: Gamma lifetime since the last associated measurement;
    clutter_prior: prior probability that a measurement is clutter given no birth;
    clutter_density: clutter likelihood 1/V; resample when ESS < resample_threshold * N.
    Returns an RBMCDAOutput; ``out[t]`` is the tuple of Track(target_id, mean, cov) at step t.
    """
    m0, P0 = kalman.check_prior(model, m0, P0)
    scans = _checks.scans(scans, model.d)
    rng = _checks.generator("rng", rng)
    dt = _checks.positive("dt", dt)
    N = _checks.positive_int("n_particles", n_particles)
    pb = _checks.probability("birth_prob", birth_prob)
    life = gamma(_checks.positive("lifetime_shape", lifetime_shape),
                 scale=_checks.positive("lifetime_scale", lifetime_scale))
    cp = _checks.probability("clutter_prior", clutter_prior)
    log_cd = np.log(_checks.positive("clutter_density", clutter_density))
    thr = _checks.probability("resample_threshold", resample_threshold) * N
    if pb == 0.0 and cp == 0.0:
        # no target can ever be born, and a measurement may not be clutter: nothing explains it
        raise ValueError("birth_prob and clutter_prior must not both be 0")
    H, R = model.H, model.R

    with np.errstate(divide="ignore"):  # log(0) = -inf removes an option exactly
        log_pb, log_1mpb = np.log(pb), np.log1p(-pb)
        log_cp, log_1mcp = np.log(cp), np.log1p(-cp)

    parts = _Particles(N, m0, P0)
    logw = np.full(N, -np.log(N))
    next_id = 0
    T = len(scans)
    tracks, ess = [], np.empty(T)
    expected_n, resampled = np.empty(T), np.zeros(T, dtype=bool)

    for k, ys in enumerate(scans):
        t_prev, t = k * dt, (k + 1) * dt
        parts.M, parts.P = kalman.predict(parts.M, parts.P, model.A, model.Q)

        if parts.alive.any():
            # survival ratio S(t - tau) / S(t_prev - tau); logsf avoids 0/0 for old targets
            log_surv = life.logsf(t - parts.tau) - life.logsf(t_prev - parts.tau)
            dies = parts.alive & (np.log(rng.random(parts.alive.shape)) >= log_surv)
            parts.kill(dies)

        for y in ys:
            n_alive = parts.alive.sum(axis=1)
            M_upd, P_upd, ll = kalman.update_with_loglik(parts.M, parts.P, y, H, R)
            m_b, P_b, ll_b = kalman.update_with_loglik(m0, P0, y, H, R)
            # priors as in the docstring; with no target alive, renormalise birth vs clutter
            with np.errstate(divide="ignore"):
                log_norm = np.where(n_alive > 0, 0.0, np.logaddexp(log_pb, log_1mpb + log_cp))
                log_prior_c = log_1mpb + log_cp - log_norm
                log_prior_b = log_pb - log_norm
                log_prior_t = log_1mpb + log_1mcp - np.log(np.maximum(n_alive, 1))
            log_joint = np.empty((N, parts.alive.shape[1] + 2))
            log_joint[:, 0] = log_prior_c + log_cd
            log_joint[:, 1] = log_prior_b + ll_b
            log_joint[:, 2:] = np.where(parts.alive, ll + log_prior_t[:, None], -np.inf)
            log_pred = logsumexp(log_joint, axis=1)
            logw = logw + log_pred

            # draw the association from the optimal importance distribution (inverse CDF)
            cdf = np.cumsum(np.exp(log_joint - log_pred[:, None]), axis=1)
            u = rng.random(N) * cdf[:, -1]
            choice = np.minimum((cdf < u[:, None]).sum(axis=1), log_joint.shape[1] - 1)

            r = np.flatnonzero(choice >= 2)
            s = choice[r] - 2
            parts.M[r, s], parts.P[r, s], parts.tau[r, s] = M_upd[r, s], P_upd[r, s], t

            b = np.flatnonzero(choice == 1)
            if b.size:
                if parts.alive[b].all(axis=1).any():
                    parts.grow()
                s = np.argmin(parts.alive[b], axis=1)  # first free slot
                parts.M[b, s], parts.P[b, s], parts.tau[b, s] = m_b, P_b, t
                parts.alive[b, s] = True
                parts.ids[b, s] = next_id + np.arange(b.size)
                next_id += b.size

        logw = logw - logsumexp(logw)
        w = np.exp(logw)
        tracks.append(_extract(parts, w))
        ess[k] = 1.0 / np.sum(w * w)
        expected_n[k] = w @ parts.alive.sum(axis=1)
        if ess[k] < thr:
            idx = systematic_resample(logw, rng)
            parts.take(idx)
            logw = np.full(N, -np.log(N))
            resampled[k] = True
    return RBMCDAOutput(tuple(tracks), ess, expected_n, resampled)
