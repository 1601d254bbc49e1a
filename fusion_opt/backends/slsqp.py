"""Baseline weight solver: scipy's SLSQP with the analytic gradient of `criteria.py`.

What a scipy user would write: minimise f(w) subject to sum(w) = 1 and 0 <= w_i <= 1,
from uniform weights, with f and g of DESIGN §1 (the Hessian is not used). A failure of
SLSQP raises `FusionSolverError`; its weights are only as exact as its tolerance (`fusion.py`
polishes them).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import minimize

from ..criteria import evaluate
from ..results import FusionSolverError
from . import WeightSolution

FTOL = 1e-14
MAX_ITER = 500
# SLSQP's steps solve dense least-squares problems in N unknowns, O(N^3) each: at n = 2 it
# fused 100 nodes in 0.3 s, reached its iteration limit after 5.7 s at 200 and 20 s at
# 300, and at 3,000 ran past 10 minutes (hours by that rate), so larger N are refused.
MAX_NODES = 200


def node_limit(N: int) -> str:
    """Why N nodes are refused."""
    return (f"N = {N} nodes: scipy's SLSQP fuses at most {MAX_NODES} (its steps cost O(N^3):"
            f" 5.7 s at 200 nodes, hours at 3,000); 'newton' is exact at any N")


def solve(Ys, M, criterion) -> WeightSolution:
    """Ys (N, n, n) scaled informations, M (n, n) trace weight -> weights (N,)."""
    N = len(Ys)
    t0 = time.perf_counter()

    def fun(w):
        ev = evaluate(Ys, w, criterion, M)
        return float(ev.f), ev.g

    try:
        res = minimize(fun, np.full(N, 1.0 / N), jac=True, method="SLSQP",
                       bounds=[(0.0, 1.0)] * N,
                       constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1.0,
                                     "jac": lambda w: np.ones((1, N))}],
                       options={"ftol": FTOL, "maxiter": MAX_ITER})
    except np.linalg.LinAlgError as exc:  # an iterate left the PD cone
        raise FusionSolverError("slsqp", "linalg_error", str(exc)) from None
    wall = time.perf_counter() - t0
    if not res.success or not np.all(np.isfinite(res.x)):
        raise FusionSolverError("slsqp", f"status_{res.status}", str(res.message))
    return WeightSolution(np.asarray(res.x), "optimal", int(res.nit), wall, wall)
