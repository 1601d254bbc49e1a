"""The compiled path of the exact backends in one call: checks and factors
(`prepare.py`), weights (`backends/newton.py`), fused estimates (`assemble.py`).

One call from Python per batch (a single problem is a batch of one) keeps the fixed cost
of a fusion in microseconds; every output goes into an array the caller made, since a
compiled function that returns new arrays pays for boxing each of them.

numba compiles the kernels it calls into this function's own cache entry and checks only
this file's source when loading it; `linalg.drop_stale_caches` drops every cached kernel
of the package when any kernel module changes, so an edit of another module (e.g. the
solver of `backends/newton.py`) cannot leave an old copy running here.
"""

from __future__ import annotations

from .assemble import assemble_one
from .backends.newton import solve_one
from .factored import work
from .linalg import jit
from .prepare import OK, prepare


@jit
def fuse_exact(means, covs, q, E, trace: bool, F, k, vertex, pnorm, where, W, rel, iters,
               mean, cov, stats) -> int:
    """prepare, then solve and assemble problem by problem (their docstrings say what each
    array holds; rel is the solver's certificate, the one of the returned estimates is
    assemble's, stats[:, 2]): assemble takes the QR and gradient the solver leaves at the
    weights instead of computing them again. Returns prepare's code, or -1 when a result
    overflows float64."""
    code = prepare(means, covs, q, E, F, k, vertex, pnorm, where)
    if code != OK:
        return code
    ws = work(F.shape[1], F.shape[2])
    finite = True
    for b in range(F.shape[0]):
        rel[b], iters[b], state = solve_one(
            F[b], trace, W[b], False, W[b], ws.At, ws.Vt, ws.R, ws.Ri, ws.P, ws.B, ws.X, ws.S,
            ws.U, ws.lam, ws.abc, ws.zeta, ws.g, ws.Et, ws.x, ws.z, ws.mask, ws.r, ws.cols,
            ws.Elt, ws.Vlt, ws.Rls, ws.qe, ws.w_try, ws.best_w)
        finite &= assemble_one(F[b], means[b], covs[b], q[b], E[b], k[b], vertex[b], pnorm[b],
                               W[b], trace, mean[b], cov[b], stats[b], state, ws.At, ws.Vt,
                               ws.R, ws.Ri, ws.P, ws.B, ws.X, ws.g, ws.z, ws.rhs)
    return OK if finite else -1
