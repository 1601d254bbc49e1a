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
