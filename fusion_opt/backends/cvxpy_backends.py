"""Weight solvers through CVXPY: "clarabel" (the reference) and "scs".

Each solves the cached DPP program of `programs.py` on the scaled problem and maps the
solver's status to weights or to `FusionSolverError`. Tolerances are tight; the Newton
polish of `fusion.py` then takes the certificate to machine precision.

One CVXPY solve at a time in a process (`_LOCK`): threads fusing problems of one shape
share its cached program, and one thread's data overwrote another's parameters between
`set_data` and the solve (fuzz of 2026-11-29: 17 of 80 results of 8 threads were another
problem's weights); `warnings.catch_warnings`, around each solve, is not thread-safe
either. The native backends and "clarabel-direct" keep no shared state and run unlocked.
"""

from __future__ import annotations

import threading
import time
import warnings

import cvxpy as cp
import numpy as np

from ..programs import program, set_data
from ..results import FusionSolverError
from . import WeightSolution, clarabel_direct, with_attempts

# Each solver with the option sets to try in turn (Clarabel's second drops chordal
# decomposition, see clarabel_direct.ATTEMPTS).
SOLVERS = {
    "clarabel": (cp.CLARABEL, clarabel_direct.ATTEMPTS),
    "scs": (cp.SCS, ({"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 200_000},)),
}
_OK = {cp.OPTIMAL: "optimal", cp.OPTIMAL_INACCURATE: "optimal_inaccurate"}
_LOCK = threading.Lock()


def solve(backend: str, Ys: np.ndarray, M: np.ndarray, criterion: str) -> WeightSolution:
    """Ys (N, n, n), M (n, n) of a scaled problem; returns weights and solver stats."""
    with _LOCK:  # the program's parameters hold this problem until its solve is read
        return _solve_locked(backend, Ys, M, criterion)


def _solve_locked(backend: str, Ys: np.ndarray, M: np.ndarray, criterion: str):
    """`solve`, holding `_LOCK`."""
    N, n = Ys.shape[:2]
    solver, attempts = SOLVERS[backend]
    prog = program(n, N, criterion, solver)
    set_data(prog, Ys, M)
    t0 = time.perf_counter()

    def once(options) -> WeightSolution:
        try:
            _solve(prog, solver, options)
        except cp.SolverError as exc:
            raise FusionSolverError(backend, "solver_error", str(exc)) from None
        status, w = prog.problem.status, prog.w.value
        if status not in _OK or w is None or not np.all(np.isfinite(w)):
            raise FusionSolverError(backend, str(status))
        stats = prog.problem.solver_stats
        return WeightSolution(np.array(w), _OK[status], int(stats.num_iters or 0),
                              time.perf_counter() - t0, stats.solve_time)

    return with_attempts(backend, attempts, once)


def _solve(prog, solver, options) -> None:
    prog.solves += 1
    with warnings.catch_warnings():  # "may be inaccurate": the status says so, polish fixes
        warnings.simplefilter("ignore", UserWarning)
        # warm_start=False: CVXPY would otherwise update the previous solver in place, whose
        # result differs in the last bits from a fresh one, so equal data could give
        # different weights depending on what was solved before.
        prog.problem.solve(solver=solver, warm_start=False, **options)
