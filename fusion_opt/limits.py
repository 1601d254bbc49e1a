"""Memory limits checked before a solver allocates, so that a problem too large for this
machine is refused with an error instead of exhausting memory (Clarabel aborts the
interpreter, uncatchably, when its KKT system does not fit).

    import fusion_opt as fo
    fo.limits.conic_memory = 16 * 2**30     # bytes; settable at any time

conic_memory: the estimated memory of a conic solve by "clarabel" / "clarabel-direct",
    whose positive semidefinite cone of order 2n makes a dense block of
    (n (2n + 1))^2 entries in the KKT system, counted four times (the system, its
    factorisation and their copies: a fuzz measured peak resident memory of 2.5 GB at
    n = 64 and 5.5 GB at n = 80, whole process, where twice the block estimated 1.1 and
    2.7 GB and let n = 90, 8.5 GB, pass the default limit); 2.2 GB at n = 64.
working_memory: the estimated memory of the native solvers' work arrays for one problem:
    the whitened nodes and the nearest-point matrix, 3 (n^2 + 1) N doubles, and five
    stacks of N n x n matrices (factors, their QR, a subproblem's factors); for "slsqp"
    also scipy SLSQP's workspace, about 10 N^2 doubles (N = 20000 asked for 31 GiB); for
    the known-cross rule its whitened joint covariance (`joint_bytes`); and, for any
    method, a whole batch's arrays (`batch_bytes`), counted together with them.
array_memory: the estimated memory of the arrays a tracker (its particles and a step's
    temporaries) or a scenario simulator (a run's truth and measurements) allocates,
    checked when it is configured, and of an Estimates' checked copies
    (`estimates_bytes`), checked before they are made.
"""

from __future__ import annotations

from dataclasses import dataclass

from .results import FusionInputError
from .validation import is_real, safe_repr, wide_float

_GIB = 2**30


@dataclass
class Limits:
    """The limits in bytes (module docstring)."""

    conic_memory: float = 4 * _GIB
    working_memory: float = 4 * _GIB
    array_memory: float = 4 * _GIB

    def __setattr__(self, name, value):
        if name not in self.__dataclass_fields__:  # a misspelt limit would do nothing
            raise AttributeError(f"fusion_opt.limits has no limit {safe_repr(name)}; its limits "
                                 f"are {tuple(self.__dataclass_fields__)}")
        try:
            ok = is_real(value) and float(value) > 0
        except OverflowError:  # an int past the float range (10**400)
            ok = False
        if not ok:
            raise ValueError(f"limits.{name} must be a positive number of bytes (inf: no "
                             f"limit), got {safe_repr(value)}")
        super().__setattr__(name, float(value))


limits = Limits()


def conic_bytes(n: int, N: int) -> float:
    """Estimated bytes of a Clarabel solve for state dimension n and N nodes."""
    n, N = wide_float(n), wide_float(N)
    psd = n * (2 * n + 1)
    return 8.0 * (4.0 * psd * psd + 4.0 * N * psd)


def batch_bytes(B: int, N: int, n: int) -> float:
    """Estimated bytes of the arrays of a batch of B problems (B = 1: one fusion): copies
    of its means and covariances, their factors, a rule's scaled covariances and the
    weights, about 4 n^2 + 2 n + 4 doubles a node, and each problem's results, computed
    and then copied into the result with their status, 2 n^2 + 2 n + 32 (without these a
    batch at n = 1, 2 peaked at 1.2-1.7 times the estimate: fuzz U9); checked against
    working_memory before anything is copied."""
    B, N, n = wide_float(B), wide_float(N), wide_float(n)
    return 8.0 * B * (N * (4.0 * n * n + 2.0 * n + 4.0) + 2.0 * n * n + 2.0 * n + 32.0)


def working_bytes(n: int, N: int, backend: str | None = None) -> float:
    """Estimated bytes of the native solvers' work arrays for one problem, and of SLSQP's
    workspace for backend "slsqp"."""
    n, N = wide_float(n), wide_float(N)
    slsqp = 10.0 * (N + 1) ** 2 if backend == "slsqp" else 0.0
    return 8.0 * (3.0 * (n * n + 1) * N + 5.0 * N * n * n + slsqp)


def joint_bytes(n: int, N: int) -> float:
    """Estimated bytes of known-cross's work arrays for one problem: the joint whitened
    node by node and its Cholesky factor, (N n)^2 doubles each (the copy of cross a batch
    may need is counted with the batch's arrays, `core.over_memory`)."""
    n, N = wide_float(n), wide_float(N)
    return 8.0 * 2.0 * (N * n) ** 2


def estimates_bytes(m: int, n: int) -> float:
    """Estimated bytes of an Estimates of m estimates of an n-dimensional state as it is
    built: its copies of the means and ids, and of the covariances three times (the
    checks' symmetrised stack, its frozen copy and the finiteness mask, counted as one)."""
    m, n = wide_float(m), wide_float(n)
    return 8.0 * m * (n + 1 + 3.0 * n * n)


def fits(what: str, n_bytes: float, limit: str = "array_memory") -> None:
    """Refuses (FusionInputError), before allocating, arrays of about n_bytes over the
    limit of that name (array_memory unless told); `what` names the arguments that set
    their size."""
    cap = getattr(limits, limit)
    if n_bytes > cap:
        raise FusionInputError(
            f"{what}: about {n_bytes / 2**30:.3g} GiB of arrays, over the limit of "
            f"{cap / 2**30:.3g} GiB (fusion_opt.limits.{limit})")
