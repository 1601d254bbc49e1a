"""CI, batch CI and modified batch CI: the public fusion functions.

For node estimates m_i (N, n), P_i (N, n, n) with informations Y_i = P_i^-1 and weights w
on the simplex chosen to minimise tr P(w) ("trace") or log det P(w) ("logdet"):

    P(w)^-1 = sum_i w_i Y_i,      m(w) = P(w) sum_i w_i Y_i m_i.

Every call validates its input, scales the problem (`scaling.py`), asks a backend for the
weights, maps them exactly onto the simplex, polishes them with the Newton method of
`backends/newton.py` started there (so the certificate reaches machine precision whatever
the backend), and reports the
optimality gap of DESIGN §1 at the returned weights.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from . import criteria
from .backends import EXACT, REGISTRY, newton
from .mbci import detection_scales
from .results import FusionInputError, FusionResult, FusionSolverError
from .rules import PAIR_ONLY, RULE_ARGS, RULES
from .scaling import ScaledProblem, scale
from .simplex import to_simplex
from .validation import check_criterion, check_estimates

# Interior-point weights below this fraction of the largest are the solver's stand-in for 0.
_SUPPORT_RTOL = 1e-7


def information(covs: np.ndarray) -> np.ndarray:
    """Y_i = P_i^-1 for covs (..., n, n), symmetrised."""
    Y = np.linalg.inv(covs)
    return 0.5 * (Y + np.swapaxes(Y, -1, -2))


def _check_backend(backend) -> str:
    if backend not in REGISTRY:
        raise FusionInputError(f"backend must be one of {tuple(REGISTRY)}, got {backend!r}")
    return backend


def bci(means, covs, criterion="trace", backend="clarabel", *, polish=True) -> FusionResult:
    """Batch covariance intersection of N estimates: means (N, n), covs (N, n, n).

    Returns a FusionResult with weights (N,), mean (n,), cov (n, n), objective, gap.
    polish=False returns the backend's weights as they are (for comparing solvers).
    """
    means, covs = check_estimates(means, covs)
    check_criterion(criterion)
    _check_backend(backend)
    return _fuse_weights(means, covs, criterion, backend, polish, method="bci")


def ci(m_a, P_a, m_b, P_b, criterion="trace", backend="clarabel", *, polish=True):
    """Pairwise covariance intersection of (m_a (n,), P_a (n, n)) and (m_b, P_b)."""
    means = _stack_pair(m_a, m_b, "m_a", "m_b")
    covs = _stack_pair(P_a, P_b, "P_a", "P_b")
    return _ci_pair(means, covs, criterion, backend, polish=polish)


def _ci_pair(means, covs, criterion="trace", backend="clarabel", *, polish=True):
    """CI of stacked pairs means (2, n), covs (2, n, n): `fuse(method="ci")` and `ci`."""
    means, covs = check_estimates(means, covs)
    if len(means) != 2:
        raise FusionInputError(f"method 'ci' fuses 2 nodes, got N = {len(means)}")
    return _renamed(bci(means, covs, criterion, backend, polish=polish), "ci")


def mbci(means, covs, p_detect, chi, criterion="trace", backend="clarabel", *, polish=True):
    """Modified batch CI: BCI on Phat_i = P_i / s_i with s = detection_scales(p_detect, chi).

    p_detect in [0, 1] and chi in (0, 1] are scalars or (N,). The returned cov is the
    modified fused covariance Phat = (sum_i w_i s_i Y_i)^-1.
    """
    means, covs = check_estimates(means, covs)
    s = detection_scales(p_detect, chi, n_nodes=len(means))
    result = bci(means, covs / s[:, None, None], criterion, backend, polish=polish)
    return _renamed(result, "mbci")


def _renamed(result: FusionResult, method: str) -> FusionResult:
    return replace(result, method=method)


def _stack_pair(a, b, name_a, name_b) -> np.ndarray:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape:
        raise FusionInputError(f"{name_a} has shape {a.shape} but {name_b} has {b.shape}")
    return np.stack([a, b])


def _fuse_weights(means, covs, criterion, backend, polish, method) -> FusionResult:
    Ys = information(covs)
    if len(Ys) == 1:
        return _single(means[0], covs[0], criterion, backend, method)
    sp = scale(Ys, criterion)
    t0 = time.perf_counter()
    sol = REGISTRY[backend](sp.Ys, sp.M, criterion)
    w, status, polish_iters = to_simplex(sol.w), sol.status, 0
    if polish and backend not in EXACT:
        w, status, polish_iters = _polish(sp, w, status)
    wall = time.perf_counter() - t0
    return _result(means, Ys, sp, w, status, backend, wall, sol.iterations, polish_iters,
                   method)


def _polish(sp: ScaledProblem, w: np.ndarray, status: str):
    """Newton from the solver's weights with its near-zero weights set to 0; the better
    certificate of the two wins (the solver's, too, if the Newton method fails)."""
    start = np.where(w >= _SUPPORT_RTOL * w.max(), w, 0.0)
    try:
        sol = newton.solve_one(sp.Ys, sp.M, sp.criterion, w0=start)
    except FusionSolverError:
        return w, status, 0
    ev = criteria.evaluate(sp.Ys, w, sp.criterion, sp.M)
    before = newton.relative_gap(ev.f, ev.g, w, sp.criterion)
    if sol.rel_gap[0] <= before:
        status = "optimal" if sol.converged[0] else status
        return sol.w[0], status, int(sol.iterations[0])
    return w, status, int(sol.iterations[0])


def _single(mean, cov, criterion, backend, method) -> FusionResult:
    """N = 1: the estimate itself with weight 1 (no inversion round trip)."""
    objective = np.trace(cov) if criterion == "trace" else np.linalg.slogdet(cov)[1]
    return FusionResult(weights=np.ones(1), mean=mean, cov=cov, objective=float(objective),
                        gap=0.0, status="optimal", backend=backend, solve_time=0.0,
                        iterations=0, method=method, criterion=criterion)


def _result(means, Ys, sp, w, status, backend, wall, iters, polish_iters, method):
    ev = criteria.evaluate(sp.Ys, w, sp.criterion, sp.M)
    P = sp.covariance(np.linalg.inv(criteria.fused_information(sp.Ys, w)))
    mean = P @ np.einsum("i,ijk,ik->j", w, Ys, means)
    return FusionResult(
        weights=w, mean=mean, cov=P,
        objective=float(sp.unscale_objective(ev.f)),
        gap=float(sp.unscale_gap(criteria.gap(ev.g, w))),
        status=status, backend=backend, solve_time=wall, iterations=int(iters),
        method=method, criterion=sp.criterion, polish_iterations=polish_iters)


def optimality_gap(covs, weights, criterion="trace") -> float:
    """The certificate g(w).w - min_i g_i(w) >= f(w) - f* at weights (N,) for covs (N, n, n),
    in the objective's units (DESIGN §1)."""
    covs = np.asarray(covs, dtype=float)
    _, covs = check_estimates(np.zeros(covs.shape[:-1]) if covs.ndim == 3 else covs, covs)
    check_criterion(criterion)
    w = np.asarray(weights, dtype=float)
    if w.shape != (len(covs),):
        raise FusionInputError(f"weights must have shape ({len(covs)},), got {w.shape}")
    if not np.all(np.isfinite(w)) or (w < 0).any() or abs(w.sum() - 1.0) > 1e-9:
        raise FusionInputError("weights must be finite, >= 0 and sum to 1")
    sp = scale(information(covs), criterion)
    ev = criteria.evaluate(sp.Ys, w, criterion, sp.M)
    return float(sp.unscale_gap(criteria.gap(ev.g, w)))


METHODS = {"ci": _ci_pair, "bci": bci, "mbci": mbci}


def fuse(means, covs, method="bci", criterion="trace", backend="clarabel", **method_args):
    """Fuse estimates means (N, n), covs (N, n, n) with a named rule.

    method: "ci" (N must be 2), "bci", "mbci" (method_args p_detect, chi), or a rule of
    `rules.py`: "naive", "known-cross" (method_args cross), "fast-ci", "ifci", "ici", "ei".
    """
    if method in RULES:
        return fuse_rule(means, covs, method, criterion, **method_args)
    if method not in METHODS:
        raise FusionInputError(
            f"method must be one of {(*METHODS, *RULES)}, got {method!r}")
    return METHODS[method](means, covs, criterion=criterion, backend=backend, **method_args)


def fuse_rule(means, covs, method, criterion="trace", **method_args) -> FusionResult:
    """A rule of `rules.py` on validated input, covariances (and cross) scaled by the power
    of two 2^-e that brings the geometric middle of the nodes' scales to about 1."""
    means, covs = check_estimates(means, covs)
    check_criterion(criterion)
    if method in PAIR_ONLY and len(means) != 2:
        raise FusionInputError(f"method {method!r} fuses 2 nodes, got N = {len(means)}")
    if set(method_args) != RULE_ARGS[method]:
        raise FusionInputError(f"method {method!r} takes the arguments "
                               f"{sorted(RULE_ARGS[method])}, got {sorted(method_args)}")
    scales = np.frexp(np.diagonal(covs, axis1=-2, axis2=-1).max(-1))[1]
    e = int(scales.min() + scales.max()) // 2
    args = {k: _ldexp_numbers(v, -e) for k, v in method_args.items()}
    t0 = time.perf_counter()
    out = RULES[method](means, np.ldexp(covs, -e), criterion, **args)
    wall = time.perf_counter() - t0
    if criterion == "trace":
        objective = np.ldexp(np.trace(out.cov), e)
    else:
        objective = np.linalg.slogdet(out.cov)[1] + len(out.mean) * e * np.log(2.0)
    return FusionResult(weights=out.weights, mean=out.mean, cov=np.ldexp(out.cov, e),
                        objective=float(objective), gap=0.0, status=out.status,
                        backend="closed-form", solve_time=wall, iterations=0, method=method,
                        criterion=criterion)


def _ldexp_numbers(value, e):
    """value * 2^e if it is an array of numbers; otherwise as it is, for the rule to refuse."""
    try:
        a = np.asarray(value)
    except ValueError:
        return value
    return np.ldexp(a, e) if a.dtype.kind in "iuf" else value
