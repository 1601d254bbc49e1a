"""CI, batch CI and modified batch CI: the public fusion functions for one problem.

For node estimates m_i (N, n), P_i (N, n, n) with informations Y_i = P_i^-1 and weights w
on the simplex chosen to minimise tr P(w) ("trace") or log det P(w) ("logdet"):

    P(w)^-1 = sum_i w_i Y_i,      m(w) = P(w) sum_i w_i Y_i m_i.

Each function checks its arguments once and hands them straight to the one fusion path of
`core.py`, which `fuse_batch` shares (`bci` and `mbci` do not go through `fuse`: one
Python layer less for a small fusion): exact prescaling, the weight solver, the polish of
an inexact solver's weights, and the certificate of DESIGN §1 at the returned weights.
The options and their defaults are listed once, in `core.py`'s docstring.
"""

from __future__ import annotations

import time

import numpy as np

from . import core
from .backends import newton
from .core import Names
from .factored import work
from .results import FusionInputError, FusionResult
from .validation import is_integer, real_array, safe_repr

_PAIR = Names("m_a and m_b", "P_a and P_b", pair=True)


def bci(means, covs, criterion="trace", backend=None, *, polish=True) -> FusionResult:
    """Batch covariance intersection of N estimates: means (N, n), covs (N, n, n).

    Returns a FusionResult with weights (N,), mean (n,), cov (n, n), objective, gap.
    backend: a weight solver of fo.BACKENDS (default "newton"); polish=False returns an
    inexact backend's weights as they are (for comparing solvers).
    """
    req = core.request("bci", criterion, backend, {"polish": polish})
    return core.run(*core.arrays(means, covs, False, req=req), req, False)


def ci(m_a, P_a, m_b, P_b, criterion="trace", backend=None, *, polish=True) -> FusionResult:
    """Pairwise covariance intersection of (m_a (n,), P_a (n, n)) and (m_b, P_b).

    Returns a FusionResult with weights (2,) = (omega, 1 - omega), mean (n,), cov (n, n),
    objective and gap: P^-1 = omega P_a^-1 + (1 - omega) P_b^-1 with omega minimising
    tr P ("trace") or log det P ("logdet") exactly. backend: "newton" (default) or
    "closed-form" (both exact and compiled), a conic reference ("clarabel", ...) or
    "slsqp"; polish=False returns an inexact backend's weights as they are."""
    req = core.request("ci", criterion, backend, {"polish": polish})
    means, covs = _pair(m_a, P_a, m_b, P_b, req)
    return core.run(means, covs, req, False, _PAIR)


def mbci(means, covs, p_detect, chi=None, criterion="trace", backend=None, *, growth=None,
         polish=True) -> FusionResult:
    """Modified batch CI: BCI on Phat_i = P_i / s_i with s = detection_scales(p_detect, chi).

    p_detect in [0, 1], and chi in (0, 1] or growth = 1 / chi >= 1 (the paper's chi^-1;
    give exactly one), each a scalar or (N,). The returned cov is the modified fused
    covariance Phat = (sum_i w_i s_i Y_i)^-1.
    """
    args = {"p_detect": p_detect, "polish": polish}
    args |= {k: v for k, v in (("chi", chi), ("growth", growth)) if v is not None}
    if chi is None and growth is None:
        args["chi"] = None  # let the core say that one of them is needed
    req = core.request("mbci", criterion, backend, args)
    return core.run(*core.arrays(means, covs, False, req=req), req, False)


def fuse(means, covs, method="bci", criterion="trace", backend=None, **method_args):
    """Fuse estimates means (N, n), covs (N, n, n) with a named method; a FusionResult.

    method: "bci" (default), "ci" (N = 2) or "mbci", whose weights minimise the criterion
    ("trace" or "logdet") over the simplex, solved by `backend` (one of fo.BACKENDS;
    default "newton", exact and compiled; "clarabel" is the conic reference); or a rule
    without a weight solver, which takes no backend: "naive" (independent errors),
    "known-cross" (the BLUE given the joint covariance), "fast-ci", "ifci", "ici" (N = 2),
    "ei" (N = 2); `fusion_opt.rules` says what each assumes.
    method_args: for "mbci", p_detect in [0, 1] and exactly one of chi in (0, 1] or
    growth = 1 / chi >= 1 (each a scalar or (N,)); for "known-cross", cross (N, N, n, n),
    cross[i, j] = cov(e_i, e_j); polish=False returns a conic or SLSQP backend's weights
    unpolished. Anything else is refused by name.
    """
    req = core.request(method, criterion, backend, dict(method_args))
    return core.run(*core.arrays(means, covs, False, req=req), req, False)


def optimality_gap(covs, weights, criterion="trace") -> float:
    """The certificate g(w).w - min_i g_i(w) >= f(w) - f* at weights (N,) for covs
    (N, n, n), in the objective's units: g is the gradient of f, -tr(P Y_i P) ("trace")
    or -tr(P Y_i) ("logdet") with P = P(w), and by convexity no weights do better than
    f(w) - gap."""
    covs = real_array(covs, "covs")
    if covs.ndim != 3:
        raise FusionInputError(f"covs must have shape (N, n, n), got {covs.shape}")
    req = core.request("bci", criterion, None, {})
    core.check_memory(req, covs.shape[-1], covs.shape[0])  # before allocating (fuzz M1)
    means, covs = core.arrays(np.zeros(covs.shape[:-1]), covs, False)
    w = _simplex_weights(weights, covs.shape[1])
    N = covs.shape[1]
    a = core._Arrays(1, N, covs.shape[2])
    core._prepare(means, covs, *core._unit_scales(1, N), a, core._NAMES, False)
    gap = newton.certificate(a.F[0], w, work(N, covs.shape[2]), req.trace)[0]
    return float(np.ldexp(gap, a.k[0]) if req.trace else gap)


def _simplex_weights(weights, N: int) -> np.ndarray:
    """weights (N,) as float64 on the simplex: finite, >= 0 and summing to 1 within 1e-9,
    or N times the rounding unit of a lower precision they came in (float32 weights of a
    float64 solution sum to 1 only within 1e-8), at most its square root (3.5e-4 for
    float32, 0.031 for float16: N eps passed 1 at N = 1,024 float16 weights, and all-zero
    weights gave an infinite certificate, fuzz of 2026-11-29); divided by their sum."""
    w = real_array(weights, "weights").copy()  # C-contiguous, writable: one compiled type
    given = np.asarray(weights).dtype  # (after the check: a ragged list raised in numpy)
    if w.shape != (N,):
        raise FusionInputError(f"weights must have shape ({N},), got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise FusionInputError(f"weights must be finite, got {w.tolist()}")
    if (w < 0).any():
        i = int(np.argmin(w))
        raise FusionInputError(f"weights must be >= 0, got {safe_repr(float(w[i]))} at node {i}")
    eps = np.finfo(given).eps if given.kind == "f" else 0.0
    tol = max(1e-9, min(N * eps, np.sqrt(eps)))
    if not abs(w.sum() - 1.0) <= tol:
        raise FusionInputError(f"weights must sum to 1 (within {tol:.3g}), got a sum of "
                               f"{safe_repr(float(w.sum()))}")
    return w / w.sum()


def warmup(n: int, N: int, criterion="trace", backend=None) -> float:
    """Fuse one problem of this shape so that later calls pay no first-call cost: the
    compiled kernels are loaded (compiled on the first call on a machine, then cached on
    disk) and, for "clarabel" and "scs", CVXPY's program for (n, N, criterion) is built.
    Returns the seconds it took."""
    for name, value in (("n", n), ("N", N)):
        if not is_integer(value) or value < 1:
            raise FusionInputError(f"{name} must be an integer >= 1, got {safe_repr(value)}")
    core.check_memory(core.request("bci", criterion, backend, {}), n, N)  # before allocating
    t0 = time.perf_counter()
    fuse(np.zeros((N, n)), np.broadcast_to(np.eye(n), (N, n, n)), "bci", criterion, backend)
    return time.perf_counter() - t0


def _pair(m_a, P_a, m_b, P_b, req) -> tuple[np.ndarray, np.ndarray]:
    """means (1, 2, n) and covs (1, 2, n, n) of a pair, shapes checked by name: new
    C-contiguous arrays, as `core.arrays` gives (whose checks and copies they need not pay
    again: a third of the Python cost of a small `ci`), each made by one np.array (0.9 us
    less than filling np.empty's by items)."""
    m_a, P_a = real_array(m_a, "m_a"), real_array(P_a, "P_a")
    m_b, P_b = real_array(m_b, "m_b"), real_array(P_b, "P_b")
    if m_a.shape != m_b.shape:
        raise FusionInputError(f"m_a has shape {m_a.shape} but m_b has {m_b.shape}")
    if P_a.shape != P_b.shape:
        raise FusionInputError(f"P_a has shape {P_a.shape} but P_b has {P_b.shape}")
    if m_a.ndim != 1:
        raise FusionInputError(f"m_a and m_b must have shape (n,), got {m_a.shape}")
    n = m_a.shape[0]
    if P_a.shape != (n, n):
        raise FusionInputError(f"P_a and P_b must have shape (n, n) = ({n}, {n}) for means "
                               f"of length n = {n}, got {P_a.shape}")
    if n == 0:
        raise FusionInputError("m_a and m_b are empty (n = 0)")
    core.check_memory(req, n, 2)
    return np.array((m_a, m_b))[None], np.array((P_a, P_b))[None]
