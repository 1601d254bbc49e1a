"""CVXPY programs for the CI weight problem, built once per shape and re-solved (DPP).

One problem per (n, N, criterion, solver) holds a single stacked Parameter `Ystack`
(n*n, N) whose column i is vec(Y'_i), so Y'(w) = reshape(Ystack @ w) is affine in w with
the data as a parameter, and a re-solve skips canonicalisation. With the unit-trace weight
M = B B^T of `scaling.py` (B a Parameter (n, n)):

    trace:   minimise tr(Z)  s.t. [[Z, B^T], [B, Y'(w)]] >= 0 (PSD),  w in simplex
             (Schur complement: Z >= B^T Y'(w)^-1 B, so tr Z = tr(M P'(w)) at the optimum)
    logdet:  maximise log det Y'(w),  w in simplex

The Schur form is used rather than cp.tr_inv, measured slower to compile and to solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import cvxpy as cp
import numpy as np

_CACHE: dict[tuple, CompiledProgram] = {}


@dataclass
class CompiledProgram:
    """A CVXPY problem with its parameters and weight variable; `solves` counts uses."""

    problem: cp.Problem
    Ystack: cp.Parameter
    B: cp.Parameter | None
    w: cp.Variable
    solves: int = 0


def _build(n: int, N: int, criterion: str) -> CompiledProgram:
    Ystack = cp.Parameter((n * n, N), name="Ystack")
    w = cp.Variable(N, name="w", nonneg=True)
    Yw = cp.reshape(Ystack @ w, (n, n), order="F")
    Yw = 0.5 * (Yw + Yw.T)
    constraints = [cp.sum(w) == 1]
    if criterion == "trace":
        B = cp.Parameter((n, n), name="B")
        Z = cp.Variable((n, n), name="Z", symmetric=True)
        constraints.append(cp.bmat([[Z, B.T], [B, Yw]]) >> 0)
        objective = cp.Minimize(cp.trace(Z))
    else:
        B = None
        objective = cp.Maximize(cp.log_det(Yw))
    return CompiledProgram(cp.Problem(objective, constraints), Ystack, B, w)


def program(n: int, N: int, criterion: str, solver: str) -> CompiledProgram:
    """The cached program for this shape (built on first use)."""
    key = (n, N, criterion, solver)
    if key not in _CACHE:
        prog = _build(n, N, criterion)
        # Compile now, on placeholder data: every solve, the first included, then takes
        # the same parametrised path, so equal data give bit-identical results.
        set_data(prog, np.broadcast_to(np.eye(n), (N, n, n)), np.eye(n) / n)
        prog.problem.get_problem_data(solver)
        _CACHE[key] = prog
    return _CACHE[key]


def clear_cache() -> None:
    _CACHE.clear()


def set_data(prog: CompiledProgram, Ys: np.ndarray, M: np.ndarray) -> None:
    """Load scaled information Ys (N, n, n) and trace weight M (n, n) into the parameters."""
    N, n = Ys.shape[:2]
    prog.Ystack.value = Ys.reshape(N, n * n).T  # column i = vec(Y_i) (symmetric: C = F order)
    if prog.B is not None:
        prog.B.value = np.linalg.cholesky(M)
