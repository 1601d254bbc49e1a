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
        solver tolerance of `core.OPTIMAL_RTOL`).
    OPTIMAL_INACCURATE: the best weights found, whose certificate (reported in `gap`)
        falls short of that tolerance.
    CLOSED_FORM: a rule without a weight optimisation (naive, known-cross, fast-ci, ifci,
        ei), for any number of nodes: computed by its formula; `gap` is 0. (A single node
        through ci, bci or mbci is OPTIMAL: its weight problem is solved by w = 1, gap 0.)

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
    """A weight solver, or a rule without one, failed. `backend` and `status` say which
    and how; `role` is "backend", or "method" for a rule (whose name `backend` holds)."""

    def __init__(self, backend: str, status: str, detail: str = "", role: str = "backend"):
        self.backend, self.status, self.detail, self.role = backend, status, detail, role
        msg = f"{role} {backend!r} failed with status {status!r}"
        super().__init__(f"{msg}: {detail}" if detail else msg)

    def __reduce__(self):  # picklable, so it crosses a process pool intact
        return type(self), (self.backend, self.status, self.detail, self.role)


def overflow_error(mean, cov, objective, batch: bool, b: int | None = None
                   ) -> FusionInputError:
    """What of problem b (default: the first of mean (B, n), cov (B, n, n), objective (B,)
    that is not finite) overflowed: its objective (a trace of 1e308 I) or the estimate;
    "problem b: " first in a batch."""
    estimate = np.isfinite(mean).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    if b is None:
        b = int(np.flatnonzero(~(estimate & np.isfinite(objective)))[0])
    what = "objective (its trace)" if estimate[b] else "estimate"
    return FusionInputError(
        f"{f'problem {b}: ' if batch else ''}the fused {what} overflows float64 "
        "(covariances or means too large, or MBCI scales too small for it to be represented)")


def in_context(exc: FusionInputError | FusionSolverError, before: str, after: str = ""):
    """A new error of exc's type whose message is exc's with `before` and `after` around
    it (a FusionSolverError keeps its backend, status and role; the words go around its
    detail): what a network says of the node or group a fusion failed in."""
    if isinstance(exc, FusionSolverError):
        return FusionSolverError(exc.backend, exc.status, f"{before}{exc.detail}{after}",
                                 exc.role)
    return FusionInputError(f"{before}{exc}{after}")


def status_array(status) -> np.ndarray:
    """A read-only object array of Status from Status values or their strings."""
    values = np.asarray(status, dtype=object).ravel().tolist()
    table = {v: Status(v) for v in set(values)}
    out = np.empty(len(values), dtype=object)
    out[:] = [table[v] for v in values]
    out.setflags(write=False)
    return out


WEIGHTS_ARE = {
    "ci_weights": "CI weights on the simplex",
    "gain_shares": "gain shares tr(K_i)/n (no CI weights; they sum to 1 and may be negative)",
}


class ReadOnly:
    """A frozen holder of read-only arrays that stays read-only when pickled, copied or
    deep-copied: numpy gives an unpickled or deep-copied array back writeable, and a
    copied result's covariance could be written in place (fuzz of 2026-11-29)."""

    def __setstate__(self, state: dict) -> None:
        for value in state.values():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
        self.__dict__.update(state)


def _frozen(a, dtype=np.float64) -> np.ndarray:
    """A read-only copy (results own their arrays)."""
    a = a.copy() if type(a) is np.ndarray and a.dtype == dtype else np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, repr=False, eq=False)
class FusionResult(ReadOnly):
    """One fused estimate.

    weights (N,): the CI weights on the simplex, or for the rules without them (naive,
    known-cross, ei) the gain shares tr(K_i) / n, which sum to 1 and may be negative;
    `weights_are` says which ("ci_weights" or "gain_shares"). mean (n,); cov (n, n) the
    fused covariance (for MBCI the modified one, Phat); objective tr(cov) ("trace") or
    log det(cov) ("logdet"); gap the optimality certificate at `weights`,
    g(w).w - min_i g_i(w) with g the gradient of the objective (so f(w) - f* <= gap by
    convexity), in the objective's units (0 for rules without an optimisation). At a
    single node (a vertex) it bounds the certificate for the covariances as fused,
    sym(P_i) / s_i as rounded (the inputs themselves when symmetric, for ci and bci), the
    scales' own error counted (`factored.vertex_gap`); a fused result's comes from the
    nodes' Cholesky factors and holds for covariances within their rounding, (n + 3) eps
    |C_i| |C_i|^T of those given (P_i = C_i C_i^T), which moves it negligibly for "trace"
    and by up to about n^2 eps cond(P_i) nats for "logdet";
    status a `Status`; backend the weight solver; solve_time the wall time of the weight
    solve in seconds (solver and polish); iterations the solver's, polish_iterations those
    of the Newton polish. Its arrays are read-only, in pickled and copied results too; == is
    identity, as for an Estimates (compare the fields, e.g. np.array_equal(a.cov, b.cov)).
    """

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    objective: float
    gap: float
    status: Status
    backend: str
    solve_time: float
    iterations: int
    method: str = "bci"
    criterion: str = "trace"
    polish_iterations: int = 0
    weights_are: str = "ci_weights"

    def __post_init__(self):
        for name in ("weights", "mean", "cov"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        if type(self.status) is not Status:
            object.__setattr__(self, "status", Status(self.status))

    @classmethod
    def owning(cls, weights, mean, cov, objective, gap, status, backend, solve_time,
               iterations, method, criterion, polish_iterations, weights_are) -> FusionResult:
        """The result of every field in field order, taking ownership of the float64 arrays
        weights, mean and cov (the caller's views, which nothing else writes to), made
        read-only in place, and of a Status: what __init__ does without its copies and
        checks, which cost a third of a small fusion (the fields passed by position and
        named once here, not collected as **fields: 0.14 us less of 1.8)."""
        weights.setflags(write=False)  # half the cost of .flags.writeable = False
        mean.setflags(write=False)
        cov.setflags(write=False)
        result = object.__new__(cls)
        result.__dict__.update(
            weights=weights, mean=mean, cov=cov, objective=objective, gap=gap, status=status,
            backend=backend, solve_time=solve_time, iterations=iterations, method=method,
            criterion=criterion, polish_iterations=polish_iterations, weights_are=weights_are)
        return result

    def __repr__(self) -> str:
        with np.printoptions(precision=6, suppress=False, threshold=20, edgeitems=3):
            return (f"FusionResult(method={self.method!r}, criterion={self.criterion!r}, "
                    f"backend={self.backend!r}, status={self.status.value!r},\n"
                    f"  objective={self.objective:.12g}, gap={self.gap:.3g},\n"
                    f"  weights={self.weights}  # {WEIGHTS_ARE[self.weights_are]}\n"
                    f"  mean={self.mean},\n  cov={_indent(self.cov)})")


@dataclass(frozen=True, repr=False, eq=False)
class BatchFusionResult(ReadOnly):
    """B fused estimates as arrays: weights (B, N) (as `weights_are` says, see
    FusionResult), mean (B, n), cov (B, n, n), objective (B,), gap (B,), status (B,) of
    `Status`, iterations (B,) int; solve_time is the wall time of the whole batch (s).
    Read-only and compared by identity, as a FusionResult."""

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
    weights_are: str = "ci_weights"

    def __post_init__(self):
        for name in ("weights", "mean", "cov", "objective", "gap"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        object.__setattr__(self, "iterations", _frozen(self.iterations, np.int64))
        object.__setattr__(self, "status", status_array(self.status))

    @classmethod
    def owning(cls, weights, mean, cov, objective, gap, status, iterations, backend,
               solve_time, method, criterion, weights_are) -> BatchFusionResult:
        """The result of every field in field order, taking ownership of the float64 arrays
        weights, mean and cov and of status, an object array of Status (the caller's new
        arrays, which nothing else writes to), made read-only in place, or a tuple of
        Status; objective, gap and iterations are copied (they may be views of the caller's
        scratch arrays). What __init__ does without its conversions (`status_array` alone
        took 4 us of a processing node's batch of four problems)."""
        if type(status) is not np.ndarray:
            status = np.array(status, dtype=object)
        for a in (weights, mean, cov, status):
            a.setflags(write=False)
        result = object.__new__(cls)
        result.__dict__.update(
            weights=weights, mean=mean, cov=cov, objective=_frozen(objective),
            gap=_frozen(gap), status=status, iterations=_frozen(iterations, np.int64),
            backend=backend, solve_time=solve_time, method=method, criterion=criterion,
            weights_are=weights_are)
        return result

    def __len__(self) -> int:
        return len(self.objective)

    def __repr__(self) -> str:
        B, N = self.weights.shape
        counts = ", ".join(f"{s.value}: {int((self.status == s).sum())}" for s in Status
                           if (self.status == s).any())
        scale = np.abs(self.objective) if self.criterion == "trace" else 1.0
        worst = float(np.max(self.gap / scale)) if B else 0.0
        return (f"BatchFusionResult(B={B}, N={N}, n={self.mean.shape[1]}, "
                f"method={self.method!r}, criterion={self.criterion!r}, "
                f"backend={self.backend!r}, status {{{counts}}}, worst relative gap "
                f"{worst:.2g}, solve_time={self.solve_time:.3g} s; weights are "
                f"{WEIGHTS_ARE[self.weights_are]})")


def _indent(a: np.ndarray) -> str:
    return str(a).replace("\n", "\n      ")
