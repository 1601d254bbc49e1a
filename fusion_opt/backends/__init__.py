"""Weight solvers (backends) and their registry.

A backend maps a scaled problem (Ys (N, n, n), M (n, n), criterion; see `scaling.py`) to
weights near the simplex. `fusion.py` puts them exactly on the simplex, polishes them and
computes the optimality certificate, the same way for every backend.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WeightSolution:
    """w (N,), the solver's status string, its iteration count, wall time (s) of the
    backend call and the solver's own reported time (s; equal to solve_time if native)."""

    w: np.ndarray
    status: str
    iterations: int
    solve_time: float
    solver_time: float | None = None


def _cvxpy(name):
    def solve(Ys, M, criterion):
        from .cvxpy_backends import solve as cvx_solve

        return cvx_solve(name, Ys, M, criterion)

    return solve


def _newton(Ys, M, criterion):
    """One problem: `newton.solve_one`, or for N = 2 the 1-D Newton of `closed_form`."""
    import time

    from . import closed_form, newton

    if len(Ys) == 2:
        return closed_form.solve(Ys, M, criterion)
    t0 = time.perf_counter()
    sol = newton.solve_one(Ys, M, criterion)
    status = "optimal" if sol.converged[0] else "optimal_inaccurate"
    wall = time.perf_counter() - t0
    return WeightSolution(sol.w[0], status, int(sol.iterations[0]), wall, wall)


def _native(module):
    """The `solve` of a backend module, imported on first use (as the CVXPY ones are)."""

    def solve(Ys, M, criterion):
        return importlib.import_module(f".{module}", __name__).solve(Ys, M, criterion)

    return solve


REGISTRY = {"clarabel": _cvxpy("clarabel"), "scs": _cvxpy("scs"),
            "clarabel-direct": _native("clarabel_direct"), "newton": _newton,
            "closed-form": _native("closed_form"), "slsqp": _native("slsqp")}
# Backends whose weights are exact to the certificate's rounding level: not polished.
EXACT = frozenset({"newton", "closed-form"})
BACKENDS = tuple(REGISTRY)
