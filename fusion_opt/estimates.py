"""`Estimates`: the one form in which estimates travel between the parts of a network.

A tracker's step, a processing node's step, a replay of recorded tracks and the Stone Soup
adapter all give the same thing: m estimates of an n-dimensional state, each a mean and a
covariance with an integer track id, stamped with the time of the step and the node that
made them.

    Estimates(means (m, n), covs (m, n, n), ids (m,) = arange(m), time=None, node=None)

It is validated on construction (FusionInputError naming the field and the estimate), its
arrays are read-only copies (covariances symmetrised), and m = 0 is allowed:
`Estimates.empty(n)`. Track ids are unique within one Estimates; whether an id persists
from one step to the next is the producer's promise (each tracker's docstring says).
"""

from __future__ import annotations

import decimal
import numbers
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np

from .limits import estimates_bytes, fits
from .results import FusionInputError, ReadOnly
from .validation import (
    check_spd,
    finite_array,
    finite_real,
    hashable,
    is_integer,
    real_array,
    safe_repr,
    short_repr,
)


@dataclass(frozen=True, eq=False)
class Estimates(ReadOnly):
    """m estimates: means (m, n), covs (m, n, n), ids (m,) int64, time (float or None),
    node (any hashable, or None). `len(e)` is m; `e.n` the state dimension."""

    means: np.ndarray
    covs: np.ndarray
    ids: np.ndarray | None = None
    time: float | None = None
    node: Hashable | None = None

    def __post_init__(self):
        if self.node is not None and not hashable(self.node):
            raise FusionInputError(f"node must be hashable (a name), got "
                                   f"{type(self.node).__name__}")
        try:
            object.__setattr__(self, "time", check_time(self.time))
            arrays = _arrays(self.means, self.covs, self.ids)
        except FusionInputError as exc:  # say whose estimates, when it is known
            where = " ".join(f"{k} {_shown(v)}" for k, v in (("of node", self.node),
                                                                 ("at time", self.time))
                             if v is not None)
            raise FusionInputError(f"Estimates {where}: {exc}" if where else str(exc)) from None
        for name, value in zip(("means", "covs", "ids"), arrays, strict=True):
            value = np.array(value, copy=True)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @classmethod
    def _of(cls, means, covs, ids, time, node) -> Estimates:
        """Estimates of new arrays the library made and checked, taken without the checks
        (40 of a processing node's 500 us step at 3 sources of 4 tracks): a processing
        node's fused estimates, finite, positive definite and exactly symmetric as the
        fusion makes them, or a source's as given, ids int64 and unique, time and node
        checked. The arrays are made read-only in place (nothing else writes to them)."""
        for a in (means, covs, ids):
            a.setflags(write=False)
        estimates = object.__new__(cls)
        estimates.__dict__.update(means=means, covs=covs, ids=ids, time=time, node=node)
        return estimates

    @classmethod
    def empty(cls, n: int, time: float | None = None, node: Hashable | None = None):
        """No estimate of an n-dimensional state (a step with nothing to report)."""
        if not is_integer(n) or n < 1:
            raise FusionInputError(f"n must be an integer >= 1, got {safe_repr(n)}")
        fits(f"n = {safe_repr(n)}", estimates_bytes(1, n))  # an estimate of a later step
        return cls(np.zeros((0, n)), np.zeros((0, n, n)), None, time, node)

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def n(self) -> int:
        """The state dimension."""
        return self.means.shape[1]

    def take(self, indices) -> Estimates:
        """The estimates at `indices`, same time and node: integer positions (not ids) in
        [-m, m), or a boolean mask (m,)."""
        idx = np.asarray(indices) if not isinstance(indices, str | bytes) else None
        m = len(self)
        if idx is not None and idx.dtype == bool and idx.shape == (m,):
            idx = np.flatnonzero(idx)
        elif idx is not None and idx.size == 0:
            idx = np.zeros(0, dtype=np.intp)
        if idx is None or idx.dtype.kind not in "iu" or idx.ndim > 1 \
                or (idx.size and not -m <= idx.min() <= idx.max() < m):
            raise FusionInputError(f"indices must be integer positions in [-{m}, {m}) or a "
                                   f"boolean mask ({m},), got {safe_repr(indices)}")
        idx = idx.reshape(-1)
        return Estimates(self.means[idx], self.covs[idx], self.ids[idx], self.time, self.node)

    def __repr__(self) -> str:
        return (f"Estimates(m={len(self)}, n={self.n}, ids={self.ids.tolist()}, "
                f"time={self.time}, node={safe_repr(self.node)})")


def _arrays(means, covs, ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """means (m, n), covs (m, n, n) symmetrised and ids (m,), checked by name."""
    means = finite_array(means, "means")
    if means.ndim != 2 or means.shape[1] == 0:
        hint = " (no estimate: Estimates.empty(n))" if means.size == 0 else ""
        raise FusionInputError(f"means must have shape (m, n) with n >= 1, got "
                               f"{means.shape}{hint}")
    m, n = means.shape
    fits(f"means: {m} estimates of dimension {n}", estimates_bytes(m, n))
    ids = track_ids(ids, m)
    covs = finite_array(covs, "covs")
    if covs.shape != (m, n, n):
        raise FusionInputError(f"covs must have shape {(m, n, n)} to match means, got "
                               f"{covs.shape}")
    return means, check_spd(covs, "covs", item="estimate", labels=ids), ids


def track_ids(ids, m: int, unique: bool = True) -> np.ndarray:
    """Integer track ids (m,) as int64, unique unless told; arange(m) when None. An integer
    or float array is read as it is (floats must be whole numbers); any other container
    (a list, an object array from a table, long doubles) id by id, each exactly, so that
    no id above 2^53 is rounded through a float on the way (fuzz K1: 2^62 + 1 became 2^62
    and could merge with another id)."""
    if ids is None:
        return np.arange(m, dtype=np.int64)
    if isinstance(ids, np.ma.MaskedArray):  # its hidden values would be read as ids
        raise FusionInputError("ids is a masked array: fill or drop its masked values first "
                               "(np.ma.filled, or select the rows to keep)")
    numeric = isinstance(ids, np.ndarray) and ids.dtype.kind in "iuf" and ids.dtype.itemsize <= 8
    if not numeric:  # strings, booleans, complex, ragged: refused by name
        if isinstance(ids, list | tuple) and all(type(v) is int for v in ids) and \
                _beyond_int64(ids) is not None:  # named exactly, before real_array's range
            raise _out_of_range(_beyond_int64(ids))
        shape = _decimal_shape(ids)
        try:
            shape = real_array(ids, "ids").shape if shape is None else shape
        except FusionInputError as exc:
            raise FusionInputError(f"ids must be integers (map other track names to "
                                   f"integers): {exc}") from None
    else:
        shape = ids.shape
    if shape != (m,):
        raise FusionInputError(f"ids must have shape ({m},), one per estimate, got {shape}")
    out = _numeric_ids(ids) if numeric else _exact_ids(ids)
    if unique and len(np.unique(out)) != m:
        raise FusionInputError(f"ids must be unique within one Estimates, got {out.tolist()}")
    return out


def _numeric_ids(a: np.ndarray) -> np.ndarray:
    """An integer or float array of ids (m,) as int64: whole numbers within int64 (floats
    compared as float64: float16's overflowed comparing with 2^63, fuzz L2)."""
    # every tracker's ids are int64 already: copied as int64 (a long long is one too),
    # without the range checks, which cost 4 of an Estimates' 22 us
    if a.dtype == np.int64:
        return a.astype(np.int64)
    if a.dtype.kind == "f":
        a = a.astype(np.float64)
        if not np.all(np.isfinite(a) & (a == np.round(a))):
            raise FusionInputError("ids must be integers")
    if a.size and not _fit_int64(a):
        raise _out_of_range(_beyond_int64(a.tolist()))
    return a.astype(np.int64)


def _decimal_shape(ids) -> tuple[int, ...] | None:
    """The shape of a flat list, tuple or object array of Decimals (ids read from a
    database's NUMERIC column), which `real_array` refuses as objects; else None. Their
    values are then read exactly, as a list of ints is (`_exact_ids`)."""
    if isinstance(ids, list | tuple) or (isinstance(ids, np.ndarray) and ids.dtype == object
                                          and ids.ndim == 1):
        if len(ids) and all(isinstance(v, decimal.Decimal) for v in ids):
            return (len(ids),)
    return None


def _exact_ids(ids) -> np.ndarray:
    """Ids (m,) of another container as int64, each converted by itself, exactly: a value
    that is not a whole number, or not within int64, is refused by name."""
    values = np.asarray(ids, dtype=object).reshape(-1)
    out = np.empty(values.size, dtype=np.int64)
    for k, v in enumerate(values.tolist()):
        if isinstance(v, decimal.Decimal) and v.is_finite() and v.adjusted() >= 19:
            raise _out_of_range(v)  # past int64 by its exponent: int() of 1E+1000000 took
        try:  # 75 s (fuzz O4)
            i = int(v)
            whole = i == v
        except (TypeError, ValueError, OverflowError):  # nan, inf
            whole = False
        if not whole:
            raise FusionInputError(f"ids must be integers, got {_shown(v)} at index {k}")
        if not -(2**63) <= i < 2**63:
            raise _out_of_range(v)
        out[k] = i
    return out


def _fit_int64(a: np.ndarray) -> bool:
    """Whether every value of a (integers, or floats that are whole numbers) is an int64."""
    if a.dtype.kind == "f":  # 2^63 is a float; the int64 maximum, 2^63 - 1, is not
        return bool(a.max() < 2.0**63 and a.min() >= -(2.0**63))
    info = np.iinfo(np.int64)
    return bool(a.max() <= info.max and a.min() >= info.min)


def _beyond_int64(values):
    """The first of values (Python numbers) outside int64, or None."""
    return next((v for v in values if not -(2**63) <= v < 2**63), None)


def _out_of_range(value) -> FusionInputError:
    """The refusal of an id outside int64."""
    return FusionInputError(f"ids must fit in a signed 64-bit integer (-2^63 to 2^63 - 1), "
                            f"got {_shown(value)}")


def _shown(value) -> str:
    """A number as a message shows it: numpy's scalars as their value, not np.float64(...),
    but a datetime64 or timedelta64 as itself (the item of a unitless np.timedelta64(5) is
    the int 5, and "must be a finite real number, got 5" named a valid time: fuzz5 1),
    and an int of 400 digits shortened (`short_repr`)."""
    if isinstance(value, decimal.Decimal) and value.is_finite() and value.adjusted() < 30 \
            and value == value.to_integral():
        value = int(value)  # a whole Decimal of a few digits by them, as an int is shown
    return short_repr(value.item() if isinstance(value, np.generic) and value.dtype.kind
                      not in "mM" and value.dtype.itemsize <= 8 else value)


def check_forward(time: float | None, last: float | None, name: str = "time") -> None:
    """Refuse a step stamped before the previous one (times as floats, None: not stamped):
    the trackers predict forward and the processing nodes continue tracks forward, so data
    out of time order would be fused as if in order (fuzz I10)."""
    if time is not None and last is not None and time < last:
        raise FusionInputError(f"{name} = {safe_repr(time)} is before the previous step's, "
                               f"{safe_repr(last)}: "
                               "steps go forward in time (data out of order is not "
                               "supported)")


def check_time(time) -> float | None:
    """A time stamp: None or a finite real number, as a float (`check_exact_time`)."""
    if time is None:
        return None
    value = finite_real(time)
    if value is None:
        raise FusionInputError(f"time must be a finite real number or None, got "
                               f"{_shown(time)}")
    check_exact_time(time)
    return value


_EXACT = 2**53  # float64 holds every integer up to here


def _inexact_whole(time) -> bool:
    """A whole number beyond 2^53 of another type than an integer or a float64 (a Fraction,
    a long double) that float64 does not hold (fuzz L1: Fraction(2^53 + 1) was rounded)."""
    if isinstance(time, float | numbers.Integral):
        return False
    try:
        whole = int(time)
        return whole == time and abs(whole) > _EXACT and float(time) != time
    except (TypeError, ValueError, OverflowError):
        return False


def check_exact_time(time) -> None:
    """Refuses an integer time beyond 2^53, which float64 does not hold exactly (nanoseconds
    since 1970 lose up to 128 ns: two stamps merged, and a step back went unseen, fuzz
    K6); refused whether or not this one rounds, so that a stream of them is refused at
    its first."""
    if isinstance(time, np.ndarray) and time.ndim == 0:  # a tracker's step takes a 0-d array
        time = time.item()                               # (fuzz4: array(2^53 + 1) was rounded)
    if isinstance(time, numbers.Integral) and not -_EXACT <= int(time) <= _EXACT \
            or _inexact_whole(time):
        raise FusionInputError(
            f"time {short_repr(int(time))} is an integer beyond 2^53, where float64 (the type "
            "of a time stamp) does not hold every integer: give times as seconds, e.g. "
            "nanoseconds / 1e9, or counted from an epoch near them")
