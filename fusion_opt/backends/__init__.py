"""Weight solvers (backends) and their registry.

"newton" and "closed-form" (N = 2) are native and compiled (`newton.py`, `closed_form.py`):
the fusion core calls them once on the factors of a whole batch. The others solve one
congruence-scaled problem (Ys (N, n, n), M (n, n), criterion; `scaling.py`) and return
weights near the simplex, which the core puts exactly on the simplex, polishes by Newton
steps and certifies: "clarabel" (CVXPY with Clarabel, the conic reference), "scs" (CVXPY
with SCS), "clarabel-direct" (the same conic program handed to Clarabel without CVXPY) and
"slsqp" (scipy, the baseline a user would write).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..results import FusionSolverError


@dataclass(frozen=True)
class WeightSolution:
    """w (N,), the solver's status string, its iteration count, wall time (s) of the
    backend call and the solver's own reported time (s; equal to solve_time if native)."""

    w: np.ndarray
    status: str
    iterations: int
    solve_time: float
    solver_time: float | None = None


def with_attempts(backend: str, attempts: Sequence[dict],
                  once: Callable[[dict], WeightSolution]) -> WeightSolution:
    """The first usable solution of once(options) over the option sets in turn (a conic
    solver that fails is tried once more with other settings); FusionSolverError with the
    last failure's status otherwise. `once` raises FusionSolverError on a failed status."""
    error = FusionSolverError(backend, "solver_error", "no attempt was made")
    for options in attempts:
        try:
            return once(options)
        except FusionSolverError as exc:
            error = exc
    raise error


def _lazy(module: str, *args):
    """The `solve` of a backend module, imported on first use (CVXPY is slow to import)."""

    def solve(Ys, M, criterion):
        return importlib.import_module(f".{module}", __name__).solve(*args, Ys, M, criterion)

    return solve


REGISTRY = {"clarabel": _lazy("cvxpy_backends", "clarabel"),
            "scs": _lazy("cvxpy_backends", "scs"),
            "clarabel-direct": _lazy("clarabel_direct"),
            "slsqp": _lazy("slsqp")}
# Native, compiled and exact to the certificate's rounding level: called by the core on
# whole batches, never polished.
EXACT = frozenset({"newton", "closed-form"})
BACKENDS = ("newton", "closed-form", "clarabel", "clarabel-direct", "scs", "slsqp")
