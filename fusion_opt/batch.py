"""Batched fusion: B independent CI / BCI / MBCI problems as arrays, without a loop over B.

    r = fuse_batch(means, covs, method="bci", criterion="trace", backend="newton")
    # means (B, N, n), covs (B, N, n, n) -> r.weights (B, N), r.mean (B, n), r.cov (B, n, n),
    # r.objective (B,), r.gap (B,), r.status (B,)

Each problem is the one `fusion.fuse` solves (same scaling, same certificate). The native
backends run vectorised over B: for N = 2, "closed-form" and "newton" diagonalise each pair
of covariances at once (P_b = T T^T, P_a = T diag(1/lam) T^T, `backends/closed_form.py`) and
solve the 1-D problem in w for all pairs together, so

    P(w) = T diag(1/d) T^T,   d = 1 + w (lam - 1),   m(w) = T diag(1/d) (w lam z_a + (1 - w) z_b),

with z = T^-1 m; for N > 2, "newton" is the batched active-set Newton method. Other backends
("clarabel", "scs", "slsqp") solve problem by problem and are polished like `fuse`.
"""

from __future__ import annotations

import time

import numpy as np

from . import criteria
from .backends import EXACT, REGISTRY, closed_form, newton
from .fusion import _check_backend, _polish, fuse_rule, information
from .mbci import detection_scales
from .results import BatchFusionResult, FusionInputError
from .rules import RULES
from .scaling import scale
from .simplex import to_simplex
from .validation import check_criterion, check_estimates

METHODS = ("ci", "bci", "mbci", *RULES)


def fuse_batch(means, covs, method="bci", criterion="trace", backend="newton", *,
               p_detect=None, chi=None, cross=None) -> BatchFusionResult:
    """Fuse B problems of N estimates each: means (B, N, n), covs (B, N, n, n).

    method "ci" (N must be 2), "bci" or "mbci" (with p_detect and chi, each a scalar, one
    value per node (N,) shared by all problems, or (B, N)), or a rule of `rules.py`:
    "naive" vectorised, the others problem by problem ("known-cross" with cross
    (B, N, N, n, n)). backend as in `fuse`; the default "newton" is the fast exact one here
    (results match "clarabel").
    """
    means, covs = check_estimates(means, covs, batch=True)
    check_criterion(criterion)
    _check_backend(backend)
    if method not in METHODS:
        raise FusionInputError(f"method must be one of {METHODS}, got {method!r}")
    B, N = means.shape[:2]
    if method == "ci" and N != 2:
        raise FusionInputError(f"method 'ci' fuses 2 nodes, got N = {N}")
    if method in RULES:
        return _rule(means, covs, method, criterion, cross)
    if method == "mbci":
        if p_detect is None or chi is None:
            raise FusionInputError("method 'mbci' needs p_detect and chi")
        covs = covs / batch_detection_scales(p_detect, chi, B, N)[..., None, None]
    elif p_detect is not None or chi is not None:
        raise FusionInputError(f"p_detect and chi apply to method 'mbci', not {method!r}")
    if backend == "closed-form" and N != 2:
        raise FusionInputError(f"backend 'closed-form' fuses N = 2 nodes, got N = {N}")
    t0 = time.perf_counter()
    if N == 2 and backend in EXACT:
        out = _pairs(means, covs, criterion)
    else:
        out = _general(means, covs, criterion, backend)
    w, mean, cov, objective, gap, status, iters = out
    return BatchFusionResult(w, mean, cov, objective, gap, status, iters, backend,
                             time.perf_counter() - t0, method, criterion)


def batch_detection_scales(p_detect, chi, B: int, N: int) -> np.ndarray:
    """MBCI scales s (B, N) for p_detect, chi scalars, (N,) or (B, N)."""
    s = detection_scales(p_detect, chi, n_nodes=N)
    if s.shape not in ((N,), (B, N)):
        raise FusionInputError(
            f"p_detect and chi must be scalars, ({N},) or ({B}, {N}), got {s.shape}")
    return np.broadcast_to(s, (B, N))


def _pairs(means, covs, criterion):
    """N = 2 for every problem at once by simultaneous diagonalisation (module docstring)."""
    lam, T = closed_form.diagonalise_covariances(covs[:, 0], covs[:, 1])
    a = lam - 1.0
    c = (T * T).sum(-2)  # c_k = (T^T T)_kk: the trace weight of the unscaled problem
    w, fprime, iters = closed_form.solve_weight(a, c, criterion)
    d_inv = 1.0 / (1.0 + w[:, None] * a)
    cov = (T * d_inv[:, None, :]) @ np.swapaxes(T, -1, -2)
    z = np.linalg.solve(T[:, None], means[..., None])[..., 0]  # (B, 2, n)
    mean = (T @ (d_inv * (w[:, None] * lam * z[:, 0] + (1.0 - w[:, None]) * z[:, 1]))[..., None])
    objective = closed_form.objective(w, a, c, criterion)
    if criterion == "logdet":
        objective = objective + 2.0 * np.linalg.slogdet(T)[1]
    B = len(w)
    return (np.stack([w, 1.0 - w], -1), mean[..., 0], 0.5 * (cov + np.swapaxes(cov, -1, -2)),
            objective, closed_form.pair_gap(w, fprime), np.full(B, "optimal"),
            np.full(B, iters))


def _general(means, covs, criterion, backend):
    """Any N: batched Newton, or a backend problem by problem (then polished as `fuse`)."""
    Ys = information(covs)
    sp = scale(Ys, criterion)
    B, N = means.shape[:2]
    if N == 1:
        w, status, iters = np.ones((B, 1)), np.full(B, "optimal"), np.zeros(B)
    elif backend == "newton":
        sol = newton.solve(sp.Ys, sp.M, criterion)
        w, iters = sol.w, sol.iterations
        status = np.where(sol.converged, "optimal", "optimal_inaccurate")
    else:
        w, status, iters = np.empty((B, N)), np.empty(B, dtype=object), np.zeros(B)
        for b in range(B):
            sp_b = sp.problem(b)  # already scaled with the batch
            sol = REGISTRY[backend](sp_b.Ys, sp_b.M, criterion)
            w[b], status[b] = _polish(sp_b, to_simplex(sol.w), sol.status)[:2]
            iters[b] = sol.iterations
    ev = criteria.evaluate(sp.Ys, w, criterion, sp.M)
    cov = sp.covariance(np.linalg.inv(criteria.fused_information(sp.Ys, w)))
    mean = (cov @ np.einsum("bi,bijk,bik->bj", w, Ys, means)[..., None])[..., 0]
    return (w, mean, cov, sp.unscale_objective(ev.f), sp.unscale_gap(criteria.gap(ev.g, w)),
            status, iters)


def _rule(means, covs, method, criterion, cross) -> BatchFusionResult:
    """A rule of `rules.py`: "naive" at once, P = (sum_i Y_i)^-1; the others per problem."""
    t0 = time.perf_counter()
    B, N, n = means.shape
    if method == "naive":
        Ys = information(covs)
        P = np.linalg.inv(Ys.sum(1))
        gains = P[:, None] @ Ys
        w = np.trace(gains, axis1=-2, axis2=-1) / n
        mean = np.einsum("bijk,bik->bj", gains, means)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        obj = np.trace(P, axis1=-2, axis2=-1) if criterion == "trace" else \
            np.linalg.slogdet(P)[1]
        return BatchFusionResult(w, mean, P, obj, np.zeros(B), np.full(B, "closed-form"),
                                 np.zeros(B), "closed-form", time.perf_counter() - t0,
                                 method, criterion)
    extra = [{} if cross is None else {"cross": cross[b]} for b in range(B)]
    rs = [fuse_rule(means[b], covs[b], method, criterion, **extra[b]) for b in range(B)]
    return BatchFusionResult(
        np.array([r.weights for r in rs]), np.array([r.mean for r in rs]),
        np.array([r.cov for r in rs]), np.array([r.objective for r in rs]), np.zeros(B),
        np.array([r.status for r in rs]), np.zeros(B), "closed-form",
        time.perf_counter() - t0, method, criterion)
