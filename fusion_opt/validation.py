"""Input checks shared by every entry point.

Each check raises `FusionInputError` naming the argument, the node (and, in a batch, the
problem) index and what is wrong, so a bad input never reaches a solver or turns into NaN.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Set

import numpy as np

from .linalg import cholesky, jit
from .prepare import MAX_CONDITION, SYMMETRY_RTOL, asymmetric
from .results import FusionInputError

CRITERIA = ("trace", "logdet")


def _where(index: tuple[int, ...], item: str = "node", labels=None) -> str:
    """'node 3' or 'problem 2, node 3' for a multi-index (batch..., node); 'estimate 3
    (id 17)' with labels."""
    if len(index) == 1:
        label = "" if labels is None else f" (id {labels[index[0]]})"
        return f"{item} {index[0]}{label}"
    return f"problem {index[:-1] if len(index) > 2 else index[0]}, {item} {index[-1]}"


def is_real(x) -> bool:
    """Whether x is a real number as a scalar option takes one: a numbers.Real (a Python or
    numpy int or float, a Fraction, ...) but not a bool, nor a np.timedelta64, which numpy
    registers as an integer: a duration read as a count (np.timedelta64(5) as 5 particles),
    and one with a unit made float() and int() raise TypeError in place of the refusal
    (fuzz U3)."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool | np.timedelta64)


def is_integer(x) -> bool:
    """Whether x is an integer as a count or an index takes one: a numbers.Integral but not
    a bool or a np.timedelta64 (`is_real`)."""
    return isinstance(x, numbers.Integral) and not isinstance(x, bool | np.timedelta64)


def is_sequence(x) -> bool:
    """Whether x can be a sequence of items (names, components, ids, targets): iterable, and
    not a string, bytes, a mapping (whose keys would be the items), a set (whose order,
    which numbers the items, changes between processes with the hash seed: fuzz U11) or a
    0-d array, which has __iter__ but raises TypeError when iterated (fuzz U5, U6)."""
    return hasattr(x, "__iter__") and not isinstance(x, str | bytes | Mapping | Set) \
        and not (isinstance(x, np.ndarray) and x.ndim == 0)


def scalar(x):
    """x, or the numpy scalar of a 0-d array of integers or floats: a scalar option takes
    one as the number it holds (fuzz8: a processing node's p_detect refused np.array(0.7),
    which fo.mbci's p_detect and the trackers' options take)."""
    if isinstance(x, np.ndarray) and x.ndim == 0 and x.dtype.kind in "iuf":
        return x[()]
    return x


def finite_real(x) -> float | None:
    """x as a float when it is a real number (`is_real`, after `scalar`) whose float is
    finite, else None: a numpy scalar, a 0-d array of integers or floats, a Fraction or a
    Python int of any size is a real number, and one whose float overflows (10**400) is
    refused, not crashed on."""
    x = scalar(x)
    if not is_real(x):
        return None
    try:
        f = float(x)
    except (OverflowError, ValueError, TypeError):
        return None
    return f if math.isfinite(f) else None


def hashable(value) -> bool:
    """Whether value can name something (a dict key): hash() succeeds. isinstance(value,
    Hashable) is True for a tuple holding a list, which then fails as a key; a generic
    np.timedelta64 raises ValueError (fuzz4), and any error of hash() means no name."""
    try:
        hash(value)
    except Exception:  # noqa: BLE001 (whatever hash() raises, the value cannot be a key)
        return False
    return True


def check_criterion(criterion) -> str:
    if criterion not in CRITERIA:
        raise FusionInputError(f"criterion must be one of {CRITERIA}, got {safe_repr(criterion)}")
    return criterion


def check_estimates(means, covs, batch: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Validate node estimates and return them as float arrays, covariances symmetrised.

    means (N, n) and covs (N, n, n); with batch=True, (B, N, n) and (B, N, n, n).
    """
    lead = 2 if batch else 1
    means = finite_array(means, "means")
    covs = finite_array(covs, "covs")
    if means.ndim != lead + 1:
        raise FusionInputError(
            f"means must have shape {'(B, N, n)' if batch else '(N, n)'}, got {means.shape}")
    if covs.ndim != lead + 2 or covs.shape[-1] != covs.shape[-2]:
        raise FusionInputError(
            f"covs must have shape {'(B, N, n, n)' if batch else '(N, n, n)'}, got {covs.shape}")
    if covs.shape[:-1] != means.shape:
        raise FusionInputError(
            f"covs shape {covs.shape} does not match means shape {means.shape}")
    if means.shape[-2] == 0:
        raise FusionInputError("means and covs hold no nodes (N = 0)")
    if means.shape[-1] == 0:
        raise FusionInputError("the state dimension n is 0")
    if batch and means.shape[0] == 0:
        raise FusionInputError("the batch holds no problems (B = 0)")
    return means, check_spd(covs)


def real_array(x, name: str) -> np.ndarray:
    """x as a float array, refusing what is not an array of real numbers: strings (also
    numeric ones), mappings, ragged nesting, booleans, complex and object values, each with
    a message naming the argument (a complex input is never silently truncated)."""
    if type(x) is np.ndarray and x.dtype == np.float64:  # the common case, at no cost
        return x
    if type(x) is float:  # a scalar option (chi, growth, a threshold): 1.9 -> 0.2 us
        return np.array(x)
    if isinstance(x, str | bytes) or isinstance(x, Mapping):
        raise FusionInputError(f"{name} must be an array of real numbers, got "
                               f"{type(x).__name__}")
    if isinstance(x, list | tuple) and _contains_bool(x):  # numpy would read True as 1.0
        raise FusionInputError(f"{name} must be an array of real numbers, got a boolean in it")
    if isinstance(x, np.ma.MaskedArray):  # asarray would drop the mask, using hidden values
        raise FusionInputError(f"{name} is a masked array: fill or drop its masked values "
                               "first (np.ma.filled, or select the rows to keep)")
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise FusionInputError(f"{name} must be an array of real numbers ({exc})") from None
    if a.dtype.kind == "O" and a.size and all(map(is_real, a.flat)):
        return _reals(a, name)  # Fraction, int beyond int64: numbers numpy keeps as objects
    if a.dtype.kind == "O" and a.size == 0:  # an empty object array (a table's empty
        return a.astype(float)  # column) holds no wrong value (fuzz L3)
    if a.dtype.kind not in "iuf":
        kind = {"b": "booleans", "c": "complex numbers", "U": "strings", "S": "bytes",
                "O": "objects (ragged or not numbers)"}.get(a.dtype.kind, str(a.dtype))
        raise FusionInputError(f"{name} must be an array of real numbers, got {kind}")
    with np.errstate(over="ignore", under="ignore"):
        out = a.astype(float, copy=False)
    if a.dtype.itemsize > 8 and a.dtype.kind == "f":  # long double: beyond float64?
        lost = (np.isinf(out) & np.isfinite(a)) | ((out == 0) & (a != 0))
        if lost.any():
            idx = tuple(int(i) for i in np.argwhere(lost)[0])
            raise FusionInputError(f"{name} has a value beyond float64's range, {a[idx]!s} "
                                   f"at index {idx}")
    return out


def _reals(a: np.ndarray, name: str) -> np.ndarray:
    """An object array of real numbers (numbers.Real, fuzz I7) as floats, each rounded once
    by its own float(); one beyond float64's range is refused, naming its index."""
    out = np.empty(a.shape)
    for idx in np.ndindex(a.shape):
        try:
            out[idx] = float(a[idx])
        except OverflowError:
            raise FusionInputError(f"{name} has a value beyond float64's range, "
                                   f"{short_repr(a[idx])}"
                                   f"{f' at index {idx}' if idx else ''}") from None
    return out


def wide_float(x) -> float:
    """A real number (an int or a Fraction of any size) as a float, +-inf past float64's
    range, where float() raises OverflowError (an int of 5,001 digits as a count or a
    cut-off: fuzz T3, T4); the callers refuse it by range."""
    try:
        return float(x)
    except OverflowError:
        return float("inf") if x > 0 else float("-inf")


def safe_repr(value) -> str:
    """What a refusal shows of a value the caller gave: its repr, an int of hundreds of
    digits shortened (`short_repr`), and never an error of its own: the repr of an int
    past Python's 4,300 digits raises ValueError, also inside a list or a tuple, and
    options such as a criterion or a threshold of 10**5000 crashed with that ValueError
    in place of their refusal (fuzz T4)."""
    if isinstance(value, int):
        return short_repr(value)
    try:
        return repr(value)
    except Exception as exc:  # noqa: BLE001 (a refusal must not fail on what it shows)
        return _unshowable(value, exc)


def _unshowable(value, exc: Exception) -> str:
    """How a refusal names a value whose repr raised exc."""
    if isinstance(exc, ValueError) and "4300" in str(exc):
        return f"a {type(value).__name__} holding an integer of more than 4,300 digits"
    return f"a {type(value).__name__} whose repr fails ({type(exc).__name__})"


def short_repr(value) -> str:
    """repr(value); of an int longer than 24 characters its first 8 and its length (an int
    of 400 digits, named in a one-line refusal); an int past Python's 4,300 digits of repr
    by its size alone (its repr raised ValueError inside the refusal: fuzz O3); any other
    value's repr whole up to 200 characters (a datetime's 38 were shown as "datetime...
    (38 digits)": fuzz of 2026-11-29, F4), else its first 100 and its length."""
    if isinstance(value, int) and value.bit_length() > 14_000:
        return f"an integer of about {int(value.bit_length() * 0.30103) + 1} digits"
    try:
        text = repr(value)
    except Exception as exc:  # noqa: BLE001 (an int past 4,300 digits inside it, ...)
        return _unshowable(value, exc)
    if isinstance(value, int):
        return text if len(text) <= 24 else f"{text[:8]}... ({len(text)} digits)"
    return text if len(text) <= 200 else f"{text[:100]}... ({len(text)} characters)"


def _contains_bool(value) -> bool:
    """Whether a (nested) list or tuple holds a boolean, which numpy would turn into 0 or 1
    beside numbers. A stack of its own, not recursion: a list nested 3,000 deep raised
    RecursionError (fuzz K16)."""
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, bool | np.bool_) or (isinstance(v, np.ndarray) and v.dtype == bool):
            return True
        if isinstance(v, list | tuple):
            stack.extend(x for x in v if type(x) not in _PLAIN)  # a float or int: nothing
    return False


_PLAIN = (float, int)  # exactly these types: bool is an int subclass, np.float64 a float one


def kernel_array(a: np.ndarray) -> np.ndarray:
    """a C-contiguous and writable: numba compiles a kernel once per array type, and a
    read-only array (an Estimates' means, say) is another type, which would cost the whole
    compiled path again (15 s) for the same arithmetic. The kernels never write to it."""
    a = np.ascontiguousarray(a)
    return a if a.flags.writeable else a.copy()


def finite_array(x, name: str) -> np.ndarray:
    """real_array(x, name) whose every value is finite."""
    a = real_array(x, name)
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise FusionInputError(f"{name} has a non-finite value {a[idx]} at index {idx}")
    return a


def check_spd(covs: np.ndarray, name: str = "covs", item: str = "node",
              labels=None) -> np.ndarray:
    """Symmetric within SYMMETRY_RTOL of its largest entry, and positive definite; returns
    the symmetrised stack (..., n, n) (`symmetrised`). Messages name `name` and the `item`
    index, and its label (e.g. a track id) from labels (m,) for a stack (m, n, n).

    One compiled call (`_spd`) checks and symmetrises: through numpy's calls on small
    arrays it took 28 us for two 4 x 4 covariances, more than a fusion of them."""
    if covs.size == 0:
        return covs
    n = covs.shape[-1]
    flat = np.array(covs, dtype=np.float64, order="C").reshape(-1, n, n)  # one array type
    sym = np.empty_like(flat)
    code, k = _spd(flat, sym, np.empty((n, n)), np.empty((n, n)))
    if code:
        idx = tuple(int(i) for i in np.unravel_index(k, covs.shape[:-2]))
        where = _where(idx, item, labels)
    if code == _ASYMMETRIC:
        P = flat[k]
        raise FusionInputError(
            f"{name} of {where} is not symmetric: max |P - P^T| = "
            f"{np.abs(P - P.T).max():.3g} exceeds {SYMMETRY_RTOL:g} x max |P| = "
            f"{np.abs(P).max():.3g}")
    if code == _NOT_PD:
        raise definiteness_error(f"{name} of {where}", sym[k])
    return sym.reshape(covs.shape)


def definiteness_error(label: str, S: np.ndarray) -> FusionInputError:
    """Why the symmetric S (n, n), which failed a Cholesky factorisation or the condition
    limit, is refused, from its eigenvalues, computed on S scaled by the power of two of
    its largest entry (exact: entries near 1e308 or subnormal stay in range): not positive
    definite where the smallest is negative beyond n eps of the largest; numerically
    singular where it is 0 or negative within that (eigenvalues 1e-300 and 1e300, the
    smallest computed as 0, were reported as "not positive definite", fuzz I6), or
    positive with the condition estimate of `prepare._factor`, |P|_F tr(P^-1), near or
    above MAX_CONDITION (said with its value: the message named |P|_F |P^-1|_F, up to
    sqrt(n) times smaller, and a covariance at 5e13 by that measure was refused "above
    7.04e13", soak 1), or else a failed Cholesky factorisation."""
    e = int(np.frexp(np.abs(S).max())[1])
    with np.errstate(all="ignore"):
        unit = np.linalg.eigvalsh(np.ldexp(S, -e))
        eig = np.ldexp(unit, e)
    lo, hi, tol = eig[0], eig[-1], len(eig) * np.finfo(float).eps * eig[-1]
    if not hi > 0.0 or lo < -tol:
        return FusionInputError(f"{label} is not positive definite (smallest eigenvalue "
                                f"{lo:.3g})")
    if lo <= 0.0:  # else every eigenvalue, scaled or not, is positive
        return FusionInputError(f"{label} is numerically singular: its smallest eigenvalue, "
                                f"{lo:.3g}, is within float64's rounding of 0 beside its "
                                f"largest, {hi:.3g}")
    # the estimate is scale-free: from the scaled eigenvalues, which do not overflow
    with np.errstate(over="ignore"):  # 1 / a subnormal eigenvalue
        estimate = float(np.sqrt(np.sum(unit * unit)) * np.sum(1.0 / unit))
    if estimate > 0.9 * MAX_CONDITION:  # its rounding here, n eps cond, is a few % there
        shown = f"{estimate:.3g}" if estimate < np.inf else "beyond float64's range"
        why = (f"its condition estimate |P|_F tr(P^-1), {shown}, is "
               f"{'above' if estimate > MAX_CONDITION else 'at'} the limit "
               f"{MAX_CONDITION:.3g}, beyond which a singular covariance passes a Cholesky "
               "factorisation with pivots of rounding size")
    else:
        why = "its Cholesky factorisation fails (pivots of rounding size)"
    return FusionInputError(f"{label} is numerically singular: eigenvalues {lo:.3g} to "
                            f"{hi:.3g} (condition {hi / lo:.3g}); {why}")


_ASYMMETRIC, _NOT_PD = 1, 2


@jit
def _spd(P, S, C, L):
    """(code, k) for finite P (m, n, n): _ASYMMETRIC or _NOT_PD and the first matrix k
    that is not symmetric within SYMMETRY_RTOL of its largest entry, or whose symmetrised
    S[k] fails a Cholesky factorisation, else (0, -1); S gets the symmetrised stack as
    `symmetrised` makes it. The factorisation runs on S[k] scaled by the power of two that
    brings its largest entry into [1, 2) (exact; C, L (n, n) scratch), so entries near
    1e308 or subnormal are tested in float64's normal range."""
    m, n = P.shape[0], P.shape[1]
    for k in range(m):
        if asymmetric(P[k]):
            return _ASYMMETRIC, k
    finite = True
    for k in range(m):
        for j in range(n):
            for i in range(n):
                S[k, j, i] = 0.5 * (P[k, j, i] + P[k, i, j])
                finite = finite and np.isfinite(S[k, j, i])
    if not finite:  # a sum overflowed: every entry halved before the sum, as numpy did
        for k in range(m):
            for j in range(n):
                for i in range(n):
                    S[k, j, i] = 0.5 * P[k, j, i] + 0.5 * P[k, i, j]
    for k in range(m):
        top = 0.0
        for j in range(n):
            for i in range(n):
                top = max(top, abs(S[k, j, i]))
        shift = -math.frexp(top)[1] + 1  # top * 2^shift in [1, 2)
        for j in range(n):
            for i in range(n):
                C[j, i] = math.ldexp(S[k, j, i], shift)
        if not cholesky(C, L):
            return _NOT_PD, k
    return 0, -1


def symmetrised(covs: np.ndarray) -> np.ndarray:
    """(P + P^T) / 2 for finite P (..., n, n), exactly symmetric; halved before the sum
    where the sum overflows (entries near 1.8e308), after it elsewhere, where halving first
    would round away a subnormal's last bit."""
    with np.errstate(over="ignore"):
        sym = 0.5 * (covs + np.swapaxes(covs, -1, -2))
    if not np.isfinite(sym).all():
        sym = 0.5 * covs + 0.5 * np.swapaxes(covs, -1, -2)
    return sym


def cholesky_ok(covs: np.ndarray) -> np.ndarray:
    """Boolean mask over the leading axes: True where the Cholesky factorisation succeeds."""
    flat = covs.reshape(-1, *covs.shape[-2:])
    try:
        np.linalg.cholesky(flat)
        return np.ones(covs.shape[:-2], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    ok = np.empty(len(flat), dtype=bool)
    for k, c in enumerate(flat):  # only on failure, to find which matrix
        try:
            np.linalg.cholesky(c)
            ok[k] = True
        except np.linalg.LinAlgError:
            ok[k] = False
    return ok.reshape(covs.shape[:-2])


def per_node(value, n_nodes: int, name: str) -> np.ndarray:
    """A scalar, one value per node (N,), or per problem and node (..., N), as a finite
    float array with last axis N."""
    a = finite_array(value, name)
    if a.ndim == 0:
        return np.full(n_nodes, float(a))
    if a.shape[-1] != n_nodes:
        raise FusionInputError(
            f"{name} must be a scalar or have one value per node ({n_nodes},), got {a.shape}")
    return a


def check_detection(p_detect, chi, n_nodes: int, chi_name: str = "chi"):
    """p_detect in [0, 1] and chi in (0, 1], each a scalar, (N,) or (..., N); returned
    broadcast to one shape. chi_name names chi in messages ("growth" when the user gave
    the growth factor, whose inverse chi is)."""
    p = per_node(p_detect, n_nodes, "p_detect")
    c = per_node(chi, n_nodes, chi_name)
    try:
        p, c = np.broadcast_arrays(p, c)
    except ValueError:
        raise FusionInputError(
            f"p_detect {p.shape} and {chi_name} {c.shape} do not broadcast together") from None
    checks = (("p_detect", p, (p < 0) | (p > 1), "must lie in [0, 1]"),
              (chi_name, c, (c <= 0) | (c > 1),
               "must lie in (0, 1]" if chi_name == "chi" else "must be >= 1"))
    for name, a, bad, rule in checks:
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            value = a[idx] if name != "growth" else 1.0 / a[idx]
            raise FusionInputError(f"{name} of {_where(idx)} {rule}, got {value}")
    return p, c
