"""Input checks shared by the trackers' public entry points.

Every check raises ``fusion_opt.FusionInputError`` (a ``ValueError``) whose message names the
argument and what is wrong, so a caller who passes a (n, 1) column, a NaN, a string, a
boolean, a complex number or a probability of 1.3 learns which one at once; nothing is
silently converted (a complex value is never truncated to its real part).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from fusion_opt import FusionInputError
from fusion_opt import validation as _fo
from fusion_opt.estimates import Estimates, check_exact_time, check_forward
from fusion_opt.limits import fits  # noqa: F401 (the trackers call _checks.fits)


def finite_array(name: str, value, ndim: int | None = None, shape=None) -> np.ndarray:
    """``value`` as a finite real float array after checking its dimension and shape.

    ``shape`` may contain ``None`` for a free axis.
    """
    arr = _fo.real_array(value, name)
    if ndim is not None and arr.ndim != ndim:
        raise FusionInputError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(
            s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)
        ):
            want = tuple("any" if s is None else s for s in shape)
            raise FusionInputError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise FusionInputError(f"{name} contains non-finite values")
    return arr


def real(name: str, value) -> float:
    """A real scalar (int, float or a 0-d real array), refusing None, strings, booleans and
    complex numbers; NaN and inf pass here (the callers say which range is allowed)."""
    if not _fo.is_real(_fo.scalar(value)):
        raise FusionInputError(f"{name} must be a real number, got {_fo.safe_repr(value)}")
    return _fo.wide_float(value)  # an int past float64 (2**2000): +-inf, refused by range


def finite(name: str, value) -> float:
    x = real(name, value)
    if not np.isfinite(x):
        raise FusionInputError(f"{name} must be a finite real number, got {_fo.safe_repr(value)}")
    return x


def nonnegative(name: str, value) -> float:
    x = real(name, value)
    if not (np.isfinite(x) and x >= 0.0):
        raise FusionInputError(f"{name} must be a finite number >= 0, got {_fo.safe_repr(value)}")
    return x


def positive(name: str, value) -> float:
    x = real(name, value)
    if not (np.isfinite(x) and x > 0.0):
        raise FusionInputError(f"{name} must be a finite positive number, got "
                               f"{_fo.safe_repr(value)}")
    return x


def variance(name: str, sd) -> float:
    """sd^2 of a finite positive standard deviation sd, refused by name when the square
    leaves float64's normal range (1e200 squared overflows; 1e-200 squared is 0)."""
    s = positive(name, sd)
    v = s * s
    if not np.finfo(float).tiny <= v < np.inf:
        raise FusionInputError(f"{name} = {_fo.safe_repr(sd)}: its square, the variance, is "
                               "outside float64's range")
    return v


def probability(name: str, value) -> float:
    p = real(name, value)
    if not 0.0 <= p <= 1.0:  # False for NaN
        raise FusionInputError(f"{name} must be a probability in [0, 1], got "
                               f"{_fo.safe_repr(value)}")
    return p


def positive_int(name: str, value) -> int:
    if not _fo.is_integer(value) or value < 1:
        raise FusionInputError(f"{name} must be an integer >= 1, got {_fo.safe_repr(value)}")
    return int(value)


def boolean(name: str, value) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise FusionInputError(f"{name} must be True or False, got {_fo.safe_repr(value)}")
    return bool(value)


def node_name(value):
    """A tracker's name, stamped on its Estimates as the node: any hashable, or None."""
    if value is not None and not _fo.hashable(value):
        raise FusionInputError(f"name must be hashable (e.g. a string), got "
                               f"{type(value).__name__}")
    return value


def step_time(value, last: float | None) -> float | None:
    """The time stamped on a step's Estimates: None or a finite real number, not before
    last, the time stamped on the previous step (None: none was)."""
    time = None if value is None else finite("time", value)
    check_exact_time(value)
    check_forward(time, last)
    return time


def read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (a filter's state is shown, never lent out to write)."""
    v = a.view()
    v.flags.writeable = False
    return v


def step_estimates(name: str, steps: int, means: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Refuses a filter's step whose estimates, means (..., n) and covs (..., n, n), are not
    finite, or whose covariances an `Estimates` would refuse (`validation.check_spd`: not
    symmetric, not positive definite, or numerically singular), before the filter keeps its
    new state, which is then the one before the step: the step's report is then always an
    Estimates (fuzz K2: diag(1e-300, 1e300) passed numpy's Cholesky, the filter stepped,
    and only its report was refused). float64 cannot represent such a step: a measurement
    ``name`` far beyond the model's scale (a mixture's spread falls below the rounding of
    its means), or a model and prior at float64's limits. Returns the covs symmetrised, a
    new array (..., n, n), as an Estimates holds them (`report`)."""
    reason = "not finite"
    if np.isfinite(means).all() and np.isfinite(covs).all():
        try:
            flat = covs.reshape(-1, *covs.shape[-2:])
            return _fo.check_spd(flat, "covs", item="estimate").reshape(covs.shape)
        except FusionInputError as exc:
            reason = str(exc)
    raise FusionInputError(
        f"{name}: step {steps + 1}'s estimate cannot be represented in float64 ({reason}: a "
        "measurement far beyond the model's scale, or a model and prior at float64's "
        "limits); the filter's state is the one before this step")


def report(means: np.ndarray, covs: np.ndarray, ids, time, node) -> Estimates:
    """A step's Estimates, of new arrays nothing writes to again: means (m, n) and the covs
    (m, n, n) `step_estimates` returned, ids (m,) int64 and unique (None: 0, ..., m - 1),
    time from `step_time` and node from `node_name`: taken without the Estimates checks
    again (`Estimates._of`; the covariance check was a tenth of an RBMCDA step)."""
    ids = np.arange(len(means), dtype=np.int64) if ids is None else ids
    return Estimates._of(means, covs, ids, time, node)


def generator(name: str, value) -> np.random.Generator:
    if not isinstance(value, np.random.Generator):
        raise FusionInputError(
            f"{name} must be a numpy.random.Generator, got {type(value).__name__}")
    return value


def _symmetric(name: str, value, n: int) -> tuple[np.ndarray, float]:
    """A finite symmetric (n, n) matrix and its scale max |P|: the tolerances are relative
    to it, so that a covariance of 1e-20 is held to the standard of one of 1."""
    P = finite_array(name, value, shape=(n, n))
    scale = float(np.max(np.abs(P)))
    if not np.allclose(P, P.T, rtol=1e-9, atol=1e-12 * scale):
        raise FusionInputError(f"{name} must be symmetric")
    return P, scale


def covariance(name: str, value, n: int) -> np.ndarray:
    """Check a symmetric positive-definite (n, n) matrix (Cholesky must succeed)."""
    P, _ = _symmetric(name, value, n)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise FusionInputError(f"{name} must be positive definite") from None
    return P


def psd_covariance(name: str, value, n: int) -> np.ndarray:
    """Check a symmetric positive-semidefinite (n, n) matrix (a process noise may be singular)."""
    P, scale = _symmetric(name, value, n)
    if np.min(np.linalg.eigvalsh(_fo.symmetrised(P))) < -1e-10 * scale:
        raise FusionInputError(f"{name} must be positive semidefinite")
    return P


def scan(name: str, value, d: int) -> np.ndarray:
    """The measurements of one step as a finite (k, d) float array, k >= 0.

    An empty scan may be given as ``[]`` or any (0, d) array; a single measurement must
    still be a (1, d) row.
    """
    if value is None:
        raise FusionInputError(f"{name} must be an array-like (k, {d}) of measurements, "
                               "got None (an empty step is [] or a (0, d) array)")
    arr = finite_array(name, value)
    if arr.shape == (0,):
        arr = arr.reshape(0, d)
    if arr.ndim != 2 or arr.shape[1] != d:
        raise FusionInputError(f"{name} must have shape (k, {d}), got {arr.shape}")
    return arr


def scans(value, d: int) -> list[np.ndarray]:
    """Check a sequence of per-step measurement arrays, each (k_t, d) with k_t >= 0."""
    if value is None or isinstance(value, str | bytes | Mapping):
        raise FusionInputError(
            f"scans must be a sequence of (k_t, {d}) arrays, got {type(value).__name__}")
    if isinstance(value, np.ndarray) and value.ndim != 3:
        raise FusionInputError(
            f"scans must be a sequence of (k_t, {d}) arrays, got array {value.shape}")
    try:
        items = list(value)
    except TypeError:
        raise FusionInputError(
            f"scans must be a sequence of (k_t, {d}) arrays, got {type(value).__name__}"
        ) from None
    if not items:
        raise FusionInputError("scans must contain at least one step")
    return [scan(f"scans[{t}]", s, d) for t, s in enumerate(items)]
