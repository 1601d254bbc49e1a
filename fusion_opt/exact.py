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

from .assemble import assemble
from .backends.newton import solve
from .linalg import jit
from .prepare import OK, prepare


@jit
def fuse_exact(means, covs, q, E, trace: bool, F, k, vertex, pnorm, where, W, rel, iters,
               mean, cov, stats) -> int:
    """prepare, solve, assemble (their docstrings say what each array holds; rel is the
    solver's scratch: the certificate of the returned estimates is assemble's, stats[:, 2],
    so the pairwise solver need not compute its own). Returns prepare's code, or -1 when
    a result overflows float64."""
    code = prepare(means, covs, q, E, F, k, vertex, pnorm, where)
    if code != OK:
        return code
    solve(F, trace, W, False, W, rel, iters, False)
    return OK if assemble(F, means, covs, q, E, k, vertex, pnorm, W, trace, mean, cov,
                          stats) else -1
