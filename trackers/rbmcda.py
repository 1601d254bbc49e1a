"""Rao-Blackwellised Monte Carlo data association (RBMCDA) for an unknown number of targets
(Särkkä, Vehtari & Lampinen 2007; paper §3.2).

Each particle i holds a list of alive targets, each a Kalman filter N(m_ij, P_ij) with a
unique id (unique over all particles, assigned at birth and inherited through resampling)
and the time tau_ij of its last associated measurement, plus a log-weight l_i.

Per step (time t_k = (k + 1) dt; the prior state is at time 0):

1. Predict every target with the Kalman prediction.
2. Deaths, drawn from their prior (independent of the measurements): target j of particle
   i, alive at t_{k-1}, survives to t_k with probability
       S(t_k - tau_ij) / S(t_{k-1} - tau_ij),
   S(a) = Q(lifetime_shape, a / lifetime_scale) the survival function of the
   Gamma(lifetime_shape, scale=lifetime_scale) lifetime (Q the regularised upper
   incomplete gamma function). A target so old that S(t_{k-1} - tau_ij) underflows to 0
   dies.
3. Each measurement y of the step, one at a time. With T_i alive targets the joint prior of
   (birth, association) is
       birth (new target):         p_b
       clutter:                    (1 - p_b) pi_c
       existing target j:          (1 - p_b) (1 - pi_c) / T_i,
   and when T_i = 0 it is conditioned on there being no existing target to pick, i.e. birth
   and clutter keep the odds p_b : (1 - p_b) pi_c (as the RBMCDA toolbox does by
   normalising its event priors),
   with likelihoods N(y; H m0, H P0 H^T + R) (birth, from the new-target prior m0, P0 as
   given, not predicted), clutter_density (clutter) and N(y; H m-_ij, S_ij) (target j).
   The association is drawn from its optimal importance distribution (prior x likelihood,
   normalised) and the weight is multiplied by the predictive likelihood
   sum_c prior_c lik_c, as in ``trackers.rbpf``. The chosen target takes the Kalman update
   and tau_ij = t_k; a birth adds a target initialised by updating the prior (m0, P0) with
   y. A measurement with predictive likelihood 0 for every particle (clutter_prior = 0 and
   a squared Mahalanobis distance above ~1e308 from every target and from the birth prior)
   raises FusionInputError; the particles are then unchanged (the generator has
   moved on).
4. Resample systematically when ESS < resample_threshold * N
   (``trackers.resampling.end_of_step``).

Vectorisation: targets are padded into arrays (N, C, n), (N, C, n, n) with an alive mask
(N, C); C grows (doubles) when a particle needs a new slot. Steps 1, 2 and 4 are array
operations over particles and slots; step 3 is one compiled call per measurement
(`_association`, numba) that loops over the particles and their alive targets, with
`trackers.kalman`'s algebra (its numpy form is the tests' reference): over Table 2's
scans at 20 particles, 81-95 us a measurement amid a step against 309-388 for the numpy
calls on the same arrays, of d x d and n x n matrices (2026-11-29).

Track extraction (the per-step output): take the particle with the largest weight after
the step's updates (the MAP association hypothesis); its alive targets are the reported
targets. For each reported id u, its mean and covariance are the moments of the mixture
over all particles in which u is alive, with their weights renormalised:
    m_u = sum_i w_i m_iu / W_u,   P_u = sum_i w_i (P_iu + (m_iu - m_u)(.)^T) / W_u.
So the number of targets and their ids follow the most probable hypothesis, and each
target's moments use every particle that shares that target (after resampling, usually all).

``filter_step`` is the pure step; the class ``RBMCDA`` holds the particles between steps.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import gammaincc

from fusion_opt import FusionInputError, linalg
from fusion_opt.estimates import Estimates
from fusion_opt.linalg import cholesky, jit
from fusion_opt.validation import safe_repr, wide_float
from trackers import _checks, kalman
from trackers.kalman import _LOG_2PI
from trackers.models import LinearGaussian
from trackers.rbpf import mixture_moments
from trackers.resampling import end_of_step

# `_association`'s cached code embeds fusion_opt's Cholesky: dropped when either changes
linalg.drop_stale_caches(os.path.dirname(os.path.abspath(__file__)),
                         os.path.dirname(os.path.abspath(linalg.__file__)))


class Track(NamedTuple):
    """One reported target: id, mean (n,), covariance (n, n)."""

    target_id: int
    mean: np.ndarray
    cov: np.ndarray


@dataclass(frozen=True, eq=False)  # == is identity, as for an Estimates
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


class RBMCDAParams(NamedTuple):
    """Fixed settings: the model, the new-target prior m0 (n,), P0 (n, n), the step dt, the
    log-priors of the association events (module docstring, step 3), the Gamma lifetime's
    shape and scale, and the resampling threshold (a particle count).

    log_clutter_birth (2, 2): row 0 for a particle with a target alive, row 1 for one with
    none (birth and clutter renormalised); column 0 log(prior of clutter x clutter
    density), column 1 log(prior of a birth). log_target: log((1 - p_b)(1 - pi_c)), to
    share among the particle's alive targets.
    """

    model: LinearGaussian
    m0: np.ndarray
    P0: np.ndarray
    dt: float
    log_clutter_birth: np.ndarray
    log_target: float
    lifetime_shape: float
    lifetime_scale: float
    threshold: float


def event_log_priors(birth_prob: float, clutter_prior: float, clutter_density: float):
    """(log_clutter_birth (2, 2), log_target) of RBMCDAParams from the probabilities."""
    birth_prob = _checks.probability("birth_prob", birth_prob)
    clutter_prior = _checks.probability("clutter_prior", clutter_prior)
    clutter_density = _checks.positive("clutter_density", clutter_density)
    if birth_prob == 0.0 and clutter_prior == 0.0:
        # no target can ever be born, and a measurement may not be clutter
        raise FusionInputError("birth_prob and clutter_prior must not both be 0: "
                               "nothing could explain a measurement")
    with np.errstate(divide="ignore"):  # log(0) = -inf removes an option exactly
        log_pb, log_1mpb = np.log(birth_prob), np.log1p(-birth_prob)
        log_cp, log_1mcp = np.log(clutter_prior), np.log1p(-clutter_prior)
    log_c, log_cd = log_1mpb + log_cp, np.log(clutter_density)
    log_norm = np.logaddexp(log_pb, log_c)  # P(birth or clutter): no target to pick
    table = np.array([[log_c + log_cd, log_pb], [log_c - log_norm + log_cd, log_pb - log_norm]])
    return table, log_1mpb + log_1mcp


class RBMCDAState(NamedTuple):
    """The particles, their targets padded into C slots.

    M (N, C, n), P (N, C, n, n): target means and covariances (a dead slot holds finite
    values that are never read);
    alive (N, C) bool; ids (N, C) int64 target ids (-1 in a dead slot); tau (N, C) time of
    each target's last associated measurement; logw (N,) normalised log-weights;
    next_id: the id the next born target gets; k: the number of steps taken.
    """

    M: np.ndarray
    P: np.ndarray
    alive: np.ndarray
    ids: np.ndarray
    tau: np.ndarray
    logw: np.ndarray
    next_id: int
    k: int


class RBMCDAReport(NamedTuple):
    """One step's tracks, ids (m,), means (m, n), covs (m, n, n), and its ESS (before
    resampling), posterior mean number of targets and whether it resampled."""

    ids: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    ess: float
    expected_n_targets: float
    resampled: bool


def initial_state(m0: np.ndarray, P0: np.ndarray, n_particles: int,
                  capacity: int = 4) -> RBMCDAState:
    """N particles with no target, equal weights, C = capacity empty slots."""
    N = _checks.positive_int("n_particles", n_particles)
    C, n = _checks.positive_int("capacity", capacity), m0.shape[0]
    return RBMCDAState(np.broadcast_to(m0, (N, C, n)).copy(),
                       np.broadcast_to(P0, (N, C, n, n)).copy(),
                       np.zeros((N, C), dtype=bool), np.full((N, C), -1, dtype=np.int64),
                       np.zeros((N, C)), np.full(N, -np.log(N)), 0, 0)


def _grow(s: RBMCDAState, m0, P0) -> RBMCDAState:
    """Double the number of slots (new slots are dead and hold the prior), within
    fusion_opt.limits.array_memory."""
    N, C, n = s.M.shape
    _checks.fits(f"scan: {N} particles of {2 * C} target slots",
                 8.0 * 2 * N * 2 * C * (n * n + n + 3))
    return s._replace(
        M=np.concatenate([s.M, np.broadcast_to(m0, s.M.shape)], axis=1),
        P=np.concatenate([s.P, np.broadcast_to(P0, s.P.shape)], axis=1),
        alive=np.concatenate([s.alive, np.zeros_like(s.alive)], axis=1),
        ids=np.concatenate([s.ids, np.full_like(s.ids, -1)], axis=1),
        tau=np.concatenate([s.tau, np.zeros_like(s.tau)], axis=1))


def survival(age, shape: float, scale: float) -> np.ndarray:
    """S(age) = P(lifetime > age) of the Gamma(shape, scale) lifetime, = Q(shape, age/scale)
    (regularised upper incomplete gamma; equal to scipy.stats.gamma.sf, at 1/17 the cost);
    1 for a negative age (no lifetime is negative)."""
    return gammaincc(shape, np.maximum(np.asarray(age), 0.0) / scale)


def deaths(alive, tau, t_prev: float, t: float, shape: float, scale: float, u) -> np.ndarray:
    """Mask (N, C) of the alive targets that die between t_prev and t, given uniforms u
    (N, C): a target survives iff u < S(t - tau) / S(t_prev - tau), written
    u S(t_prev - tau) < S(t - tau) so that a target whose survival underflowed to 0 dies."""
    return alive & ~(u * survival(t_prev - tau, shape, scale) < survival(t - tau, shape, scale))


def _associate(s: RBMCDAState, y: np.ndarray, t: float, p: RBMCDAParams, rng) -> RBMCDAState:
    """Process one measurement y (d,) at time t for all particles (module docstring, step
    3): the events' log-joints, the draw and the Kalman updates in one compiled call
    (`_association`), the births' slots here. Writes into the state's arrays, which the
    caller owns. The draw's uniforms (N,) are taken from rng first."""
    u = rng.random(s.alive.shape[0])
    ok, choice, log_pred, m_new, P_new = _association(
        s.alive, s.M, s.P, p.m0, p.P0, p.model.H, p.model.R, y,
        p.log_clutter_birth, p.log_target, u)
    if not ok:
        raise FusionInputError(
            f"measurement y = {y.tolist()}: the innovation covariance H P H^T + R of a target "
            "or of the birth prior is not positive definite in float64 (a model and prior at "
            "float64's limits)")
    if log_pred.max() == -np.inf:
        raise FusionInputError(
            f"measurement y = {y.tolist()} has likelihood 0 under every particle's targets "
            "and the birth prior, and clutter has prior 0 (clutter_prior = 0, or "
            "birth_prob = 1): no hypothesis explains it")
    logw = s.logw + log_pred
    if logw.max() == -np.inf:
        raise FusionInputError(
            f"measurement y = {y.tolist()} leaves every particle with weight 0: no particle "
            "explains all of this scan's measurements")
    s = s._replace(logw=logw)
    r = np.flatnonzero(choice)  # the particles that chose a target or a birth
    if r.size == 0:
        return s
    c = choice[r] - 2
    born = c < 0
    if born.any():
        s, c[born] = _births(s, r[born], p)
    s.M[r, c], s.P[r, c], s.tau[r, c] = m_new[r], P_new[r], t
    return s


@jit
def _association(alive, M, P, m0, P0, H, R, y, table, log_target: float, u):
    """One measurement y (d,) for every particle: alive (N, C), M (N, C, n), P (N, C, n, n),
    the birth prior m0 (n,), P0 (n, n), the model's H (d, n) and R (d, d), the events'
    log-priors table (2, 2) and log_target (RBMCDAParams), and uniforms u (N,). Each
    particle's events, clutter, birth and the target in slot c, have the log-joints
    log(prior x likelihood); one is drawn by inverse CDF with u and the log-normaliser
    log sum exp is the particle's log predictive likelihood (-inf where no event is
    possible). Returns (ok, choice (N,): 0 clutter, 1 birth, 2 + c slot c; log_pred (N,);
    m_new (N, n), P_new (N, n, n): the chosen filter's Kalman update (Joseph's form,
    symmetrised), in the rows whose choice is not clutter); ok is False where an innovation
    covariance has no Cholesky factor."""
    N, C, n = M.shape
    d = y.size
    choice, log_pred = np.zeros(N, dtype=np.int64), np.empty(N)
    m_new, P_new = np.empty((N, n)), np.empty((N, n, n))
    PHt, S, L, v, z = np.empty((n, d)), np.empty((d, d)), np.empty((d, d)), np.empty(d), np.empty(d)
    lj, cdf = np.empty(C + 2), np.empty(C + 2)
    m0, P0 = m0.copy(), P0.copy()  # writable, as the slots' views: one compiled type
    ll_birth, ok = _log_likelihood(m0, P0, H, R, y, PHt, S, L, v, z)
    if not ok:
        return False, choice, log_pred, m_new, P_new
    for i in range(N):
        T = 0
        for c in range(C):
            T += alive[i, c]
        row = 1 if T == 0 else 0  # no target to pick: birth and clutter renormalised
        lj[0], lj[1] = table[row, 0], table[row, 1] + ll_birth
        share = log_target - np.log(max(T, 1))
        for c in range(C):
            lj[2 + c] = -np.inf
            if alive[i, c]:
                ll, ok = _log_likelihood(M[i, c], P[i, c], H, R, y, PHt, S, L, v, z)
                if not ok:
                    return False, choice, log_pred, m_new, P_new
                lj[2 + c] = ll + share
        choice[i], log_pred[i] = _draw(lj, u[i], cdf)
        e = choice[i]
        if e == 1:
            _update(m0, P0, H, R, y, PHt, S, L, v, m_new[i], P_new[i])
        elif e >= 2:
            _update(M[i, e - 2], P[i, e - 2], H, R, y, PHt, S, L, v, m_new[i], P_new[i])
    return True, choice, log_pred, m_new, P_new


@jit
def _draw(lj, u: float, cdf):
    """(event, log sum exp(lj)) for log-joints lj (E,): the event drawn with probability
    proportional to exp(lj) by inverse CDF at u in [0, 1); event E - 1 and -inf where every
    lj is -inf."""
    E = lj.size
    peak = -np.inf
    for e in range(E):
        peak = max(peak, lj[e])
    if peak == -np.inf:
        peak = 0.0
    total = 0.0
    for e in range(E):
        total += np.exp(lj[e] - peak)
        cdf[e] = total
    at, event = u * total, 0
    for e in range(E):
        event += cdf[e] < at
    return min(event, E - 1), peak + np.log(total)


@jit
def _innovation(m, P, H, R, y, PHt, S, v) -> None:
    """v = y - H m (d,), S = H P H^T + R (d, d), PHt = P H^T (n, d)."""
    n, d = m.size, y.size
    for a in range(n):
        for b in range(d):
            t = 0.0
            for k in range(n):
                t += P[a, k] * H[b, k]
            PHt[a, b] = t
    for a in range(d):
        for b in range(d):
            t = 0.0
            for k in range(n):
                t += H[a, k] * PHt[k, b]
            S[a, b] = t + R[a, b]
        t = 0.0
        for k in range(n):
            t += H[a, k] * m[k]
        v[a] = y[a] - t


@jit
def _log_likelihood(m, P, H, R, y, PHt, S, L, v, z):
    """(log N(y; H m, S), ok) with S = H P H^T + R, by its Cholesky factor; -inf where the
    squared Mahalanobis distance overflows. Leaves v, S, PHt and L in the buffers."""
    _innovation(m, P, H, R, y, PHt, S, v)
    if not cholesky(S, L):
        return -np.inf, False
    d = y.size
    maha, logdet = 0.0, 0.0
    for a in range(d):
        t = v[a]
        for k in range(a):
            t -= L[a, k] * z[k]
        z[a] = t / L[a, a]
        maha += z[a] * z[a]
        logdet += np.log(L[a, a])
    return -0.5 * (maha + 2.0 * logdet + d * _LOG_2PI), True


@jit
def _update(m, P, H, R, y, PHt, S, L, v, m_out, P_out) -> None:
    """The Kalman update of (m (n,), P (n, n)) with y into m_out, P_out (Joseph's form,
    `trackers.kalman`), its gain from the Cholesky factor of S. v, S, PHt and L are made
    again for this filter: the buffers hold those of the last filter `_log_likelihood`
    saw, and the same arithmetic gives the same numbers."""
    n, d = m.size, y.size
    _innovation(m, P, H, R, y, PHt, S, v)
    cholesky(S, L)  # succeeded in `_log_likelihood` for the same numbers
    Kt, w = np.empty((d, n)), np.empty(d)
    for col in range(n):  # Kt = S^-1 (P H^T)^T: L w = PHt[col], then L^T Kt[:, col] = w
        for a in range(d):
            t = PHt[col, a]
            for k in range(a):
                t -= L[a, k] * w[k]
            w[a] = t / L[a, a]
        for a in range(d - 1, -1, -1):
            t = w[a]
            for k in range(a + 1, d):
                t -= L[k, a] * Kt[k, col]
            Kt[a, col] = t / L[a, a]
    for k in range(n):
        t = m[k]
        for a in range(d):
            t += v[a] * Kt[a, k]
        m_out[k] = t
    IKH, T1 = np.empty((n, n)), np.empty((n, n))
    for a in range(n):  # I - K H, K = Kt^T
        for b in range(n):
            t = 1.0 if a == b else 0.0
            for c in range(d):
                t -= Kt[c, a] * H[c, b]
            IKH[a, b] = t
    for a in range(n):  # (I - K H) P
        for b in range(n):
            t = 0.0
            for k in range(n):
                t += IKH[a, k] * P[k, b]
            T1[a, b] = t
    for a in range(n):  # (I - K H) P (I - K H)^T + K R K^T
        for b in range(n):
            t = 0.0
            for k in range(n):
                t += T1[a, k] * IKH[b, k]
            kr = 0.0
            for c in range(d):
                r = 0.0
                for e in range(d):
                    r += Kt[e, a] * R[e, c]
                kr += r * Kt[c, b]
            P_out[a, b] = t + kr
    for a in range(n):
        for b in range(a):
            P_out[a, b] = P_out[b, a] = 0.5 * (P_out[a, b] + P_out[b, a])


def _births(s: RBMCDAState, b: np.ndarray, p: RBMCDAParams):
    """Give each particle in b a new target with a fresh id in its first free slot (the
    slots grow if one has none). Returns the state and those slots (b.size,)."""
    if s.alive[b].all(axis=1).any():
        s = _grow(s, p.m0, p.P0)
    c = s.alive[b].argmin(axis=1)
    s.alive[b, c] = True
    s.ids[b, c] = s.next_id + np.arange(b.size)
    return s._replace(next_id=s.next_id + b.size), c


def extract_tracks(s: RBMCDAState, w: np.ndarray):
    """The MAP particle's targets (ids (m,)) with their mixture moments over the particles
    sharing them: means (m, n), covs (m, n, n). w (N,) normalised weights."""
    best = int(w.argmax())
    ids = s.ids[best][s.alive[best]]
    if ids.size == 0:
        n = s.M.shape[-1]
        return ids, np.zeros((0, n)), np.zeros((0, n, n))
    rows, cols = s.alive.nonzero()
    # share (U, K) and its mask, and mixture_moments' dm and weighted dm, (U, K, n) each
    _checks.fits(f"scan: the MAP particle's {ids.size} tracks over {rows.size} alive targets",
                 8.0 * ids.size * rows.size * (2 * s.M.shape[-1] + 2))
    # share[u, k]: weight of alive target k in track u's mixture (one per particle at most)
    share = (s.ids[rows, cols] == ids[:, None]) * w[rows]
    share /= share.sum(axis=1, keepdims=True)
    means, covs = mixture_moments(share, s.M[rows, cols], s.P[rows, cols])
    return ids, means, covs


def filter_step(s: RBMCDAState, scan: np.ndarray, p: RBMCDAParams, rng):
    """One RBMCDA step (module docstring) on the measurements ``scan`` (k, d).
    Returns (RBMCDAState, RBMCDAReport); the input state is not modified."""
    t_prev, t = s.k * p.dt, (s.k + 1) * p.dt
    if not np.isfinite(t):
        raise FusionInputError(f"step {s.k + 1} at dt = {p.dt:g} is past float64's times")
    alive, ids, M, P = s.alive.copy(), s.ids.copy(), s.M.copy(), s.P.copy()
    if alive.any():
        dead = deaths(alive, s.tau, t_prev, t, p.lifetime_shape, p.lifetime_scale,
                      rng.random(alive.shape))
        alive &= ~dead
        ids[dead] = -1
    # predict the survivors; a dead slot keeps its last (finite, never read) moments
    rows, cols = alive.nonzero()
    M[rows, cols], P[rows, cols] = kalman.predict(M[rows, cols], P[rows, cols],
                                                  p.model.A, p.model.Q)
    s = s._replace(M=M, P=P, alive=alive, ids=ids, tau=s.tau.copy(), k=s.k + 1)
    for y in np.ascontiguousarray(scan):  # rows of one compiled type
        s = _associate(s, y, t, p, rng)

    end = end_of_step(s.logw, p.threshold, rng)
    track_ids, means, covs = extract_tracks(s, end.weights)
    n_expected = float(end.weights @ s.alive.sum(axis=1))
    if end.ancestors is not None:
        a = end.ancestors
        s = s._replace(M=s.M[a], P=s.P[a], alive=s.alive[a], ids=s.ids[a], tau=s.tau[a])
    s = s._replace(logw=end.logw)
    return s, RBMCDAReport(track_ids, means, covs, end.ess, n_expected,
                           end.ancestors is not None)


class RBMCDA:
    """RBMCDA (module docstring) for an unknown number of targets, one step at a time.

    RBMCDA(model, m0, P0, *, rng, dt, n_particles=20, birth_prob=0.01, lifetime_shape=2.0,
    lifetime_scale=0.5, clutter_prior=0.05, clutter_density=1/16, resample_threshold=0.25,
    name=None): model a LinearGaussian with step dt; m0 (n,), P0 (n, n) the prior of a
    new-born target; dt the step length (s), used for the lifetimes (step k is at time
    (k + 1) dt); rng a numpy Generator; birth_prob the prior probability that a measurement
    comes from a new target; lifetime_shape, lifetime_scale: the Gamma lifetime since the
    last associated measurement; clutter_prior the prior probability that a measurement is
    clutter given no birth; clutter_density the clutter likelihood 1/V; resample when
    ESS < resample_threshold * n_particles.

    ``step(scan, time=None)`` takes the measurements (k, d) of one step (k may be 0) and
    returns an Estimates with the MAP particle's targets (means (m, n), covs (m, n, n),
    possibly m = 0) and their target ids. An id is assigned once, at the target's birth,
    and never reused; it is reported at every step at which that target is alive in the
    MAP particle. Ids persist while the MAP hypothesis keeps the target; a target that
    dies never returns, and when the MAP particle changes, ids the new one does not share
    drop out and its own appear. ``time`` is stamped on the Estimates; None stamps the
    filter's clock (k + 1) dt (the lifetimes always run on that clock). ``name`` is
    stamped as its node.

    Read-only state: ``particles`` (an RBMCDAState of read-only arrays), ``log_weights``
    (N,), ``steps``, and of the last step ``ess``, ``expected_n_targets``, ``resampled``.
    """

    def __init__(self, model: LinearGaussian, m0, P0, *, rng: np.random.Generator,
                 dt: float, n_particles: int = 20, birth_prob: float = 0.01,
                 lifetime_shape: float = 2.0, lifetime_scale: float = 0.5,
                 clutter_prior: float = 0.05, clutter_density: float = 1 / 16,
                 resample_threshold: float = 0.25, name=None):
        m0, P0 = kalman.check_prior(model, m0, P0)
        self._rng = _checks.generator("rng", rng)
        N = _checks.positive_int("n_particles", n_particles)
        # the particles' 4 first slots and a step's temporaries (about 8 copies)
        _checks.fits(f"n_particles = {safe_repr(N)}",
                     8.0 * 8 * 4 * wide_float(N) * (model.n**2 + model.n + 3))
        table, log_target = event_log_priors(birth_prob, clutter_prior, clutter_density)
        self.params = RBMCDAParams(
            model, _checks.read_only(m0), _checks.read_only(P0), _checks.positive("dt", dt),
            _checks.read_only(table), log_target,
            _checks.positive("lifetime_shape", lifetime_shape),
            _checks.positive("lifetime_scale", lifetime_scale),
            _checks.probability("resample_threshold", resample_threshold) * N)
        self.name = _checks.node_name(name)
        self._state, self._time = initial_state(m0, P0, N), None
        self._last = RBMCDAReport(np.zeros(0, dtype=np.int64), np.zeros((0, model.n)),
                                  np.zeros((0, model.n, model.n)), float(N), 0.0, False)

    @property
    def particles(self) -> RBMCDAState:
        """The particles (RBMCDAState; its arrays are read-only views)."""
        return RBMCDAState(*(_checks.read_only(v) if isinstance(v, np.ndarray) else v
                             for v in self._state))

    @property
    def log_weights(self) -> np.ndarray:
        """(N,) normalised log-weights."""
        return _checks.read_only(self._state.logw)

    @property
    def steps(self) -> int:
        """Number of steps taken."""
        return self._state.k

    @property
    def ess(self) -> float:
        """Effective sample size of the last step, before its resampling (N before any)."""
        return self._last.ess

    @property
    def expected_n_targets(self) -> float:
        """Posterior mean number of targets after the last step."""
        return self._last.expected_n_targets

    @property
    def resampled(self) -> bool:
        """Whether the last step resampled."""
        return self._last.resampled

    def _advance(self, scan: np.ndarray, name: str = "scan") -> RBMCDAReport:
        """One step on a checked scan (k, d); the state changes only if it succeeds."""
        with np.errstate(over="ignore", invalid="ignore"):  # refused just below
            state, last = filter_step(self._state, scan, self.params, self._rng)
        last = last._replace(
            covs=_checks.step_estimates(name, self._state.k, last.means, last.covs))
        self._state, self._last = state, last
        return last

    def step(self, scan, time=None) -> Estimates:
        """Predict, draw deaths, associate every measurement of ``scan`` (k, d), report the
        MAP particle's targets with their ids."""
        time = _checks.step_time(time, self._time) if time is not None else self._clock()
        r = self._advance(_checks.scan("scan", scan, self.params.model.d))
        self._time = time
        return _checks.report(r.means, r.covs, r.ids, time, self.name)

    def _clock(self) -> float:
        """The next step's clock time (k + 1) dt, stamped where no time is given; refused
        where it is before the time stamped on the last step (fuzz K3: after time=100, a
        step without one was stamped 2.0, and a later time=50 was then accepted)."""
        k = self._state.k + 1
        clock = k * self.params.dt
        if self._time is not None and clock < self._time:
            raise FusionInputError(
                f"time: without one, step {k} is stamped with its clock time {k} x dt = "
                f"{clock:g}, before the time of the step before it, {self._time:g}: give "
                "this step's time (or no step one)")
        return clock


def run(scans: Sequence, model: LinearGaussian, m0, P0, *, rng: np.random.Generator,
        dt: float, n_particles: int = 20, birth_prob: float = 0.01,
        lifetime_shape: float = 2.0, lifetime_scale: float = 0.5,
        clutter_prior: float = 0.05, clutter_density: float = 1 / 16,
        resample_threshold: float = 0.25) -> RBMCDAOutput:
    """Run RBMCDA over ``scans`` (sequence of T arrays (k_t, d), k_t may be 0): a loop over
    ``RBMCDA.step`` (the tracks without the Estimates wrapper). The arguments are those of
    ``RBMCDA``. Returns an RBMCDAOutput; ``out[t]`` is the tuple of Track(target_id, mean,
    cov) at step t.
    """
    f = RBMCDA(model, m0, P0, rng=rng, dt=dt, n_particles=n_particles, birth_prob=birth_prob,
               lifetime_shape=lifetime_shape, lifetime_scale=lifetime_scale,
               clutter_prior=clutter_prior, clutter_density=clutter_density,
               resample_threshold=resample_threshold)
    scans = _checks.scans(scans, model.d)
    T = len(scans)
    tracks, ess = [], np.empty(T)
    expected_n, resampled = np.empty(T), np.zeros(T, dtype=bool)
    for k, scan in enumerate(scans):
        r = f._advance(scan, f"scans[{k}]")
        tracks.append(tuple(Track(int(u), m, P) for u, m, P in zip(r.ids, r.means, r.covs,
                                                                   strict=True)))
        ess[k], expected_n[k], resampled[k] = r.ess, r.expected_n_targets, r.resampled
    return RBMCDAOutput(tuple(tracks), ess, expected_n, resampled)
