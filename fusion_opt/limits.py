"""Memory limits checked before a solver allocates, so that a problem too large for this
machine is refused with an error instead of exhausting memory (Clarabel aborts the
interpreter, uncatchably, when its KKT system does not fit).

    import fusion_opt as fo
    fo.limits.conic_memory = 16 * 2**30     # bytes; settable at any time

conic_memory: the estimated memory of a conic solve by "clarabel" / "clarabel-direct",
    whose positive semidefinite cone of order 2n makes a dense block of
    (n (2n + 1))^2 entries in the KKT system, counted twice for its factorisation
    (about 1 GB at n = 64, 100 GB at n = 200).
working_memory: the estimated memory of the native solvers' work arrays for one problem:
    the whitened nodes and the nearest-point matrix, 3 (n^2 + 1) N doubles, and five
    stacks of N n x n matrices (factors, their QR, a subproblem's factors).
array_memory: the estimated memory of the arrays a tracker (its particles and a step's
    temporaries) or a scenario simulator (a run's truth and measurements) allocates,
    checked when it is configured.
"""

from __future__ import annotations

from dataclasses import dataclass

_GIB = 2**30


@dataclass
class Limits:
    """The limits in bytes (module docstring)."""

    conic_memory: float = 4 * _GIB
    working_memory: float = 4 * _GIB
    array_memory: float = 4 * _GIB

    def __setattr__(self, name, value):
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ValueError(f"limits.{name} must be a positive number of bytes, got {value!r}")
        super().__setattr__(name, float(value))


limits = Limits()


def conic_bytes(n: int, N: int) -> float:
    """Estimated bytes of a Clarabel solve for state dimension n and N nodes."""
    psd = n * (2 * n + 1)
    return 8.0 * (2.0 * psd * psd + 4.0 * N * psd)


def working_bytes(n: int, N: int) -> float:
    """Estimated bytes of the native solvers' work arrays for one problem."""
    return 8.0 * (3.0 * (n * n + 1) * N + 5.0 * N * n * n)
