"""Compiled dense linear algebra for the matrices of a fusion problem.

numba-compiled and cached on disk (compiled once per machine). The routines write into
arrays their caller owns, so a solver allocates its work arrays once per problem, not once
per step: at n = 4 an allocation or a LAPACK call from compiled code costs more than the
arithmetic it serves (a 12 x 4 QR took 1.3 µs through LAPACK). Up to `SMALL` rows and
columns the products, the QR and the Cholesky factor are loops written here; above it
the products call BLAS, and `eigh`, `qr`, `qr_thin` and `cholesky` LAPACK (through
numba's own wrappers by symbol name, which cost a first compile about 1.5 s more; a
pair at n = 800 2.1-2.6 -> 0.9-1.1 s).

    cholesky(A, L)            A = L L^T, L lower; False if A is not positive definite
    lower_inverse(L, X)       X = L^-1, L lower triangular; upper_inverse(R, X) likewise
    householder(At, n, rows, Vt, R)  QR of A given as At = A^T (columns contiguous):
                              reflectors in Vt, R upper (R_kk of either sign)
    qr(At, n, rows, Vt, R)    householder's outputs, by LAPACK above SMALL columns
    apply_qt(Vt, n, rows, b)  b[:rows] <- Q^T b[:rows]
    thin_qt(Vt, n, rows, Qt)  Qt = the first n columns of Q, transposed
    qr_thin(At, n, rows, Vt, R)  R, and Q^T into At (householder, thin_qt; or LAPACK)
    eigh(S, lam, V)           S = V diag(lam) V^T, lam ascending (Jacobi when small)
    matmul(A, B, C), gram(B, G)   C = A B, G = B^T B (small_mul, small_gram: their loops)

Stale caches. numba keys each cached function by the source of its own file only, but a
cached caller embeds the compiled code of the kernels it calls from other files: after an
edit of `backends/newton.py` alone, `exact.fuse_exact` would keep loading the old solver.
So `jit` (and `inline`) is defined here, in the module every kernel module imports
first, after `drop_stale_caches` has compared one hash of the sources of every module of
the package that defines kernels (its files containing "@jit" or "@inline") with a stamp
kept beside the caches, and dropped every cached kernel (*.nbi, *.nbc) of the package
when they differ (1.3 ms added to an import of 0.5 s; see the function).

Compile time. At least half of a first fusion on a new machine is LLVM optimising and
emitting the exact path (numba finalizes each kernel's module with every kernel it calls
linked in; under cProfile 35 of 71 s, the profiler inflating the rest, numba's own typing
and lowering), and its level 3 passes cost more than they give here: `jit` compiles at
level 2 (`_at_level_2`) unless the user set NUMBA_OPT. Measured on a 2-core AMD EPYC,
empty cache: `fo.warmup` of both criteria 57.0 -> 43.2 s, `python -m studies run paper
--quick` 58.5 -> 48.2 s with bit-identical tables, and `fuse_exact` as fast (level 3 /
level 2, median of 32 problems, run in turn twice; a third run was noisy for both, 235 /
214 us at (6, 64)): (6, 64) "trace" 206.1 / 206.7-207.3 us, (2, 3) 8.2 / 8.2-8.4, (4, 16)
"logdet" 31.8-32.1 / 31.9-32.2; level 1 compiled in 39.1 s but ran 3-5 % slower. The first
compile of a kernel in a process logs COMPILE_NOTICE (`NOTICE`), so that a first fusion
is not a silent minute.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import stat
import uuid

import numpy as np
from numba import njit
from numba.core import config as _numba_config
from numba.core import event as _numba_event
from numba.core import types as _numba_types
from numba.core.compiler_lock import global_compiler_lock
from numba.np.linalg import ensure_lapack

SMALL = 16
BY_ROWS = 8  # the triangular inverses go by rows of X above this order
_JACOBI_SWEEPS = 60
_EPS = np.finfo(np.float64).eps
_STAMP = "fusion_opt-kernels.stamp"

# LAPACK through numba's own wrappers, by symbol name (so a kernel that calls them is
# cached like any other): the blocked QR dgeqrf, its Q dorgqr (both size their work array
# themselves; (kind, m, n, [k,] a, lda, tau) -> 0) and the Cholesky factor dpotrf ((kind,
# uplo, n, a, lda) -> info, > 0 where a pivot is not positive).
ensure_lapack()
_DOUBLE, _UPPER = ord("d"), ord("U")
_F64P = _numba_types.CPointer(_numba_types.float64)
_CHAR, _INTP, _INT = _numba_types.char, _numba_types.intp, _numba_types.intc
_GEQRF = _numba_types.ExternalFunction(
    "numba_ez_geqrf", _INT(_CHAR, _INTP, _INTP, _F64P, _INTP, _F64P))
_ORGQR = _numba_types.ExternalFunction(
    "numba_ez_xxgqr", _INT(_CHAR, _INTP, _INTP, _INTP, _F64P, _INTP, _F64P))
_POTRF = _numba_types.ExternalFunction("numba_xxpotrf", _INT(_CHAR, _CHAR, _INTP, _F64P, _INTP))


def drop_stale_caches(root: str, *linked: str) -> list[str]:
    """Drop numba's cached kernels of the package at `root` where its kernel sources, or
    those of the packages at `linked` whose kernels its kernels call (`trackers` calls
    this package's), changed; returns the cache folders emptied (root's only).

    The hash covers every .py file under root and each linked root that contains "@jit"
    or "@inline" (path and bytes; sha256). Each source folder's kernels are cached where
    numba's own locators put them (asked in numba's order, so the same folder numba
    uses): in-tree `__pycache__` when it is writable, else the user-wide cache
    (~/.cache/numba/<folder>_<hash of its path>), or NUMBA_CACHE_DIR when set. The stamp
    lives in that same folder, so a read-only install is covered too: its caches live in
    the user-wide folder, and since numba stamps a file by the hash of its content, a pip
    upgrade that changes `newton.py` but not `exact.py` would otherwise leave `fuse_exact`
    stale there. Nothing here may fail an import: a folder that cannot be read or written
    is skipped (numba does not use it either). Processes starting at once may both drop
    the caches (one recompiles for nothing); numba writes its files by os.replace and
    treats a vanished one as a miss, and the stamp is written the same way, so none can
    read a half-written file. Not covered: a process still running code imported before
    the edit, which may cache a kernel compiled from the old sources under the new stamp."""
    digest = hashlib.sha256()
    folders = _kernel_sources(root, digest)
    for other in linked:
        digest.update(b"\1")  # root's files and each linked package's apart
        _kernel_sources(other, digest)
    stamp = digest.hexdigest()
    dropped = []
    for cache in dict.fromkeys(map(_cache_folder, folders.values())):
        if cache is not None and _refresh(cache, stamp):
            dropped.append(cache)
    return dropped


def _kernel_sources(root: str, digest) -> dict[str, str]:
    """Hashes into digest the path (from root) and bytes of every .py file under root
    containing "@jit" or "@inline"; returns {folder: one such file} of their folders."""
    folders = {}
    for folder, subdirs, files in os.walk(root):
        subdirs[:] = sorted(d for d in subdirs if d != "__pycache__")
        for name in sorted(files):
            if not name.endswith(".py"):
                continue
            path = os.path.join(folder, name)
            try:
                with open(path, "rb") as f:
                    data = f.read()
            except OSError:
                continue
            if b"@jit" in data or b"@inline" in data:
                digest.update(os.path.relpath(path, root).encode() + b"\0")
                digest.update(hashlib.sha256(data).digest())
                folders.setdefault(folder, path)
    return folders


def _cache_folder(py_file: str) -> str | None:
    """The folder numba caches the kernels of py_file in (its locators, in its order; the
    in-tree __pycache__ should a numba release move that list)."""
    try:
        from numba.core.caching import CacheImpl

        locators = list(CacheImpl._locator_classes)
    except (ImportError, AttributeError):
        return os.path.join(os.path.dirname(py_file), "__pycache__")
    for locator in locators:
        try:
            found = locator.from_function(_cache_folder, py_file)
        except Exception:  # a locator numba could not use either
            continue
        if found is not None:
            return found.get_cache_path()
    return None


def _refresh(cache: str, stamp: str) -> bool:
    """Empty the numba files of `cache` unless its stamp is `stamp`; True if emptied. A
    stamp that cannot be written is said on the "fusion_opt" logger (the caches are then
    dropped at every start)."""
    path = os.path.join(cache, _STAMP)
    if _read_stamp(path) == stamp:
        return False
    try:
        names = os.listdir(cache)
    except OSError:
        return False
    for name in names:
        if name.endswith((".nbi", ".nbc")):
            try:
                os.remove(os.path.join(cache, name))
            except OSError:
                pass  # gone already (another process), or not ours to remove
    tmp = f"{path}.{uuid.uuid4().hex[:16]}.tmp"
    try:
        with open(tmp, "w") as f:
            f.write(stamp)
        os.replace(tmp, path)
    except OSError as exc:
        logging.getLogger("fusion_opt").warning(
            "fusion_opt: cannot write the stamp of the kernel cache, %s (%s): its cached "
            "kernels are dropped and compiled again at every start until it can be", path,
            exc.strerror or exc)
        try:
            os.remove(tmp)
        except OSError:
            pass
    return True


def _read_stamp(path: str) -> str | None:
    """The stamp at path, or None: only a regular file is read, and only as much as a stamp
    holds, as bytes (fuzz9: a FIFO there blocked the import, a link to /dev/zero filled
    the memory, bytes that are not UTF-8 raised UnicodeDecodeError)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        with open(path, "rb") as f:
            return f.read(2 * hashlib.sha256().digest_size + 1).decode("ascii", "replace")
    except OSError:
        return None


def _at_level_2(decorator, uncached):
    """`decorator` (an njit with cache=True; `uncached`, the same without, where numba has
    no folder to cache in) whose kernels compile with LLVM's level 2 passes (module
    docstring). numba reads the level, `numba.core.config.OPT`, each time it builds a
    pass manager, so it is set for the duration of a kernel's compile only, under numba's
    own (reentrant) compiler lock, which every compile holds: no other compile in the
    process sees it. The kernels a compile calls compile inside it, at the same level.
    A level the user chose (NUMBA_OPT set) is kept. A kernel is compiled for the plain
    types of its arguments: numba would compile another copy of it (and of the kernels it
    calls) for each constant a caller passes (`evaluate_at(..., True)`, `householder(...,
    0)`), which LLVM's inlining specialises anyway (186 -> 155 compiled signatures on the
    exact path, `fo.warmup` of both criteria 45.0 -> 42.9 s, the mean of three runs each,
    run times equal)."""

    def decorate(fn):
        try:
            kernel = decorator(fn)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            if "locator" not in str(exc):
                raise
            kernel = _uncached(uncached, fn, exc)
        _guard_cache(kernel)
        compile_ = kernel.compile

        def compile(sig):
            if isinstance(sig, tuple):  # argument types of a call from a kernel
                sig = tuple(_numba_types.unliteral(t) for t in sig)
            with global_compiler_lock, _llvm_level(2):
                return compile_(sig)

        kernel.compile = compile
        return kernel

    return decorate


def _uncached(uncached, fn, exc):
    """`fn` compiled without a disk cache where numba has no folder to cache it in (fuzz9: a
    read-only install, HOME not writable, NUMBA_CACHE_DIR unset: the import raised numba's
    RuntimeError); said once on the "fusion_opt" logger."""
    if not _UNCACHED:
        _UNCACHED.append(fn)
        logging.getLogger("fusion_opt").warning(
            "fusion_opt: numba cannot cache the kernels (%s): each process compiles them "
            "again; set NUMBA_CACHE_DIR to a writable folder", exc)
    return uncached(fn)


_UNCACHED: list = []


def _guard_cache(kernel) -> None:
    """A damaged, unreadable or unwritable entry of numba's disk cache is a miss: the kernel
    compiles again, and numba writes its entry afresh where it can (fuzz9: a truncated or
    altered index or code file, or an unreadable one, made every fusion raise numba's
    EOFError, UnpicklingError, PermissionError or LLVM parsing error, in every process);
    so is an entry compiled from another function (code files swapped between kernels of
    one signature were run as the kernel's). A damaged index is removed so that the new
    entry can be written. numba checks no entry's content: a bit flipped inside compiled
    code that still loads is run (README)."""
    cache = getattr(kernel, "_cache", None)
    if cache is None or not hasattr(cache, "load_overload"):
        return
    load, save = cache.load_overload, cache.save_overload
    name = (kernel.py_func.__qualname__, kernel.py_func.__module__)

    def load_overload(sig, target_context):
        try:
            data = load(sig, target_context)
            fn = getattr(data, "fndesc", None)
            if fn is None or (fn.qualname, fn.modname) == name:
                return data
        except Exception:  # noqa: BLE001, S110 (any failure to read an entry is a miss)
            pass
        index = getattr(getattr(cache, "_cache_file", None), "_index_path", None)
        if index is not None:
            with contextlib.suppress(OSError):
                os.remove(index)
        return None

    def save_overload(sig, data):
        with contextlib.suppress(Exception):  # not cached: the next process compiles it
            save(sig, data)

    cache.load_overload, cache.save_overload = load_overload, save_overload


@contextlib.contextmanager
def _llvm_level(level: int):
    if "NUMBA_OPT" in os.environ:
        yield
        return
    saved = _numba_config.OPT
    _numba_config.OPT = type(saved)(level)
    try:
        yield
    finally:
        _numba_config.OPT = saved


COMPILE_NOTICE = (
    "fusion_opt: compiling native kernels that numba has not cached on this machine yet "
    "(about a minute before the first fusion; later processes load them from the cache in "
    "about half a second; fusion_opt.warmup(n, N, criterion) compiles them ahead)")


class _CompileNotice(_numba_event.Listener):
    """Says once per process, on the "fusion_opt" logger at WARNING (shown on stderr when
    the application configures no logging), that numba has started compiling one of the
    package's kernels: the first fusion on a machine otherwise sits silent for about a
    minute. numba announces a compile only on a miss of its disk cache, so a fusion whose
    kernels are cached (or compiled already) never reaches this. `send_to` gives it to
    another channel (a worker process passes it to its parent, which tells)."""

    def __init__(self):
        self.told = False
        self._channel = None

    def tell(self, write=None) -> None:
        """The notice, unless told already: logged, or given to write(text) (an
        application's own channel, such as its progress bar's; default: `send_to`'s)."""
        if not self.told:
            self.told = True
            write = self._channel if write is None else write
            if write is None:
                logging.getLogger("fusion_opt").warning(COMPILE_NOTICE)
            else:
                write(COMPILE_NOTICE)

    def send_to(self, write) -> None:
        """Later notices go to write(text) instead of the log."""
        self._channel = write

    def on_start(self, event):
        fn = getattr((event.data or {}).get("dispatcher"), "py_func", None)
        if getattr(fn, "__module__", "").startswith("fusion_opt."):
            self.tell()

    def on_end(self, event):
        pass


NOTICE = _CompileNotice()
_numba_event.register("numba:compile", NOTICE)
# numba joins a relative NUMBA_CACHE_DIR to the folder current at each load: a program
# that changed folder after the import loaded kernels the stale-cache check had not seen
# (fuzz9); the folder of the import is the one both use.
if _numba_config.CACHE_DIR and not os.path.isabs(_numba_config.CACHE_DIR):
    _numba_config.CACHE_DIR = os.path.abspath(_numba_config.CACHE_DIR)
drop_stale_caches(os.path.dirname(os.path.abspath(__file__)))
jit = _at_level_2(njit(cache=True, error_model="numpy"), njit(error_model="numpy"))
# For a one-problem step of a batch loop that takes its ~30 work arrays one by one: a
# compiled call passes each as a struct, and inlined into the loop (numba IR) the calls of
# `newton.solve_one` and `assemble.assemble_one` cost 0.5 us a problem less at (4, 3).
# Also for a kernel with one caller below those steps (`factored.improvement`, `eigh`, ...):
# numba optimises and emits each jit kernel's module with every kernel it calls linked in,
# so each link of a chain of such kernels did its callees' work again. Inlining 30 of them
# cut the six parts of the paper study, compiled cold one after the other, from 67.2 and
# 69.1 s of CPU to 62.6 and 65.3 (two runs each, in pairs on 2 cores); the tables and
# `fo.bci`'s results are bit for bit the same, and as fast.
inline = _at_level_2(njit(cache=True, error_model="numpy", inline="always"),
                     njit(error_model="numpy", inline="always"))


def row_norms(d: np.ndarray) -> np.ndarray:
    """Euclidean norms (...) of the vectors d (..., k), each in units of its largest
    |component|, so that no square over- or underflows (np.linalg.norm's squares made a
    distance of 2e200 inf and one of 2e-170 zero: fuzz N1); inf where a component is."""
    with np.errstate(over="ignore", invalid="ignore"):
        a = np.abs(d)
        top = a.max(axis=-1) if a.shape[-1] else np.zeros(a.shape[:-1])
        unit = np.where((top > 0.0) & (top < np.inf), top, 1.0)[..., None]
        out = top * np.sqrt(np.einsum("...k,...k->...", a / unit, a / unit))
    return np.where(top < np.inf, out, np.inf)


@jit
def cholesky(A, L) -> bool:
    """Lower Cholesky factor of the symmetric A (n, n) into L; False (L undefined) when a
    pivot is not positive or not finite, i.e. A is not positive definite to rounding.
    Above SMALL by LAPACK's blocked dpotrf (at n = 800 0.014 against 0.083 s)."""
    n = A.shape[0]
    if n > SMALL:
        return _lapack_cholesky(A, L)
    for j in range(n):
        d = A[j, j]
        for p in range(j):
            d -= L[j, p] * L[j, p]
        if not d > 0.0 or not np.isfinite(d):
            return False
        d = np.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for p in range(j):
                t -= L[i, p] * L[j, p]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@jit
def lower_inverse(L, X):
    """X = L^-1 for a lower-triangular L with a nonzero diagonal (X may not be L). Above
    order BY_ROWS by rows of X (each entry's sum in the same order, so the same bits: at 256 the
    columns' stride made it 4.5 against 1.0 ms; at 6, 0.13 against 0.17 us the other way)."""
    n = L.shape[0]
    if n > BY_ROWS:
        _lower_inverse_rows(L, X)
        return
    for j in range(n):
        for i in range(j):
            X[i, j] = 0.0
        X[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            t = 0.0
            for p in range(j, i):
                t -= L[i, p] * X[p, j]
            X[i, j] = t / L[i, i]


@jit
def _lower_inverse_rows(L, X):
    """`lower_inverse` row by row: entry (i, j) is 0 - sum_{p = j}^{i - 1} L[i, p] X[p, j]
    in the order of p, then divided by L[i, i], as by columns."""
    n = L.shape[0]
    for i in range(n):
        for j in range(n):
            X[i, j] = 0.0
        for p in range(i):
            a = L[i, p]
            for j in range(p + 1):
                X[i, j] -= a * X[p, j]
        for j in range(i):
            X[i, j] /= L[i, i]
        X[i, i] = 1.0 / L[i, i]


@jit
def lower_solve(L, B, X):
    """X = L^-1 B by forward substitution, for a lower-triangular L with a nonzero diagonal
    and B (n, k) (X may not be L or B): exact where B = L (the identity), as LAPACK's
    dtrtrs, which a product with L^-1 is not."""
    n, k = B.shape
    for i in range(n):  # by rows of X (each entry's sums in the same order as by columns,
        for j in range(k):  # which strode through X: 3 times slower at n = 200, k = 100)
            X[i, j] = B[i, j]
        for p in range(i):
            a = L[i, p]
            for j in range(k):
                X[i, j] -= a * X[p, j]
        for j in range(k):
            X[i, j] /= L[i, i]


@jit
def lower_t_solve(L, Bt, X):
    """X = L^-T B for a lower-triangular L (m, m) and B (m, k) given as Bt (k, m), by back
    substitution in rows of L (each x_i, once known, is taken from the rows above it:
    column by column, L's stride made it 6.6 against 1.0 ms at m = 1024, k = 4)."""
    m, kk = L.shape[0], Bt.shape[0]
    for i in range(m):
        for j in range(kk):
            X[i, j] = Bt[j, i]
    for i in range(m - 1, -1, -1):
        for j in range(kk):
            X[i, j] /= L[i, i]
        for p in range(i):
            for j in range(kk):
                X[p, j] -= L[i, p] * X[i, j]


@jit
def upper_inverse(R, X):
    """X = R^-1 for an upper-triangular R with a nonzero diagonal (X may not be R); above
    order BY_ROWS by rows of X, as `lower_inverse` (the same bits; at 800, 0.10 s by columns)."""
    n = R.shape[0]
    if n > BY_ROWS:
        _upper_inverse_rows(R, X)
        return
    for j in range(n):
        for i in range(j + 1, n):
            X[i, j] = 0.0
        X[j, j] = 1.0 / R[j, j]
        for i in range(j - 1, -1, -1):
            t = 0.0
            for p in range(i + 1, j + 1):
                t -= R[i, p] * X[p, j]
            X[i, j] = t / R[i, i]


@jit
def _upper_inverse_rows(R, X):
    """`upper_inverse` row by row, from the last: entry (i, j) is 0 - sum_{p = i + 1}^{j}
    R[i, p] X[p, j] in the order of p, then divided by R[i, i], as by columns."""
    n = R.shape[0]
    for i in range(n - 1, -1, -1):
        for j in range(n):
            X[i, j] = 0.0
        for p in range(i + 1, n):
            a = R[i, p]
            for j in range(p, n):
                X[i, j] -= a * X[p, j]
        for j in range(i + 1, n):
            X[i, j] /= R[i, i]
        X[i, i] = 1.0 / R[i, i]


@jit
def householder(At, n, rows, Vt, R):
    """QR of A = At[:n, :rows]^T (rows >= n), given transposed so that every column of A is
    a contiguous row: At is overwritten, the unit reflectors v_k (H_k = I - 2 v v^T) go to
    Vt[k, k:rows], R[:n, :n] is upper triangular (R_kk of either sign). Q = H_0 ... H_{n-1}.
    Whole buffers and sizes are passed, not slices: each array layout would compile anew,
    and at n = 4 a view costs more than the arithmetic."""
    for k in range(n):
        alpha, nonzero = _reflector(At, k, rows, Vt)
        if nonzero:
            # four (then two) columns at once (`_reflect4`)
            j = k + 1
            while j + 4 <= n:
                _reflect4(At, j, Vt, k, rows)
                j += 4
            if j + 2 <= n:
                t0 = t1 = 0.0
                for i in range(k, rows):
                    v = Vt[k, i]
                    t0 += v * At[j, i]
                    t1 += v * At[j + 1, i]
                t0 *= 2.0
                t1 *= 2.0
                for i in range(k, rows):
                    v = Vt[k, i]
                    At[j, i] -= t0 * v
                    At[j + 1, i] -= t1 * v
                j += 2
            if j < n:
                _reflect(At, j, Vt, k, rows)
        R[k, k] = alpha
        for j in range(k + 1, n):
            R[k, j] = At[j, k]
        for j in range(k):
            R[k, j] = 0.0


@inline
def householder_column(At, k, rows, Vt, R):
    """Column k of `householder`'s QR given its first k reflectors in Vt (left-looking:
    a column appended to a factorization, in O(k rows) instead of a new QR): At[k] is
    overwritten, v_k goes to Vt[k], R[:k + 1, k] and R[k, :k] are set. The same numbers
    as `householder` of the k + 1 columns: each reflector meets column k with the same
    operations in the same order."""
    for p in range(k):
        _reflect(At, k, Vt, p, rows)
        R[p, k] = At[k, p]  # final once reflector p is applied (later ones start below)
        R[k, p] = 0.0
    R[k, k] = _reflector(At, k, rows, Vt)[0]


@jit
def _reflector(At, k, rows, Vt):
    """The unit Householder vector v_k of column At[k, k:rows] into Vt[k, k:rows]; returns
    (R_kk, whether v_k is nonzero; for a zero column it is 0 and H_k = I)."""
    norm = 0.0
    for i in range(k, rows):
        norm += At[k, i] * At[k, i]
    norm = np.sqrt(norm)
    alpha = -norm if At[k, k] >= 0.0 else norm
    vnorm2 = 0.0
    for i in range(k, rows):
        Vt[k, i] = At[k, i]
    Vt[k, k] -= alpha
    for i in range(k, rows):
        vnorm2 += Vt[k, i] * Vt[k, i]
    if vnorm2 > 0.0:
        scale = 1.0 / np.sqrt(vnorm2)
        for i in range(k, rows):
            Vt[k, i] *= scale
    return alpha, vnorm2 > 0.0


@inline
def _reflect4(X, j, Vt, k, rows):
    """`_reflect` of rows j..j + 3 of X at once: four independent sums, each in the order
    of i as one row at a time would (the same results, 20 to 40% faster)."""
    t0 = t1 = t2 = t3 = 0.0
    for i in range(k, rows):
        v = Vt[k, i]
        t0 += v * X[j, i]
        t1 += v * X[j + 1, i]
        t2 += v * X[j + 2, i]
        t3 += v * X[j + 3, i]
    t0 *= 2.0
    t1 *= 2.0
    t2 *= 2.0
    t3 *= 2.0
    for i in range(k, rows):
        v = Vt[k, i]
        X[j, i] -= t0 * v
        X[j + 1, i] -= t1 * v
        X[j + 2, i] -= t2 * v
        X[j + 3, i] -= t3 * v


@jit
def _reflect(X, j, Vt, k, rows):
    """X[j, k:rows] <- (I - 2 v v^T) X[j, k:rows] with v = Vt[k]."""
    t = 0.0
    for i in range(k, rows):
        t += Vt[k, i] * X[j, i]
    t *= 2.0
    for i in range(k, rows):
        X[j, i] -= t * Vt[k, i]


@jit
def _lapack_cholesky(A, L) -> bool:
    """`cholesky` by dpotrf: "U" on the C-order copy is the lower factor (Fortran's upper
    triangle is C's lower one); then a pivot that is not finite is refused as the loop
    refuses it (dpotrf passes an inf)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            L[i, j] = A[i, j]
        for j in range(i + 1, n):
            L[i, j] = 0.0
    if _POTRF(_DOUBLE, _UPPER, n, L.ctypes, L.strides[0] // 8) != 0:
        return False
    for j in range(n):
        if not np.isfinite(L[j, j]):
            return False
    return True


@jit
def qr(At, n, rows, Vt, R):
    """`householder`'s QR (the same outputs: unit reflectors v_k in Vt, H_k = I - 2 v v^T,
    R upper), above SMALL columns by LAPACK's blocked dgeqrf: its reflectors w_k (w_kk = 1)
    with factors tau_k, H_k = I - tau_k w w^T, are householder's v_k = sqrt(tau_k / 2) w_k.
    At (C order, rows along its second axis) is A in Fortran order, as LAPACK takes it."""
    if n <= SMALL:
        householder(At, n, rows, Vt, R)
        return
    tau = np.empty(n)
    _GEQRF(_DOUBLE, rows, n, At.ctypes, At.strides[0] // 8, tau.ctypes)
    for k in range(n):
        s = np.sqrt(0.5 * tau[k])
        Vt[k, k] = s
        for i in range(k + 1, rows):
            Vt[k, i] = s * At[k, i]
        _r_row(At, k, n, R)


@jit
def qr_thin(At, n, rows, Vt, R):
    """`householder` then `thin_qt` into At (At[:n, :rows] = the first n columns of Q,
    transposed, and R); above SMALL columns by LAPACK's dgeqrf and dorgqr (Vt is then
    left as it was)."""
    if n <= SMALL:
        householder(At, n, rows, Vt, R)
        thin_qt(Vt, n, rows, At)
        return
    tau = np.empty(n)
    _GEQRF(_DOUBLE, rows, n, At.ctypes, At.strides[0] // 8, tau.ctypes)
    for k in range(n):
        _r_row(At, k, n, R)
    _ORGQR(_DOUBLE, rows, n, n, At.ctypes, At.strides[0] // 8, tau.ctypes)


@jit
def _r_row(At, k, n, R):
    """Row k of R from LAPACK's factored At (R in its upper triangle, Fortran order)."""
    for j in range(k):
        R[k, j] = 0.0
    for j in range(k, n):
        R[k, j] = At[j, k]


@jit
def apply_qt(Vt, n, rows, b):
    """b[:rows] <- Q^T b[:rows] with the n reflectors of `householder`."""
    for k in range(n):
        apply_reflector(Vt, k, rows, b)


@jit
def apply_reflector(Vt, k, rows, b):
    """b[k:rows] <- (I - 2 v v^T) b[k:rows] with v = Vt[k] (H_k of `householder`)."""
    t = 0.0
    for i in range(k, rows):
        t += Vt[k, i] * b[i]
    t *= 2.0
    for i in range(k, rows):
        b[i] -= t * Vt[k, i]


@inline
def thin_qt(Vt, n, rows, Qt):
    """Qt[:n, :rows] = the transpose of the first n columns of Q (n reflectors): column
    j is H_j ... H_0 e_j (H_k e_j = e_j for k > j), four columns at a time where all four
    meet H_k (`_reflect4`: the same bits, each reflector read once for four; at n = 800,
    rows = 1600, one at a time took 1.0 s)."""
    for j in range(n):
        for i in range(rows):
            Qt[j, i] = 1.0 if i == j else 0.0
    j = 0
    while j + 4 <= n:
        for k in range(j + 3, j, -1):
            for q in range(k, j + 4):
                _reflect(Qt, q, Vt, k, rows)
        for k in range(j, -1, -1):
            _reflect4(Qt, j, Vt, k, rows)
        j += 4
    for q in range(j, n):
        for k in range(q, -1, -1):
            _reflect(Qt, q, Vt, k, rows)


@jit
def copy(dst, src):
    """dst[...] = src for arrays of one shape (1-D or 2-D): a loop, which in compiled code
    costs a fraction of an array assignment's broadcasting machinery (6 against 200 ns)."""
    if src.ndim == 1:
        for i in range(src.shape[0]):
            dst[i] = src[i]
    else:
        for i in range(src.shape[0]):
            for j in range(src.shape[1]):
                dst[i, j] = src[i, j]


@jit
def pow2(e) -> float:
    """2^e where it is a normal number (-1022 <= e <= 1023), else 0. x * pow2(e) is then
    ldexp(x, e) exactly (one rounding of x 2^e either way, also to a subnormal) without a
    library call per entry (7 ns each, more than the rest of scaling an n = 4 matrix)."""
    if -1022 <= e <= 1023:
        return np.ldexp(1.0, e)
    return 0.0


@jit
def fill(dst, value):
    """dst[:] = value for a 1-D array, as a loop."""
    for i in range(dst.shape[0]):
        dst[i] = value


@jit
def matmul(A, B, C):
    """C = A @ B (C may not alias A or B): BLAS above SMALL, else `small_mul`."""
    if A.shape[0] > SMALL or A.shape[1] > SMALL or B.shape[1] > SMALL:
        np.dot(np.ascontiguousarray(A), np.ascontiguousarray(B), C)
        return
    small_mul(A, B, C, False)


@jit
def matmul_t(A, B, C):
    """C = A @ B^T (C may not alias A or B): BLAS above SMALL, else `small_mul_t`."""
    if A.shape[0] > SMALL or A.shape[1] > SMALL or B.shape[0] > SMALL:
        np.dot(np.ascontiguousarray(A), np.ascontiguousarray(B.T), C)
        return
    small_mul_t(A, B, C)


@jit
def gram(B, G):
    """G = B^T B (n, n), exactly symmetric, for B (M, n): BLAS above SMALL, else
    `small_gram`."""
    n = B.shape[1]
    if B.shape[0] > SMALL or n > SMALL:
        np.dot(np.ascontiguousarray(B.T), np.ascontiguousarray(B), G)
        for i in range(n):
            for j in range(i + 1, n):
                G[i, j] = G[j, i] = 0.5 * (G[i, j] + G[j, i])
        return
    small_gram(B, G)


# The loops of matmul, matmul_t and gram. A kernel run for every node at every step of the
# SQP calls them directly when its sizes are at most SMALL: LLVM inlines a function this
# small, but not one with a BLAS branch, and the call of matmul then costs as much as a
# 4 x 4 product (56 against 26 ns). Each computes four entries of a row at once (four
# independent sums, each in the order of k as one at a time would: the same results, about
# 30% faster at n = 4 and 12, where a single sum waits on the latency of each addition).

@jit
def small_mul(A, B, C, upper: bool):
    """C = A @ B by loops (C may not alias A or B); upper: A is upper triangular (zero
    below the diagonal), whose zeros are skipped (`node_mul` says why that changes no
    bit)."""
    for i in range(A.shape[0]):
        low = i if upper else 0
        j = 0
        while j + 4 <= B.shape[1]:
            t0 = t1 = t2 = t3 = 0.0
            for k in range(low, A.shape[1]):
                a = A[i, k]
                t0 += a * B[k, j]
                t1 += a * B[k, j + 1]
                t2 += a * B[k, j + 2]
                t3 += a * B[k, j + 3]
            C[i, j], C[i, j + 1], C[i, j + 2], C[i, j + 3] = t0, t1, t2, t3
            j += 4
        for jr in range(j, B.shape[1]):
            t = 0.0
            for k in range(low, A.shape[1]):
                t += A[i, k] * B[k, jr]
            C[i, jr] = t


@jit
def small_mul_t(A, B, C):
    """C = A @ B^T by loops (C may not alias A or B)."""
    for i in range(A.shape[0]):
        j = 0
        while j + 4 <= B.shape[0]:
            t0 = t1 = t2 = t3 = 0.0
            for k in range(A.shape[1]):
                a = A[i, k]
                t0 += a * B[j, k]
                t1 += a * B[j + 1, k]
                t2 += a * B[j + 2, k]
                t3 += a * B[j + 3, k]
            C[i, j], C[i, j + 1], C[i, j + 2], C[i, j + 3] = t0, t1, t2, t3
            j += 4
        for jr in range(j, B.shape[0]):
            t = 0.0
            for k in range(A.shape[1]):
                t += A[i, k] * B[jr, k]
            C[i, jr] = t


@jit
def small_gram(B, G):
    """G = B^T B by loops, exactly symmetric."""
    n = B.shape[1]
    for i in range(n):
        j = i
        while j + 4 <= n:
            t0 = t1 = t2 = t3 = 0.0
            for k in range(B.shape[0]):
                b = B[k, i]
                t0 += b * B[k, j]
                t1 += b * B[k, j + 1]
                t2 += b * B[k, j + 2]
                t3 += b * B[k, j + 3]
            G[i, j], G[i, j + 1], G[i, j + 2], G[i, j + 3] = t0, t1, t2, t3
            G[j, i], G[j + 1, i], G[j + 2, i], G[j + 3, i] = t0, t1, t2, t3
            j += 4
        for jr in range(j, n):
            t = 0.0
            for k in range(B.shape[0]):
                t += B[k, i] * B[k, jr]
            G[i, jr] = t
            G[jr, i] = t


@jit
def node_mul(F, i, A, C, upper: bool):
    """C = F[i] @ A for a stack F (N, n, n) of lower-triangular factors (zero above the
    diagonal), by loops and without the view F[i] (whose reference count costs about 10 ns
    a product at n = 4); upper: A is upper triangular (zero below the diagonal) too. The
    products with those zeros are skipped: each is 0 * x = +-0, which leaves a sum started
    at +0 as it was, so C is bit for bit the full product's (finite entries), at 58% of its
    multiplications at n = 6 (37% with an upper A)."""
    n = F.shape[1]
    for a in range(n):
        b = 0
        while b + 4 <= A.shape[1]:
            t0 = t1 = t2 = t3 = 0.0
            for k in range((min(a, b + 3) if upper else a) + 1):
                f = F[i, a, k]
                t0 += f * A[k, b]
                t1 += f * A[k, b + 1]
                t2 += f * A[k, b + 2]
                t3 += f * A[k, b + 3]
            C[a, b], C[a, b + 1], C[a, b + 2], C[a, b + 3] = t0, t1, t2, t3
            b += 4
        for br in range(b, A.shape[1]):
            t = 0.0
            for k in range((min(a, br) if upper else a) + 1):
                t += F[i, a, k] * A[k, br]
            C[a, br] = t


@inline
def node_tmul(F, i, A, C):
    """C = F[i]^T @ A for a stack F (N, n, n) of lower-triangular factors, by loops and
    without a view; the zeros of F[i]^T below its diagonal skipped as in `node_mul`."""
    n = F.shape[1]
    for a in range(n):
        b = 0
        while b + 4 <= A.shape[1]:
            t0 = t1 = t2 = t3 = 0.0
            for k in range(a, n):
                f = F[i, k, a]
                t0 += f * A[k, b]
                t1 += f * A[k, b + 1]
                t2 += f * A[k, b + 2]
                t3 += f * A[k, b + 3]
            C[a, b], C[a, b + 1], C[a, b + 2], C[a, b + 3] = t0, t1, t2, t3
            b += 4
        for br in range(b, A.shape[1]):
            t = 0.0
            for k in range(a, n):
                t += F[i, k, a] * A[k, br]
            C[a, br] = t


@inline
def eigh(S, lam, V):
    """lam (n,) ascending and V (n, n) orthonormal with S = V diag(lam) V^T for the
    symmetric S, which is overwritten (cyclic Jacobi when small, LAPACK otherwise)."""
    n = S.shape[0]
    if n > SMALL:
        w, U = np.linalg.eigh(np.ascontiguousarray(S))
        copy(lam, w)
        copy(V, U)
        return
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(_JACOBI_SWEEPS):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                # below eps times its diagonal neighbours an entry is rounding: leave it,
                # which keeps small eigenvalues to high relative accuracy
                if abs(S[p, q]) > _EPS * np.sqrt(abs(S[p, p] * S[q, q])):
                    _rotate(S, V, p, q)
                    rotated = True
        if not rotated:
            break
    for i in range(n):
        lam[i] = S[i, i]
    _sort_pairs(lam, V)


@inline
def _rotate(A, V, p, q):
    """One Jacobi rotation zeroing A[p, q] (Golub & Van Loan, Alg. 8.5.2)."""
    theta = (A[q, q] - A[p, p]) / (2.0 * A[p, q])
    t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    n = A.shape[0]
    for k in range(n):
        akp, akq = A[k, p], A[k, q]
        A[k, p] = c * akp - s * akq
        A[k, q] = s * akp + c * akq
    for k in range(n):
        apk, aqk = A[p, k], A[q, k]
        A[p, k] = c * apk - s * aqk
        A[q, k] = s * apk + c * aqk
    A[p, q] = 0.0
    A[q, p] = 0.0
    for k in range(n):
        vkp, vkq = V[k, p], V[k, q]
        V[k, p] = c * vkp - s * vkq
        V[k, q] = s * vkp + c * vkq


@inline
def _sort_pairs(lam, V):
    """Sort lam ascending, permuting the columns of V alike (insertion sort: n is small)."""
    n = lam.size
    for i in range(1, n):
        j = i
        while j > 0 and lam[j - 1] > lam[j]:
            lam[j - 1], lam[j] = lam[j], lam[j - 1]
            for r in range(n):
                V[r, j - 1], V[r, j] = V[r, j], V[r, j - 1]
            j -= 1
