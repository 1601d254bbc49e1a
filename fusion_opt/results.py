"""Frozen result types and the two errors of the public API.

Every fusion returns a `FusionResult` (one problem) or a `BatchFusionResult` (B problems):
the numbers together with how they were obtained (backend, status, time, certificate).
Arrays inside results are made read-only so a frozen result cannot be changed in place.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np


class Status(StrEnum):
    """How a fused estimate was obtained; one set for every rule and backend. A Status is
    a str, so `r.status == "optimal"` works.

    OPTIMAL: CI weights whose certificate proves them optimal (relative gap within the
        solver tolerance of `fusion.OPTIMAL_RTOL`).
    OPTIMAL_INACCURATE: the best weights found, whose certificate (reported in `gap`)
        falls short of that tolerance.
    CLOSED_FORM: a rule without a weight optimisation (naive, known-cross, fast-ci, ifci,
        ei) or a single node: computed by its formula; `gap` is 0.

    A solver that fails raises FusionSolverError instead, whose `status` is a string
    saying why ("infeasible", "unbounded", "user_limit", "solver_error", "memory_limit",
    ...).
    """

    OPTIMAL = "optimal"
    OPTIMAL_INACCURATE = "optimal_inaccurate"
    CLOSED_FORM = "closed_form"


class FusionInputError(ValueError):
    """An argument of a fusion call is invalid; the message names it and what is wrong."""


class FusionSolverError(RuntimeError):
    """A weight solver failed. `backend` and `status` say which and how."""

    def __init__(self, backend: str, status: str, detail: str = ""):
        self.backend, self.status, self.detail = backend, status, detail
        msg = f"backend {backend!r} failed with status {status!r}"
        super().__init__(f"{msg}: {detail}" if detail else msg)

    def __reduce__(self):  # picklable, so it crosses a process pool intact
        return type(self), (self.backend, self.status, self.detail)


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class FusionResult:
    """One fused estimate.

    weights (N,) on the simplex (for the rules naive, known-cross and ei, which have no CI
    weights, the gain shares tr(K_i) / n, which sum to 1 and may be negative for
    known-cross); mean (n,); cov (n, n) the fused covariance (for MBCI the
    modified one, Phat); objective is tr(cov) ("trace") or log det(cov) ("logdet");
    gap the optimality certificate of DESIGN §1 at `weights` (f(w) - f* <= gap), in the
    objective's units; solve_time the wall time of the weight solve in seconds (solver and
    polish); iterations the solver's, polish_iterations those of the Newton polish.
    Rules without an optimisation (naive, fast-ci, ...) report gap 0 and status "closed-form".
    """

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    objective: float
    gap: float
    status: str
    backend: str
    solve_time: float
    iterations: int
    method: str = "bci"
    criterion: str = "trace"
    polish_iterations: int = 0

    def __post_init__(self):
        for name in ("weights", "mean", "cov"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))


@dataclass(frozen=True)
class BatchFusionResult:
    """B fused estimates as arrays: weights (B, N), mean (B, n), cov (B, n, n),
    objective (B,), gap (B,), status (B,) strings, iterations (B,); solve_time is the
    wall time of the whole batch in seconds."""

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    objective: np.ndarray
    gap: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    backend: str
    solve_time: float
    method: str = "bci"
    criterion: str = "trace"

    def __post_init__(self):
        for name in ("weights", "mean", "cov", "objective", "gap", "iterations"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        status = np.array(self.status, dtype=object, copy=True)
        status.setflags(write=False)
        object.__setattr__(self, "status", status)
