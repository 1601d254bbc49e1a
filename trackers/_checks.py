"""Input checks shared by the trackers' public entry points.

Every check raises ``ValueError`` whose message names the argument and what is wrong, so a
caller who passes a (n, 1) column, a NaN or a probability of 1.3 learns which one at once.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def finite_array(name: str, value, ndim: int | None = None, shape=None) -> np.ndarray:
    """Return ``value`` as a float array after checking its dimension, shape and finiteness.

    ``shape`` may contain ``None`` for a free axis.
    """
    arr = np.asarray(value, dtype=float)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(
            s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)
        ):
            want = tuple("any" if s is None else s for s in shape)
            raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _symmetric(name: str, value, n: int) -> tuple[np.ndarray, float]:
    """A finite symmetric (n, n) matrix and its scale max(1, max |P|)."""
    P = finite_array(name, value, shape=(n, n))
    scale = max(1.0, float(np.max(np.abs(P))))
    if not np.allclose(P, P.T, rtol=1e-9, atol=1e-12 * scale):
        raise ValueError(f"{name} must be symmetric")
    return P, scale


def covariance(name: str, value, n: int) -> np.ndarray:
    """Check a symmetric positive-definite (n, n) matrix (Cholesky must succeed)."""
    P, _ = _symmetric(name, value, n)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} must be positive definite") from None
    return P


def psd_covariance(name: str, value, n: int) -> np.ndarray:
    """Check a symmetric positive-semidefinite (n, n) matrix (a process noise may be singular)."""
    P, scale = _symmetric(name, value, n)
    if np.min(np.linalg.eigvalsh(0.5 * (P + P.T))) < -1e-10 * scale:
        raise ValueError(f"{name} must be positive semidefinite")
    return P


def probability(name: str, value) -> float:
    p = float(value)
    if not np.isfinite(p) or not 0.0 <= p <= 1.0:
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}")
    return p


def positive(name: str, value) -> float:
    x = float(value)
    if not np.isfinite(x) or x <= 0.0:
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return x


def positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def generator(name: str, value) -> np.random.Generator:
    if not isinstance(value, np.random.Generator):
        raise ValueError(f"{name} must be a numpy.random.Generator, got {type(value).__name__}")
    return value


def scans(value: Sequence, d: int) -> list[np.ndarray]:
    """Check a sequence of per-step measurement arrays, each (k_t, d) with k_t >= 0."""
    if isinstance(value, np.ndarray) and value.ndim != 3:
        raise ValueError(f"scans must be a sequence of (k_t, {d}) arrays, got array {value.shape}")
    out = []
    for t, s in enumerate(value):
        arr = np.asarray(s, dtype=float)
        if arr.size == 0:
            arr = arr.reshape(0, d)
        if arr.ndim != 2 or arr.shape[1] != d:
            raise ValueError(f"scans[{t}] must have shape (k, {d}), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"scans[{t}] contains non-finite values")
        out.append(arr)
    if not out:
        raise ValueError("scans must contain at least one step")
    return out
