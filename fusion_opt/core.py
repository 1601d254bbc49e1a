"""One path for every fusion: `fuse`, `fuse_batch`, `ci`, `bci` and `mbci` all come here.

A request is B problems of N estimates of an n-dimensional state (a single problem is a
batch of one, so it gives the same numbers alone or inside any batch):

    1. request  method, criterion, backend and the method's own arguments, checked by name
    2. arrays   means (B, N, n), covs (B, N, n, n): real float arrays of those shapes
    3. prepare  (compiled) checks every value; exact power-of-two prescaling; factors
    4. weights  "newton" / "closed-form": compiled, every problem in one call; another
                backend problem by problem on the congruence-scaled data, then polished by
                the compiled Newton method from its weights (the better certificate wins);
                a rule of `rules.py` gives its estimate directly
    5. assemble (compiled) fused mean, covariance, objective and certificate per problem
    6. status   Status.OPTIMAL when the relative certificate is within OPTIMAL_RTOL

Options, the same for fuse and fuse_batch (their defaults are set here and nowhere else):

    method     "bci" (default); "ci" (N = 2); "mbci"; or a rule of rules.py: "naive",
               "known-cross", "fast-ci", "ifci", "ici" (N = 2), "ei" (N = 2)
    criterion  "trace" (default) or "logdet"
    backend    a weight solver of BACKENDS, for ci, bci and mbci; default "newton" (exact,
               compiled, with its certificate; "clarabel" is the conic reference). The
               rules have no weight solver and refuse a backend.
    p_detect   mbci: detection probabilities in [0, 1]: a scalar, (N,), or (B, N) in a batch
    chi | growth   mbci: exactly one; chi in (0, 1], or growth = 1 / chi >= 1 (the paper's
               chi^-1); same shapes as p_detect
    cross      known-cross: the joint error covariance blocks (N, N, n, n), (B, N, N, n, n)
               in a batch
    polish     True (default): polish a conic or SLSQP backend's weights by Newton steps
"""

from __future__ import annotations

import functools
import threading
import time
from dataclasses import dataclass

import numpy as np

from . import rules
from .assemble import assemble
from .backends import BACKENDS, EXACT, REGISTRY, newton, slsqp
from .detection import detection_split
from .exact import fuse_exact
from .limits import batch_bytes, conic_bytes, joint_bytes, limits, working_bytes
from .prepare import (
    ASYMMETRIC,
    COVS_NONFINITE,
    MEANS_NONFINITE,
    NOT_PD,
    SPREAD,
    prepare,
)
from .results import (
    BatchFusionResult,
    FusionInputError,
    FusionResult,
    FusionSolverError,
    Status,
    overflow_error,
)
from .scaling import conic_data
from .simplex import to_simplex
from .validation import (
    CRITERIA,
    SYMMETRY_RTOL,
    definiteness_error,
    kernel_array,
    real_array,
    safe_repr,
    symmetrised,
)

DEFAULT_BACKEND = "newton"
# A result is OPTIMAL when its certificate proves f(w) - f* <= OPTIMAL_RTOL |f| ("trace";
# absolute for "logdet", where it bounds log det P(w) - log det P*).
OPTIMAL_RTOL = 1e-10
# A native result not within OPTIMAL_RTOL is solved again by Clarabel (`_rescue`) up to
# this state dimension. Clarabel's solve grows about as n^6 (one thread, 2026-11-28: 0.5 s
# at n = 24, 2 s at 32, 15 s at 48, 72 s at 64) where the native one takes well under a
# second: a fuzz's result at n = 64 whose certificate was held above the tolerance by its
# rounding bound (a best node under condition 6.4e11, the others 1e100 times its scale;
# certified since by `factored._formed_gap`'s second bound) took 150-200 s for the same
# weights and certificate again. Above it the native result stands, optimal_inaccurate
# with its certificate; backend="clarabel" is the conic solve.
RESCUE_MAX_N = 32
CI_METHODS = ("ci", "bci", "mbci")
METHODS = (*CI_METHODS, *rules.RULES)
PAIR_METHODS = frozenset({"ci", *rules.PAIR_ONLY})
_ARGS = {"ci": frozenset(), "bci": frozenset(),
         "mbci": frozenset({"p_detect", "chi", "growth"}), **rules.RULE_ARGS}
_CONIC = frozenset({"clarabel", "clarabel-direct"})
# Interior-point weights below this fraction of the largest are the solver's stand-in for 0.
_SUPPORT_RTOL = 1e-7


@dataclass(frozen=True)
class Request:
    """A checked request: the method, criterion and resolved backend, and its arguments."""

    method: str
    criterion: str
    backend: str | None
    polish: bool
    args: dict

    @property
    def trace(self) -> bool:
        return self.criterion == "trace"


@dataclass(frozen=True)
class Names:
    """What the caller called the arrays, for messages: `ci` says m_a and P_b where
    `fuse` says means and covs of node 1."""

    means: str = "means"
    covs: str = "covs"
    pair: bool = False

    def of(self, array: str, node: int, problem: int | None) -> str:
        if self.pair:
            return f"{'m' if array == 'means' else 'P'}_{'ab'[node]}"
        where = f"node {node}" if problem is None else f"problem {problem}, node {node}"
        return f"{getattr(self, array)} of {where}"


_NAMES = Names()


def request(method, criterion, backend, args: dict) -> Request:
    """Check the options by name (module docstring); nothing is computed yet. Options of
    plain types without a method argument but polish, the common case, are checked once
    per option set (`_plain_request`); a None method argument is one not given."""
    polish = args.get("polish", True)
    if len(args) == ("polish" in args) and type(polish) is bool and type(method) is str \
            and type(criterion) is str and (backend is None or type(backend) is str):
        return _plain_request(method, criterion, backend, polish)
    return _request(method, criterion, backend, {k: v for k, v in args.items() if v is not None})


@functools.lru_cache(maxsize=256)
def _plain_request(method: str, criterion: str, backend: str | None, polish: bool):
    """`request` without method arguments, the common case, checked once per option set
    (a check costs a tenth of a small fusion); a refused set is not cached."""
    return _request(method, criterion, backend, {"polish": polish})


def _request(method, criterion, backend, args: dict) -> Request:
    if not isinstance(method, str) or method not in METHODS:
        raise FusionInputError(f"method must be one of {METHODS}, got {safe_repr(method)}")
    if not isinstance(criterion, str) or criterion not in CRITERIA:
        raise FusionInputError(f"criterion must be one of {CRITERIA}, got {safe_repr(criterion)}")
    polish = args.pop("polish", True)
    if not isinstance(polish, bool):
        raise FusionInputError(f"polish must be True or False, got {safe_repr(polish)}")
    stray = sorted(set(args) - _ARGS[method])
    if stray:
        takes = sorted(_ARGS[method]) or "no other argument"
        raise FusionInputError(f"method {safe_repr(method)} takes {takes}, not {safe_repr(stray)}")
    if method in rules.RULES:
        if backend is not None:
            raise FusionInputError(f"method {safe_repr(method)} has no weight solver: leave "
                                   f"backend unset (got {safe_repr(backend)})")
        return Request(method, criterion, None, polish, args)
    if backend is None:
        backend = DEFAULT_BACKEND
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise FusionInputError(f"backend must be one of {BACKENDS}, got {safe_repr(backend)}")
    if method == "mbci" and "p_detect" not in args:
        raise FusionInputError("method 'mbci' needs p_detect, and chi or growth")
    return Request(method, criterion, backend, polish, args)


def arrays(means, covs, batch: bool, names: Names = _NAMES, req: Request | None = None):
    """means (B, N, n), covs (B, N, n, n) as C-contiguous float arrays (a single problem
    gains a leading axis of 1); shapes checked by name, and, given the request, the
    memory limits before anything is copied."""
    means, covs = real_array(means, names.means), real_array(covs, names.covs)
    lead = 2 if batch else 1
    shape = means.shape
    if means.ndim != lead + 1 or covs.shape != (*shape, shape[-1]) or 0 in shape:
        raise _shape_error(means, covs, batch, names)
    if not batch:
        means, covs = means[None], covs[None]
    if req is not None:
        B, N, n = means.shape
        check_memory(req, n, N, B)
    return kernel_array(means), kernel_array(covs)


def _shape_error(means, covs, batch: bool, names: Names) -> FusionInputError:
    """What is wrong with the shapes of means and covs, by name."""
    lead = 2 if batch else 1
    want = "(B, N, n)" if batch else "(N, n)"
    if means.ndim != lead + 1:
        return FusionInputError(f"{names.means} must have shape {want}, got {means.shape}")
    if covs.ndim != lead + 2 or covs.shape[-1] != covs.shape[-2]:
        return FusionInputError(f"{names.covs} must have shape {want[:-1]}, n), got "
                                f"{covs.shape}")
    if covs.shape[:-1] != means.shape:
        return FusionInputError(f"{names.covs} shape {covs.shape} does not match "
                                f"{names.means} shape {means.shape}")
    what = dict(zip("BNn", means.shape if batch else (1, *means.shape), strict=True))
    zero = [k for k, v in what.items() if v == 0]
    return FusionInputError(f"{names.means} and {names.covs} are empty ({zero[0]} = 0)")


def run(means, covs, req: Request, batch: bool, names: Names = _NAMES):
    """Fuse checked arrays (B, N, n), (B, N, n, n): a FusionResult (batch=False, B = 1) or
    a BatchFusionResult. newton and closed-form are one compiled call, in line here; a
    problem whose certificate is not within OPTIMAL_RTOL is tried again from Clarabel's
    weights (`_rescue`). (The Python layers this path lost on 2026-11-29, `_exact` and an
    output tuple unpacked by `_result`, cost a small fusion 6-11 % with the caches cold, as
    in the backends benchmark's rotation.)"""
    B, N, n = means.shape
    if req.method in PAIR_METHODS and N != 2:
        raise FusionInputError(f"method {safe_repr(req.method)} fuses 2 nodes, got N = {N}")
    if req.backend == "closed-form" and N != 2:
        raise FusionInputError(f"backend 'closed-form' fuses N = 2 nodes, got N = {N}")
    q, E = _detection(req, B, N, batch) if req.method == "mbci" else _unit_scales(B, N)
    a = _Arrays.take(B, N, n)
    try:
        if req.backend not in EXACT:
            if req.method in rules.RULES:
                _prepare(means, covs, q, E, a, names, batch)
                return _compiled(req, means, covs, a, batch)
            return _conic(req, means, covs, q, E, a, names, batch)
        t0 = time.perf_counter()
        code = fuse_exact(means, covs, q, E, req.trace, a.F, a.k, a.vertex, a.pnorm, a.where,
                          a.W, a.rel, a.iters, a.mean, a.cov, a.stats)
        if code > 0:
            raise _input_error(code, a.where, means, covs, names, batch, E)
        # the certificate reported, which the status is decided on
        if (a.stats[0, 2] if B == 1 else a.stats[:, 2].max()) > OPTIMAL_RTOL:
            _rescue(req, means, covs, q, E, a)
        if code < 0:
            raise _overflow(a, batch)
        return _ci_result(req, a, time.perf_counter() - t0, 0, batch)
    finally:
        a.give_back()


def _detection(req, B, N, batch):
    """MBCI's scales as covariance divisors q (B, N) in [1, 2) times 2^E."""
    a = req.args
    q, E = detection_split(a["p_detect"], a.get("chi"), N, growth=a.get("growth"),
                           leads=((), (B,)) if batch else ((),))
    # fresh arrays: (B, N) as they are, else broadcast to it
    q, E = (_read_only(x.reshape(B, N) if x.size == B * N else np.broadcast_to(x, (B, N)).copy())
            for x in (q, E))
    return q, E


@functools.lru_cache(maxsize=64)
def _unit_scales(B, N):
    """q = 1, E = 0 (B, N), read-only and shared: no scaling."""
    return _read_only(np.ones((B, N))), _read_only(np.zeros((B, N), dtype=np.int64))


def _read_only(a: np.ndarray) -> np.ndarray:
    """The scales q and E always reach the kernels read-only, shared or not, so that they
    are compiled for one array type."""
    a.setflags(write=False)
    return a


class _Arrays:
    """The arrays a batch of B problems of N nodes in dimension n is computed into."""

    def __init__(self, B, N, n):
        self.F = np.empty((B, N, n, n))
        self.vertex = np.empty((B, N, 2))
        self.pnorm = np.empty((B, N))
        self.W = np.empty((B, N))
        self.rel = np.empty(B)
        self.mean = np.empty((B, n))
        self.cov = np.empty((B, n, n))
        self.stats = np.empty((B, 3))
        self.k = np.empty(B, dtype=np.int64)
        self.iters = np.empty(B, dtype=np.int64)
        self.where = np.zeros(3, dtype=np.int64)

    @staticmethod
    def take(B, N, n) -> _Arrays:
        """New arrays for a batch; for one problem, this thread's scratch arrays of that
        shape, reused since allocating them all costs as much as fusing a small problem,
        with new output arrays W, mean and cov, which the result keeps. They are out of
        the thread's cache until `give_back`: a fusion that starts inside this one (a
        signal handler's, or one an argument's __array__ makes) gets its own (fuzz8 3, 4:
        it overwrote the arrays of the one it interrupted, which then returned its result)."""
        if B != 1:
            return _Arrays(B, N, n)
        try:
            a = _THREAD.arrays.pop((N, n))
        except (AttributeError, KeyError):
            a = _Arrays(1, N, n)
        a.W, a.mean, a.cov = np.empty((1, N)), np.empty((1, n)), np.empty((1, n, n))
        return a

    def give_back(self) -> None:
        """Return one problem's scratch arrays to this thread's cache (at most 64 shapes)."""
        _, N, n, _ = self.F.shape
        if len(self.F) == 1:
            cache = _THREAD.__dict__.setdefault("arrays", {})
            if len(cache) >= 64:
                cache.clear()
            cache[N, n] = self


_THREAD = threading.local()


# The parts of the library's kernels (`compile_part`), by stage: the parts of a stage can
# compile at once, in separate processes (longest first); "fuse" links the kernels of
# "solve" and "assemble" from their cache entries, so its stage starts after theirs, and
# "rules", "conic" and "network" load most of their kernels from those entries too.
# Tried on 2026-11-28 and slower: a second process compiling "rules" and "network" while
# "solve" compiles, so that "assemble", after them, would load the 17 s of kernels it
# shares with "solve" from the cache: cold, "rules" alone took 50-54 s (it shares most of
# its kernels with "solve" too) and the paper study's parts 133 and 136 s against 125 and
# 105 s for these stages, in turns on a busy machine. Tried on 2026-11-29 and no faster:
# numba inlining (`linalg.inline`) the solver's kernels called from one place (`_priced`,
# `_nearest`), which numba otherwise compiles, optimises and links again in every caller:
# "solve" alone 51.0 -> 40.7 s, but "assemble" 29.3 -> 34.6 and "fuse" 10.2 -> 14.7 (they
# compile the inlined code again instead of linking its cached entry), and the paper
# study's stages on a pool of two 85.5 against 86.2 s; inlining assemble's
# `_vertex_or_interior`, `_vertex` and `_interior` as well made "fuse" 43 s. Tried on
# 2026-11-29 and no faster: "network" in the first stage, after "assemble" (which now
# takes about as long as "solve", 41-50 s each on a pool of two): the paper study's parts
# 70.3 and 63.7 s against 68.1 and 59.0 s for these stages, in turns. Tried on 2026-11-29
# (parts compiled cold, each in a process of its own, in turns) and not kept: LLVM's loop
# unrolling off for the kernels ("solve", "assemble", "fuse" 92.9 -> 71.7 s of CPU, but
# `fuse_exact` 1.5 times slower from (4, 3) to (12, 7)); an inlining threshold of 75 or 25
# instead of level 2's (the eight parts 128.5, 123.5 s against 126.5, 128.7 and 115.0,
# 132.7: the machine's noise); `factored.improvement` and `_formed_gap` as kernels of
# their own instead of inlined ("assemble" 43.4, 44.4 -> 50.7, 47.4 s: each is then
# optimised and emitted again in every kernel up its chain of callers).
KERNEL_STAGES = (("solve", "assemble", "cross", "pairs"), ("rules", "fuse", "conic", "network"))
KERNEL_PARTS = tuple(part for stage in KERNEL_STAGES for part in stage)


def compile_part(part: str) -> float:
    """Compile, or load from numba's disk cache, one part of the library's kernels, each
    for the array types the library calls it with; returns the seconds it took. "solve":
    checks, factors and the weight solvers; "assemble": the fused estimates and their
    certificate; "conic": the scaled data a conic backend receives and the certificates of
    its polish; "rules": the fixed-weight rules' (naive, fast-ci, ifci) and
    `optimality_gap`'s kernels; "cross": known-cross's (7 s alone, cold, with numba's LAPACK
    Cholesky); "pairs": ici's and ei's; "fuse": `fuse_exact`,
    the whole exact path, from the kernels of "solve" and "assemble"; "network": the
    checks of an Estimates, MBCI's detection scales and the association of estimates. On
    a cold cache, processes compiling a stage's parts at once (KERNEL_STAGES) shorten the
    first fusion: about 70 s in one process; the paper study's parts took 25 s + 10.5 s
    on 2 cores (2026-11-27, an otherwise idle Intel Xeon; its first run came 38.6 s after
    the start, against 49.7 s when "conic" and "rules" were in the first stage, before the
    kernels of `linalg.inline` for compile time; `studies/runner.py` has its workers do
    it, as tests/conftest.py does)."""
    if part not in KERNEL_PARTS:
        raise ValueError(f"part must be one of {KERNEL_PARTS}, got {safe_repr(part)}")
    t0 = time.perf_counter()
    if part in ("rules", "cross", "pairs", "network"):
        {"rules": _rule_kernels, "cross": _cross_kernel, "pairs": _pair_kernels,
         "network": _network_kernels}[part]()
        return time.perf_counter() - t0
    B, N, n = 1, 3, 2
    a = _Arrays(B, N, n)
    means, covs = np.zeros((B, N, n)), np.tile(np.eye(n), (B, N, 1, 1))
    q, E = _unit_scales(B, N)
    if part == "fuse":
        fuse_exact(means, covs, q, E, True, a.F, a.k, a.vertex, a.pnorm, a.where, a.W, a.rel,
                   a.iters, a.mean, a.cov, a.stats)
        return time.perf_counter() - t0
    prepare(means, covs, q, E, a.F, a.k, a.vertex, a.pnorm, a.where)
    a.W[:] = 1.0 / N
    if part == "solve":
        newton.solve(a.F, True, a.W, False, a.W, a.rel, a.iters)
    elif part == "assemble":
        assemble(a.F, means, covs, q, E, a.k, a.vertex, a.pnorm, a.W, True, a.mean, a.cov,
                 a.stats)
    else:
        conic_data(a.F, np.empty((B, N, n, n)), np.empty((B, n, n)))
        newton.certificates(a.F, a.W, True, a.rel)
    return time.perf_counter() - t0


def _rule_kernels() -> None:
    """One call of the kernel of naive, fast-ci and ifci, and of `optimality_gap`'s."""
    from .fusion import fuse, optimality_gap

    means, covs = np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1))
    fuse(means, covs, "fast-ci")  # naive's and ifci's kernel too
    optimality_gap(covs, np.full(3, 1 / 3))


def _cross_kernel() -> None:
    """The kernel of known-cross."""
    from .fusion import fuse

    halves = np.tile(np.eye(2), (3, 3, 1, 1)) * 0.5  # correlation 1/2 between the nodes
    halves[np.arange(3), np.arange(3)] = np.eye(2)
    fuse(np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1)), "known-cross", cross=halves)


def _pair_kernels() -> None:
    """The kernel of ici and ei."""
    from .fusion import fuse

    fuse(np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1)), "ici")


def _network_kernels() -> None:
    """One call of each kernel on a network's path that a fusion does not call (two
    reports of each source at one point: a group that repeats a source is split)."""
    from .association import associate
    from .estimates import Estimates

    e = Estimates(np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1)))
    associate({0: e, 1: e}, 1.0)
    detection_split(np.full(3, 0.9), 0.9)


def _prepare(means, covs, q, E, a, names, batch):
    code = prepare(means, covs, q, E, a.F, a.k, a.vertex, a.pnorm, a.where)
    if code:
        raise _input_error(code, a.where, means, covs, names, batch, E)


def _conic(req, means, covs, q, E, a, names, batch):
    """A backend of REGISTRY problem by problem on the congruence-scaled data, then the
    Newton polish from its weights, and the fused estimates."""
    B, N, n = means.shape
    _prepare(means, covs, q, E, a, names, batch)
    t0 = time.perf_counter()
    Ys, M = np.empty((B, N, n, n)), np.empty((B, n, n))
    conic_data(a.F, Ys, M)
    for b in range(B):
        sol = REGISTRY[req.backend](Ys[b], M[b], req.criterion)
        a.W[b], a.iters[b] = to_simplex(sol.w), sol.iterations
    polish_iters = _polish(a, req.trace) if req.polish else 0
    solve_time = time.perf_counter() - t0
    if not assemble(a.F, means, covs, q, E, a.k, a.vertex, a.pnorm, a.W, req.trace, a.mean,
                    a.cov, a.stats):
        raise _overflow(a, batch)
    return _ci_result(req, a, solve_time, polish_iters, batch)


def _polish(a, trace) -> int:
    """Newton from the solver's weights a.W, its near-zero weights set to 0; per problem
    the better certificate of the two wins. Returns the largest polish iteration count."""
    W = a.W
    start = np.where(W >= _SUPPORT_RTOL * W.max(-1, keepdims=True), W, 0.0)
    start /= start.sum(-1, keepdims=True)
    Wp, rel_p, piters = np.empty_like(W), np.empty(len(W)), np.zeros(len(W), np.int64)
    newton.solve(a.F, trace, start, True, Wp, rel_p, piters)
    rel_0 = np.empty(len(W))
    newton.certificates(a.F, W, trace, rel_0)
    better = rel_p <= rel_0
    W[better] = Wp[better]
    return int(piters[better].max(initial=0))


def _rescue(req, means, covs, q, E, a):
    """Problems whose native certificate is not within OPTIMAL_RTOL (rounding level on a
    hard problem) are solved again by "clarabel-direct" and polished; per problem, the
    result with the better certificate is kept. Not where Clarabel's solve is over
    fusion_opt.limits (`over_memory`: at n = 150 its KKT system would take tens of GiB,
    and the rescue of a result spoiled on purpose there was killed for memory): the
    native result stands, with its certificate (status optimal_inaccurate); nor above
    RESCUE_MAX_N, where Clarabel takes minutes."""
    _, N, n, _ = a.F.shape
    rescue = Request(req.method, req.criterion, "clarabel-direct", True, req.args)
    if n > RESCUE_MAX_N or over_memory(rescue, n, N) is not None:
        return
    for b in np.flatnonzero(a.stats[:, 2] > OPTIMAL_RTOL):
        one = _Arrays(1, N, n)
        try:
            _conic(rescue, means[b:b + 1], covs[b:b + 1], q[b:b + 1], E[b:b + 1], one,
                   Names(), True)
        except FusionSolverError:
            continue
        if one.stats[0, 2] < a.stats[b, 2]:
            for name in ("W", "mean", "cov", "stats"):
                getattr(a, name)[b] = getattr(one, name)[0]
            a.iters[b] += one.iters[0]


_OPTIMAL_OR_NOT = np.array([Status.OPTIMAL, Status.OPTIMAL_INACCURATE], dtype=object)


def _ci_result(req, a, solve_time, polish_iters, batch):
    """The result of ci, bci or mbci from a's arrays: one problem's objective, gap, status
    and iterations read as plain numbers at once (without column views)."""
    if batch:
        status = _OPTIMAL_OR_NOT[(a.stats[:, 2] > OPTIMAL_RTOL).astype(np.intp)]
        return BatchFusionResult.owning(a.W, a.mean, a.cov, a.stats[:, 0], a.stats[:, 1],
                                        status, a.iters, req.backend, solve_time, req.method,
                                        req.criterion, "ci_weights")
    obj, gap, rel = a.stats[0].tolist()
    status = Status.OPTIMAL if rel <= OPTIMAL_RTOL else Status.OPTIMAL_INACCURATE
    return FusionResult.owning(a.W[0], a.mean[0], a.cov[0], obj, gap, status, req.backend,
                               solve_time, int(a.iters[0]), req.method, req.criterion,
                               polish_iters, "ci_weights")


def check_memory(req, n, N, B=1):
    """Refuses (FusionSolverError) B problems whose arrays, weight solver's work arrays or
    conic solve would exceed fusion_opt.limits, or whose N is past what "slsqp" can fuse
    in reasonable time (`slsqp.MAX_NODES`)."""
    if req.backend == "slsqp" and N > slsqp.MAX_NODES:
        raise FusionSolverError("slsqp", "node_limit", slsqp.node_limit(N))
    over = over_memory(req, n, N, B)
    if over is not None:
        raise FusionSolverError(req.backend or req.method, "memory_limit",
                                _memory(*over[:2], n, N, over[2]), _role(req))


def over_memory(req, n, N, B=1) -> tuple[str, float, str] | None:
    """(what, bytes, name of its limit in fusion_opt.limits) of B problems' memory over its
    limit (`check_memory`), or None: the batch's arrays and the solver's work arrays
    together against working_memory, Clarabel's KKT system against conic_memory. The
    numbers come first and the words only for one over its limit."""
    cross = req.method == "known-cross"  # its cross, copied whole where it is not float64
    arrays, work, conic = _bytes(cross, req.backend, n, N, B)
    if arrays + work <= limits.working_memory and conic <= limits.conic_memory:
        return None
    if arrays + work > limits.working_memory:  # allocated at once: their sum (fuzz O7:
        what = f"the arrays of {B} problem{'s' * (B != 1)}"  # each alone let 1.9x pass)
        if work:
            what += " and the whitened joint covariance" if cross else \
                " and the weight solver's work arrays"
        return what, arrays + work, "working_memory"
    return "Clarabel's KKT system", conic, "conic_memory"


@functools.lru_cache(maxsize=256)
def _bytes(cross: bool, backend: str | None, n: int, N: int, B: int):
    """The bytes of `over_memory` (a batch's arrays, the solver's work arrays, a conic
    solve), per request kind and shape: computed anew they cost a small fusion 0.8 us."""
    work = joint_bytes(n, N) if cross else \
        0.0 if backend is None else working_bytes(n, N, backend)
    arrays = batch_bytes(B, N, n) + (8.0 * B * (N * n) ** 2 if cross else 0.0)  # (fuzz L9)
    conic = conic_bytes(n, N) if backend in _CONIC else 0.0
    return arrays, work, conic


def _overflow(a, batch: bool) -> FusionInputError:
    """What of which problem overflowed (`results.overflow_error`)."""
    return overflow_error(a.mean, a.cov, a.stats[:, 0], batch)


def _compiled(req, means, covs, a, batch):
    """The result of a rule of rules.RULES, the whole batch in one compiled call (on the
    factors `prepare` left in a)."""
    B, N, n = means.shape
    cross = rules.cross_array(req.args.get("cross"), B, N, n, batch) \
        if req.method == "known-cross" else None
    weights, mean, cov, obj, status, are = rules.compiled(req.method, means, covs, a.F, a.k,
                                                          req.trace, cross, batch)
    if batch:
        return BatchFusionResult.owning(weights, mean, cov, obj, np.zeros(B),
                                        np.full(B, status, dtype=object),
                                        np.zeros(B, dtype=np.int64), None, 0.0, req.method,
                                        req.criterion, are)
    return FusionResult.owning(weights[0], mean[0], cov[0], float(obj[0]), 0.0, status, None,
                               0.0, 0, req.method, req.criterion, 0, are)


def _role(req) -> str:
    """What a FusionSolverError names: the backend, or a rule's method."""
    return "backend" if req.backend is not None else "method"


def _memory(what, need, n, N, limit_name) -> str:
    limit = getattr(limits, limit_name)
    return (f"n = {safe_repr(n)}, N = {safe_repr(N)}: {what} would need about "
            f"{need / 2**30:.3g} GiB, over the limit of {limit / 2**30:.3g} GiB "
            f"(fusion_opt.limits.{limit_name})")


def _input_error(code, where, means, covs, names, batch, E) -> FusionInputError:
    """The FusionInputError of a failed check of `prepare`, naming the argument."""
    b, i, j = (int(x) for x in where)
    problem = b if batch else None
    if code == MEANS_NONFINITE:
        return FusionInputError(f"{names.of('means', i, problem)} has a non-finite value "
                                f"{means[b, i, j]}")
    if code == COVS_NONFINITE:
        n = covs.shape[-1]
        value = covs[b, i, j // n, j % n]
        return FusionInputError(f"{names.of('covs', i, problem)} has a non-finite value "
                                f"{value} at [{j // n}, {j % n}]")
    P = covs[b, i]
    if code == ASYMMETRIC:
        asym = np.abs(P - P.T).max()
        return FusionInputError(
            f"{names.of('covs', i, problem)} is not symmetric: max |P - P^T| = {asym:.3g} "
            f"exceeds {SYMMETRY_RTOL:g} x max |P| = {np.abs(P).max():.3g}")
    if code == NOT_PD:
        return definiteness_error(names.of('covs', i, problem), symmetrised(P))
    assert code == SPREAD
    where_b = "" if problem is None else f" of problem {b}"
    if E[b].any():  # MBCI's scales s_i, not the covariances, make the spread
        return FusionInputError(
            f"{names.covs}{where_b} divided by their detection scales (from p_detect and chi "
            "or growth) span a ratio of scales beyond float64 (more than 2^1900 between "
            "nodes): leave out the node of the smallest scale, whose information is below "
            "float64's resolution beside the others'")
    return FusionInputError(f"{names.covs}{where_b} span a ratio of scales beyond float64 "
                            f"(more than 2^1900 between nodes)")
