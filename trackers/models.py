"""Motion and measurement models: the coordinated-turn model and its exact discretisation.

The state is x = [x, y, vx, vy]. The continuous model is dx = F(a) x dt + L dw with

    F(a) = [[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, a], [0, 0, -a, 0]],
    L = [[0, 0], [0, 0], [1, 0], [0, 1]],   E[dw dw^T] = Qc dt,  Qc = q I2,

(a is the turn rate in rad/s; a = 0 is the constant-velocity model). Over a step dt it is
exactly x_k = A x_{k-1} + q_k, q_k ~ N(0, Q) with

    A = expm(F dt),   Q = int_0^dt expm(F s) L Qc L^T expm(F s)^T ds.

Q is computed with Van Loan's method (1978): for

    M = [[-F, L Qc L^T], [0, F^T]] dt,   expm(M) = [[., G12], [0, G22]],

G22 = A^T and Q = G22^T G12. Measurements are y = H x + r, r ~ N(0, R).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from fusion_opt import FusionInputError
from fusion_opt.results import ReadOnly
from trackers import _checks

_EPS = np.finfo(np.float64).eps
_DOUBLING_RTOL = 1e-8  # `_check_doublings`: half of float64's digits
_MAX_HALVINGS = 64  # |F|_1 dt up to 2^63: each doubling of `discretize` adds rounding

#: Indices of the position components in the state [x, y, vx, vy].
POSITION = (0, 1)


def turn_F(a: float) -> np.ndarray:
    """The (4, 4) drift matrix F(a) of the coordinated-turn model with turn rate a (rad/s)."""
    a = _checks.finite("a (turn rate)", a)
    return np.array(
        [[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, a], [0.0, 0.0, -a, 0.0]]
    )


def turn_L() -> np.ndarray:
    """The (4, 2) noise-gain matrix L: white acceleration noise enters the velocities."""
    return np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def position_H() -> np.ndarray:
    """The (2, 4) measurement matrix H = [I2 0]: the sensor measures position."""
    return np.eye(2, 4)


def _halvings(norm1: float, dt: float) -> int:
    """The s >= 0 with |F|_1 dt / 2^s <= 1/2, from logs (|F|_1 dt of 1e308 overflowed,
    and int(inf) raised: fuzz N6); _MAX_HALVINGS + 1 where it is past any count."""
    if not norm1 > 0.0:
        return 0
    with np.errstate(over="ignore"):
        x = 1.0 + np.log2(norm1) + np.log2(dt)
    return 0 if x <= 0.0 else int(np.ceil(x)) if x <= _MAX_HALVINGS else _MAX_HALVINGS + 1


def _doubled(F, LQL, dt: float, s: int) -> tuple[np.ndarray, np.ndarray]:
    """(A, Q) of `discretize` over dt from Van Loan's exponential over h = dt / 2^s, doubled
    s times; inf or NaN where they overflow."""
    n = F.shape[0]
    h = dt / 2.0**s
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = LQL
    M[n:, n:] = F.T
    # The noise block enters the exponential's upper right block linearly: where it is
    # large over the step (F = 0, |L Qc L^T| dt = 1e24: scipy's expm of that nilpotent
    # matrix gave a Q off by 100% and indefinite, fuzz O8), it is taken 2^-e times and the
    # block multiplied back by 2^e, exactly; the usual models (the block below 1) as before.
    with np.errstate(over="ignore", invalid="ignore"):
        e = max(0, math.frexp(float(np.abs(M[:n, n:]).sum(axis=0).max()) * h)[1])
        M[:n, n:] = np.ldexp(M[:n, n:], -e)
        G = expm(M * h)
        A = G[n:, n:].T
        Q = np.ldexp(A @ G[:n, n:], e)
        for _ in range(s):
            Q = Q + A @ Q @ A.T
            A = A @ A
    return A, Q


def _check_doublings(F, A, s: int, dt: float) -> None:
    """Refuses A = expm(F dt) (n, n) made by s doublings (`_doubled`) whose log |det A|
    differs from tr(F) dt, which it equals exactly, by more than _DOUBLING_RTOL beyond what
    the LU of A can resolve (n eps cond(A); nothing where cond(A) is past 1 / eps: a stiff
    stable model's A underflows, and its doublings shrink their rounding anyway). Each
    doubling doubles the drift of a rotation's size: a turn rate of 1e17 rad/s over dt = 0.1 (55
    doublings) made a "rotation" that grew velocities by 54 % a step, 1.8e18 one that
    shrank them to 1.8e-5 (fuzz U8)."""
    n = A.shape[0]
    sign, logdet = np.linalg.slogdet(A)
    volume = float(np.trace(F)) * dt
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        resolved = n * _EPS * np.linalg.cond(A) + _EPS * abs(volume)
    if not resolved < 1.0:  # cond(A) past 1 / eps (or inf): the LU cannot tell
        return
    drift = abs(logdet - volume) if sign > 0 else np.inf
    if drift > _DOUBLING_RTOL + resolved:
        raise FusionInputError(
            f"dt = {dt:g} is too long a step for this F: expm(F dt), made from 2^{s} steps "
            f"of dt / 2^{s}, has log det {logdet:.6g} where tr(F) dt = {volume:.6g} (its "
            f"rounding grew past {_DOUBLING_RTOL:g}); give a shorter step")


def discretize(F, L, Qc, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation of dx = F x dt + L dw, E[dw dw^T] = Qc dt, over a step dt.

    F is (n, n), L is (n, s), Qc is (s, s) symmetric PSD, dt > 0.
    Returns (A, Q): A = expm(F dt) (n, n), Q the (n, n) process-noise covariance.

    Van Loan's block exponential holds expm(-F h), which for a stiff or stable F and a
    long step is huge and cancels in Q = A G12 (F = [[0, 1], [0, -50]], dt = 1 gave a Q
    that was not even PSD). So it is taken over h = dt / 2^s with |F|_1 h <= 1/2, and the
    step is doubled s times, exactly: Q(2h) = Q(h) + A(h) Q(h) A(h)^T, A(2h) = A(h)^2
    (s = 0, the one exponential, wherever |F|_1 dt <= 1/2, e.g. every turn model here).
    Each doubling doubles the rounding of a rotation: a result whose determinant has
    drifted from exp(tr(F) dt) is refused (`_check_doublings`).
    """
    F = _checks.finite_array("F", F, ndim=2)
    n = F.shape[0]
    if F.shape != (n, n) or n == 0:
        raise FusionInputError(f"F must be square with n >= 1, got shape {F.shape}")
    L = _checks.finite_array("L", L, ndim=2)
    if L.shape[0] != n or L.shape[1] == 0:
        raise FusionInputError(f"L must be ({n}, s) with s >= 1 to match F, got shape "
                               f"{L.shape}")
    Qc = _checks.psd_covariance("Qc", Qc, L.shape[1])
    dt = _checks.positive("dt", dt)
    norm1 = float(np.abs(F).sum(axis=0).max())
    s = _halvings(norm1, dt)
    if s > _MAX_HALVINGS:
        product = f"{norm1 * dt:.3g}" if norm1 * dt < np.inf else f"{norm1:.3g} x {dt:.3g}"
        raise FusionInputError(f"dt = {dt:g} is too long a step for this F: |F|_1 dt = "
                               f"{product} (at most 2^{_MAX_HALVINGS - 1})")
    A, Q = _doubled(F, L @ Qc @ L.T, dt, s)
    if not (np.isfinite(A).all() and np.isfinite(Q).all()):
        raise FusionInputError(f"dt = {dt:g} is too long a step for this F and Qc: its "
                               "transition or process noise overflows float64")
    if s:
        _check_doublings(F, A, s, dt)
    # Q is symmetric in exact arithmetic; remove the rounding asymmetry so Cholesky works
    # (halved before the sum, which would overflow for entries past 8.99e307).
    return A, 0.5 * Q + 0.5 * Q.T


@dataclass(frozen=True, eq=False)
class LinearGaussian(ReadOnly):
    """A linear-Gaussian state-space model x_k = A x_{k-1} + q, y_k = H x_k + r.

    A: (n, n) transition; Q: (n, n) process-noise covariance (PSD);
    H: (d, n) measurement matrix; R: (d, d) measurement-noise covariance (PD).
    Arrays are validated (finite and real: a complex matrix is refused, not truncated),
    copied and made read-only on construction, and stay read-only in a pickled or copied
    model (`fusion_opt.results.ReadOnly`; they came back writeable: fuzz6 1).
    """

    A: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray

    def __post_init__(self) -> None:
        A = _checks.finite_array("A", self.A, ndim=2)
        n = A.shape[0]
        if A.shape != (n, n) or n == 0:
            raise FusionInputError(f"A must be square with n >= 1, got shape {A.shape}")
        Q = _checks.psd_covariance("Q", self.Q, n)
        H = _checks.finite_array("H", self.H, ndim=2)
        if H.shape[1] != n or H.shape[0] == 0:
            raise FusionInputError(f"H must be (d, {n}) with d >= 1 to match A, got shape "
                                   f"{H.shape}")
        R = _checks.covariance("R", self.R, H.shape[0])
        for name, arr in (("A", A), ("Q", Q), ("H", H), ("R", R)):
            arr = np.array(arr, dtype=float)
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def d(self) -> int:
        """Measurement dimension."""
        return self.H.shape[0]


def turn_model(a: float, q: float, r: float, dt: float) -> LinearGaussian:
    """The discretised coordinated-turn model with Qc = q I2, H = [I2 0], R = r I2."""
    q = _checks.positive("q", q)
    r = _checks.positive("r", r)
    A, Q = discretize(turn_F(a), turn_L(), q * np.eye(2), dt)
    return LinearGaussian(A, Q, position_H(), r * np.eye(2))
