"""Batched fusion: B independent problems as arrays, through the same path as `fuse`.

    r = fuse_batch(means, covs, method="bci", criterion="trace", backend=None, **method_args)
    # means (B, N, n), covs (B, N, n, n) -> r.weights (B, N), r.mean (B, n), r.cov (B, n, n),
    # r.objective (B,), r.gap (B,), r.status (B,)

Every problem is solved exactly as `fuse` solves it alone (same checks, scaling, solver
and certificate, bit for bit), whatever the other problems of the batch. With the native
backends ("newton", the default, and "closed-form") all problems go to the compiled
solver in one call; other backends solve problem by problem and are polished like `fuse`;
each rule fuses the whole batch in one compiled call. The options and their defaults are
those of `fuse`,
listed once in `core.py`; per-problem MBCI arguments may be (B, N), known-cross's cross
(B, N, N, n, n).
"""

from __future__ import annotations

from . import core
from .results import BatchFusionResult


def fuse_batch(means, covs, method="bci", criterion="trace", backend=None,
               **method_args) -> BatchFusionResult:
    """Fuse B problems of N estimates each: means (B, N, n), covs (B, N, n, n); a
    BatchFusionResult with weights (B, N), mean (B, n), cov (B, n, n), objective (B,),
    gap (B,), status (B,) and iterations (B,).

    method, criterion, backend and method_args: as in `fo.fuse`, per-problem MBCI
    arguments (p_detect, chi or growth) scalars, (N,) or (B, N), known-cross's cross
    (B, N, N, n, n). Each problem comes out bit for bit as `fo.fuse` gives it alone."""
    req = core.request(method, criterion, backend, dict(method_args))
    return core.run(*core.arrays(means, covs, True, req=req), req, True)
