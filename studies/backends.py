"""Benchmark of the weight solvers against each other and against the peers a user would
otherwise use: time, accuracy and certificate per solver and shape, and the issue's targets.

For every (n, N, criterion, kind) of the config, `instances` seeded problems (kind "random":
P_i = A A^T / n + 0.01 I with A standard normal; "ill-conditioned": eigenvalues log-uniform
over 1e-6..1e6 in a random rotation, each node scaled by 10^U(-3, 3)) are solved by every
solver in turn (in a seeded random order per problem, `_loop`), in one process. A solver
is one call a user makes:

    fo.bci(means, covs, criterion, backend)                    every backend, N >= 2
    fo.ci(m_a, P_a, m_b, P_b, criterion, backend)              every backend, N = 2
    fo.fuse(means, covs, "bci", criterion, backend, polish=False)  conic and SLSQP backends
    minimize_scalar   scipy's bounded scalar minimiser on w for a pair (N = 2), numpy inverses
    scipy-slsqp       scipy SLSQP on the simplex (sum w = 1, 0 <= w <= 1), numpy inverses,
                      finite-difference gradient: what a user writes (the "slsqp" backend
                      is fusion-opt's, with the analytic gradient and the polish)
    fixed-weights     w = 1/N (Stone Soup's default omega = 0.5 for a pair), numpy inverses
    fast-ci           fo.fuse(means, covs, "fast-ci", criterion) (Niehsen's weights)

("closed-form" and minimize_scalar at N = 2 only). Each peer computes the fused mean and
covariance too, as the user would. Time is CPU time (time.process_time, one BLAS thread:
the CLI sets OPENBLAS_NUM_THREADS=1) per call, with the garbage collector held off;
`repeats` calls per problem, fewer (at least one) where they would take more than
repeat_budget_ms. The first call of each shape (n, N, criterion) is reported apart
(first_ms: it builds CVXPY's program for "clarabel" and "scs", and Clarabel's template for
"clarabel-direct"; the compiled kernels are loaded before anything is timed, in
kernel_load_s of machine.json, beside the machine's pace at the start and end of the
measurement, `_pace`). solver_own_median_ms is the time the solver itself reports
(Clarabel's, SCS's) in the same calls and overhead_median_ms the rest of each call.

Accuracy is computed outside the solvers, on the weights w each returned, never from what
it reports: f and the certificate of DESIGN §1 by `fusion_opt.criteria.evaluate` (numpy) on
the congruence-scaled problem `scaling.conic_problem(covs)`, where the relative gaps are
those of the original problem and the numbers are of order one even for the ill-
conditioned kind:

    objective_gap    (f_s - f_best) / |f_best| (trace), f_s - f_best (logdet, nats), f_best
                     the best of every solver's f on the same problem
    optimality_gap   (g.w - min_i g_i) / |f| (trace), g.w - min_i g_i (logdet)

both at the weights put on the simplex (`_accuracy` says why); how far the returned
weights were from it is reported apart (worst_simplex_violation).

A failure is a call that raises, an fo.bci or fo.ci result that is not Status.OPTIMAL, or
a scipy result that is not a success. The Dolan-More performance profile counts a problem
solved by a solver that did not fail and whose objective gap is within each of
profile_tolerances.

Per single cell, newton's time by part (`_part_rows`, rows of mode "parts"): the whole
fo.bci call and the three parts of its compiled call, each timed warm, apart, so that
the report can say how much of a call the weight solve is and what is left of the
target's budget (Clarabel's time / 100) for it.

Then the `large` shapes (n = 48, N = 8) with large_backends only; and, per shape of
batch_shapes, `fo.fuse_batch` of batch_size random problems with each native backend (one
call, CPU time / B), of the first batch_small of them, the batched-inverse floor (one
`np.linalg.inv` of the stacked (B, N, n, n) covariances, per problem), timed in turns, and
loops of fo.bci on batch_check of them, on which the gaps are computed. Writes
backends.csv (a row per solver and cell), backends_instances.csv (a row per solver and
problem), backends.md with a CSV beside it for each of its tables (backends_<table>.csv),
backends_time_vs_N.png, backends_profile.png and machine.json; `report` rebuilds every
table and figure from the two measurement CSVs.

The peers are in studies/peers.py; the tables, targets, performance profile and
figures, rebuilt from the CSVs, in studies/backends_report.py.
"""

from __future__ import annotations

import gc
import json
import platform
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import fusion_opt as fo
from fusion_opt import core, criteria, programs
from fusion_opt.assemble import assemble
from fusion_opt.backends import EXACT, REGISTRY, clarabel_direct, newton
from fusion_opt.prepare import prepare
from fusion_opt.scaling import conic_problem
from fusion_opt.validation import safe_repr

from . import config as configs
from . import meta
from .backends_report import BCI, CI, PART_NAMES, RAW, _q, _worst, _write_csv, report
from .peers import (
    PEERS,
    PeerResult,
    fast_ci_peer,
    fixed_weights_peer,
    minimize_scalar_peer,
    slsqp_peer,
)

COLUMNS = ("mode", "call", "backend", "n", "N", "criterion", "kind", "per_call", "solves",
           "first_ms", "median_ms", "p90_ms", "solver_own_median_ms", "overhead_median_ms",
           "worst_objective_gap", "worst_optimality_gap", "worst_simplex_violation",
           "failures", "first_failure")
INSTANCE_COLUMNS = ("mode", "call", "backend", "n", "N", "criterion", "kind", "problem",
                    "time_ms", "objective_gap", "optimality_gap", "failed")
# what `run` measures and `report` reads; the CLI records their SHA-256 and verifies them
MEASUREMENTS = ("backends.csv", "backends_instances.csv", "machine.json")
FIRST_BATCH = 10  # problems of the untimed first fuse_batch call (loads, allocates)
PART_CALLS = 20  # newton's parts (`_part_rows`, PART_NAMES) are each timed over these


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this benchmark
    cannot run: called on the whole merged configuration before anything runs.
    "closed-form" and minimize_scalar fuse pairs only; they are skipped where N != 2."""
    lists = {"n": 1, "N": 2}  # list field -> its smallest value
    counts = ("instances", "repeats", "batch_size", "batch_small", "batch_repeats",
              "batch_check")
    choices = {"criteria": ("trace", "logdet"), "kinds": ("random", "ill-conditioned"),
               "backends": fo.BACKENDS, "peers": PEERS, "large_backends": fo.BACKENDS}
    configs.fields(config, "", ("seed", "repeat_budget_ms", "profile_tolerances", "large",
                                "large_instances", "batch_shapes", *choices, *lists,
                                *counts))
    configs.integer("seed", config["seed"], low=0)
    configs.integer("large_instances", config["large_instances"], low=1)
    configs.number("repeat_budget_ms", config["repeat_budget_ms"], above=0)
    for key, low in lists.items():
        for i, v in enumerate(configs.items(key, config[key])):
            configs.integer(f"{key}[{i}]", v, low=low)
    for i, v in enumerate(configs.items("profile_tolerances", config["profile_tolerances"])):
        configs.number(f"profile_tolerances[{i}]", v, above=0)
    for key in counts:
        configs.integer(key, config[key], low=1)
    for key in ("batch_small", "batch_check"):  # a sample of the batch (batch_check was
        if config[key] > config["batch_size"]:   # clipped while the report said it whole)
            raise configs.ConfigError(f"{key} must be <= batch_size ({config['batch_size']}), "
                                      f"got {config[key]}")
    for key in ("large", "batch_shapes"):
        _check_shapes(key, config[key])
    for key, options in choices.items():
        values = config[key] if key == "peers" and config[key] == [] else \
            configs.items(key, config[key])  # no peer is a benchmark of the backends alone
        for i, v in enumerate(values):
            configs.choice(f"{key}[{i}]", v, options)
    for key in (*lists, *choices, "profile_tolerances"):
        twice = sorted({v for v in config[key] if config[key].count(v) > 1})
        if twice:
            raise configs.ConfigError(f"{key} lists {twice} more than once")
    _check_sizes(config)
    if set(config["backends"]) == {"closed-form"} and 2 not in config["N"]:
        raise configs.ConfigError(f"backends ['closed-form'] fuses N = 2 only, which N = "
                                  f"{config['N']} does not hold: nothing would be measured")


def _check_sizes(config: dict) -> None:
    """Every cell's problems, and each backend's fusion of them, within fusion_opt.limits
    (a cell's K problems and their copies about 4 K N n^2 doubles; a batch with its
    results about 6 B N (n^2 + n); a row per solver and problem, about 1 KB, kept to the
    end), before anything runs."""
    K, K_large = config["instances"], config["large_instances"]
    cells = [(n, N, config["backends"], "instances", K) for n in config["n"]
             for N in config["N"]]
    cells += [(n, N, config["large_backends"], "large_instances", K_large)
              for n, N in config["large"]]
    for n, N, backends, name, k in cells:
        configs.fits(f"n = {n}, N = {N} with {name} = {k}", 8.0 * 4 * k * N * n * n)
        for b in backends:
            configs.fusion_fits(f"n = {n}, N = {N} ({b})", n, N, b)
    per_cell = len(config["criteria"]) * len(config["kinds"])
    rows = per_cell * (len(config["n"]) * len(config["N"]) * K * (
        len(config["backends"]) + len(config["peers"])) + len(config["large"]) * K_large
        * len(config["large_backends"]))
    configs.fits(f"instances = {K} and large_instances = {K_large} ({rows} rows of "
                 "backends_instances.csv)", 1024.0 * rows)
    for n, N in config["batch_shapes"]:
        configs.fits(f"batch_shapes [{n}, {N}] with batch_size = {config['batch_size']}",
                     8.0 * 6 * config["batch_size"] * N * (n * n + n))


def _check_shapes(key: str, shapes) -> None:
    """shapes: a list of distinct [n, N] with n >= 1 and N >= 2 (empty: none run)."""
    if not isinstance(shapes, list):
        raise configs.ConfigError(f"{key} must be a list of [n, N], got {safe_repr(shapes)}")
    for i, shape in enumerate(shapes):
        if not isinstance(shape, list) or len(shape) != 2:
            raise configs.ConfigError(f"{key}[{i}] must be a list [n, N], got {safe_repr(shape)}")
        configs.integer(f"{key}[{i}][0] (n)", shape[0], low=1)
        configs.integer(f"{key}[{i}][1] (N)", shape[1], low=2)
    if len({tuple(s) for s in shapes}) != len(shapes):
        raise configs.ConfigError(f"{key} lists a shape more than once: {safe_repr(shapes)}")


def instance(rng: np.random.Generator, N: int, n: int, kind: str) -> np.ndarray:
    """Covariances (N, n, n) of one problem of the given kind (module docstring)."""
    if kind == "random":
        A = rng.standard_normal((N, n, n))
        return A @ np.swapaxes(A, -1, -2) / n + 0.01 * np.eye(n)
    Q = np.linalg.qr(rng.standard_normal((N, n, n)))[0]
    eig = 10.0 ** rng.uniform(-6, 6, (N, n)) * 10.0 ** rng.uniform(-3, 3, (N, 1))
    P = (Q * eig[:, None, :]) @ np.swapaxes(Q, -1, -2)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def run(config: dict, out_dir: Path, *, quick: bool, progress: bool) -> None:
    """Run the benchmark of `config` (studies/configs/backends.toml) and write its files."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    load = _load_kernels(config)
    pace = {"start": _pace()}
    rows, instances = _measure(config, progress)
    pace["end"] = _pace()
    _write_csv(out_dir / "backends.csv", COLUMNS, rows)
    _write_csv(out_dir / "backends_instances.csv", INSTANCE_COLUMNS, instances)
    info = {"versions": meta.versions(), "machine": meta.machine(),
            "git_commit": meta.git_commit(), "numpy_config": _blas(),
            "python": platform.python_implementation(), "quick": quick,
            "kernel_load_s": load, "measure_wall_time_s": time.perf_counter() - t0,
            "pace_us": pace,
            "config": config}
    (out_dir / "machine.json").write_text(json.dumps(info, indent=2, default=str))
    report(config, out_dir, quick=quick)


def _blas() -> str:
    import numpy

    cfg = numpy.show_config(mode="dicts")["Build Dependencies"]
    return f"{cfg['blas'].get('name')} {cfg['blas'].get('version')}"


def _pace() -> dict:
    """The machine's pace now: CPU microseconds per call (least of 5 rounds, `_timed`) of a fixed
    pure-Python loop and of np.linalg.inv on one 4 x 4 matrix, so that runs made in
    different hours can be compared (the same code's calls took 2-5 times longer in some
    hours than in others, Python more so than compiled code)."""
    def python_loop():
        total = 0
        for i in range(1000):
            total += i * i
        return total

    A = np.eye(4) + 0.1
    calls = {"python_loop": (python_loop, 200), "numpy_inv_4x4": (lambda: np.linalg.inv(A), 2000)}
    return {name: min(_timed(_repeat, call, k)[0] for _ in range(5)) / k * 1e6
            for name, (call, k) in calls.items()}


def _load_kernels(config) -> float:
    """Seconds to load (or, on a new machine, compile) the compiled kernels every backend
    uses, by fusing a pair and a triple with each; then the per-shape caches are emptied,
    so that first_ms is the first call of a shape and nothing else."""
    t0 = time.perf_counter()
    for b in dict.fromkeys(config["backends"] + config["large_backends"]):
        for crit in config["criteria"]:
            for N in (2, 3) if b != "closed-form" else (2,):  # N = 2 has its own kernel
                try:
                    fo.warmup(2, N, crit, b)
                except fo.FusionSolverError:
                    pass  # the kernels are loaded all the same; failures are counted later
    programs.clear_cache()
    clarabel_direct.template.cache_clear()
    return time.perf_counter() - t0


# ------------------------------------------------------------------------ measurement

@dataclass(frozen=True)
class _Solver:
    """One call: call(*data, criterion=..., **kwargs), where data is (means, covs), or
    (m_a, P_a, m_b, P_b) when pair; certified: a result not Status.OPTIMAL is a failure."""

    call: str
    backend: str
    fn: Callable
    kwargs: dict = field(default_factory=dict)
    pair: bool = False
    certified: bool = False

    def outcome(self, result) -> tuple[np.ndarray, bool]:
        """(weights, not failed) of one result of this call."""
        if isinstance(result, PeerResult):
            return np.asarray(result.weights, dtype=float), result.ok
        return result.weights, not self.certified or result.status == fo.Status.OPTIMAL


_PEERS = {"minimize_scalar": _Solver("minimize_scalar", "-", minimize_scalar_peer, pair=True),
          "scipy-slsqp": _Solver("scipy-slsqp", "-", slsqp_peer),
          "fixed-weights": _Solver("fixed-weights", "-", fixed_weights_peer),
          "fast-ci": _Solver("fast-ci", "-", fast_ci_peer)}


def _solvers(backends, peers, N: int, more: bool = True) -> list[_Solver]:
    """The calls of a cell with N nodes: fo.bci of each backend and, when more, fo.ci at
    N = 2 and fo.fuse(polish=False) of each backend that has a polish; then the peers."""
    out = []
    for b in backends:
        if b == "closed-form" and N != 2:
            continue
        out.append(_Solver(BCI, b, fo.bci, {"backend": b}, certified=True))
        if more and N == 2:
            out.append(_Solver(CI, b, fo.ci, {"backend": b}, pair=True, certified=True))
        if more and b in REGISTRY:
            out.append(_Solver(RAW, b, fo.fuse, {"method": "bci", "backend": b,
                                                  "polish": False}))
    return out + [_PEERS[p] for p in peers if N == 2 or not _PEERS[p].pair]


@dataclass
class _Runs:
    """What one solver gave on the problems of one cell: times (s) of every timed call,
    with the solver's own time of each (NaN if it reports none); per problem, the median
    time (NaN where it raised), the weights (N,) (NaN where it raised) and whether it
    failed; a call fuses `per_call` problems."""

    solver: _Solver
    mode: str
    per_call: int = 1
    times: list = field(default_factory=list)
    own: list = field(default_factory=list)
    problem_times: list = field(default_factory=list)
    weights: list = field(default_factory=list)
    failed: list = field(default_factory=list)
    first: float = np.nan
    first_failure: str = ""

    def fail(self, why: str, N: int) -> None:
        """A problem the solver raised on."""
        self.first_failure = self.first_failure or why
        self.problem_times.append(np.nan)
        self.weights.append(np.full(N, np.nan))
        self.failed.append(True)


def _measure(config, progress) -> tuple[list[dict], list[dict]]:
    """Every single-problem cell, the large cells, then every batch cell: rows per solver
    and cell, and rows per solver and problem."""
    from tqdm import tqdm

    cells = [("single", n, N, crit, kind) for n in config["n"] for N in config["N"]
             for crit in config["criteria"] for kind in config["kinds"]]
    cells += [("large", n, N, crit, kind) for n, N in config["large"]
              for crit in config["criteria"] for kind in config["kinds"]]
    batch = [(n, N, crit) for n, N in config["batch_shapes"] for crit in config["criteria"]]
    *seeds, batch_seed = np.random.SeedSequence(config["seed"]).spawn(len(cells) + 1)
    rows, instances = [], []
    with (tqdm(total=len(cells) + len(batch), disable=not progress, desc="backends",
               unit="cell") as bar, warnings.catch_warnings()):
        warnings.simplefilter("ignore")  # the peers' numpy and scipy warnings
        for cell, ss in zip(cells, seeds, strict=True):
            got = _single_cell(np.random.default_rng(ss), *cell, config)
            rows += got[0]
            instances += got[1]
            bar.update()
        problems = _batch_problems(np.random.default_rng(batch_seed), config)
        for n, N, crit in batch:
            rows += _batch_cell(*problems[n, N], crit, config)
            bar.update()
    return rows, instances


def _single_cell(rng, mode, n, N, crit, kind, config) -> tuple[list[dict], list[dict]]:
    """The problems of one (n, N, criterion, kind), solved by every solver of the mode."""
    large = mode == "large"
    K = config["large_instances" if large else "instances"]
    problems = [(rng.standard_normal((N, n)), instance(rng, N, n, kind)) for _ in range(K)]
    solvers = (_solvers(config["large_backends"], (), N, more=False) if large
               else _solvers(config["backends"], config["peers"], N))
    runs = _loop(problems, crit, solvers, mode, config, first=kind == config["kinds"][0])
    where = {"n": n, "N": N, "criterion": crit, "kind": kind}
    gaps = _accuracy(np.stack([c for _, c in problems]), [r.weights for r in runs], crit)
    parts = _part_rows(problems, crit, where) if not large and "newton" in config["backends"] \
        else []
    return _rows(runs, gaps, where) + parts, _instance_rows(runs, gaps, where)


def _loop(problems, crit, solvers, mode, config, first) -> list[_Runs]:
    """The runs of each solver on problems (means (N, n), covs (N, n, n)), each solved by
    every solver in turn, in an order drawn anew for each problem (seeded by its index):
    the first call after another solver's finds cold caches (measured: 2.5x the time of
    the next for newton at n = 4 after Clarabel), and how cold depends on that solver. A
    rotation of one fixed order, as before 2026-11-27, gave each solver the same
    predecessor on every problem: fo.bci "closed-form" always followed fo.ci "newton", which
    runs the same compiled code, and came out 1.2 times faster than fo.bci "newton", which
    always followed the fast-ci peer. With `first`, one more call on the first problem,
    reported apart (the shape's first call)."""
    runs = [_Runs(s, mode) for s in solvers]
    for k, (means, covs) in enumerate(problems):
        for i in np.random.default_rng(k).permutation(len(runs)):
            _solve(runs[i], means, covs, crit, config, first=first and k == 0)
    return runs


def _solve(runs: _Runs, means, covs, crit, config, first) -> None:
    """Timed calls of runs.solver on one problem (after one more, the shape's first, when
    `first`): `repeats` of them, or as many as fit in repeat_budget_ms (at least one)."""
    s = runs.solver
    data = (means[0], covs[0], means[1], covs[1]) if s.pair else (means, covs)
    kwargs = {"criterion": crit, **s.kwargs}
    try:
        if first:
            runs.first = _timed(s.fn, *data, **kwargs)[0]
        with _own_times(s.backend) as own:
            t, result = _timed(s.fn, *data, **kwargs)
            times = [t]
            budget = 1e-3 * config["repeat_budget_ms"]
            while len(times) < config["repeats"] and sum(times) + t <= budget:
                times.append(_timed(s.fn, *data, **kwargs)[0])
    except Exception as exc:  # noqa: BLE001 (a failure is what we count)
        runs.fail(f"{type(exc).__name__}: {exc}", len(covs))
        return
    runs.times += times
    runs.own += own if len(own) == len(times) else [np.nan] * len(times)
    runs.problem_times.append(float(np.median(times)))
    w, ok = s.outcome(result)
    runs.weights.append(w)
    runs.failed.append(not ok)
    if not ok:
        status = getattr(result, "status", None)
        runs.first_failure = runs.first_failure or (
            f"status {status.value}" if status is not None else "no success")


def _part_rows(problems, crit, where) -> list[dict]:
    """newton's time by part on one cell's problems (`_part_times`): a row per part with
    the median over the problems of the CPU time per call."""
    times = np.array([_part_times_or_nan(means, covs, crit) for means, covs in problems])
    return [{**dict.fromkeys(COLUMNS, np.nan), "mode": "parts", "call": name,
             "backend": "newton", **where, "per_call": 1, "solves": len(t) * PART_CALLS,
             "median_ms": 1e3 * _q(t, 50), "p90_ms": 1e3 * _q(t, 90), "failures": 0,
             "first_failure": ""} for name, t in zip(PART_NAMES, times.T, strict=True)]


def _part_times_or_nan(means, covs, crit) -> list[float]:
    """`_part_times`, or NaN for each part of a problem fo.bci refuses (the rotation of
    `_loop` counts that failure already)."""
    try:
        return _part_times(means, covs, crit)
    except Exception:  # noqa: BLE001 (a failure is counted where the user's call is timed)
        return [np.nan] * len(PART_NAMES)


def _part_times(means, covs, crit) -> list[float]:
    """CPU seconds per call of the PART_NAMES of fo.bci newton on one problem (means (N, n),
    covs (N, n, n)): the whole call and, apart, the three parts of its compiled call
    (`fuse_exact`): `prepare`'s checks and factors, the weight solve, and the assembly of
    the fused estimate and its certificate (which inside `fuse_exact` reuses the solve's
    last QR, so apart it costs a little more). Each is called PART_CALLS times in a row
    after an untimed call (warm caches, unlike the rotation of `_loop`), on arrays of the
    types fo.bci passes (`core._Arrays`, the core's read-only unit scales), so that what is
    timed is the code compiled for fo.bci, not another specialisation."""
    N, n = means.shape
    trace = crit == "trace"
    a, (q, E) = core._Arrays(1, N, n), core._unit_scales(1, N)
    M, C = means[None].copy(), covs[None].copy()
    calls = (lambda: fo.bci(means, covs, crit, "newton"),
             lambda: prepare(M, C, q, E, a.F, a.k, a.vertex, a.pnorm, a.where),
             lambda: newton.solve(a.F, trace, a.W, False, a.W, a.rel, a.iters),
             lambda: assemble(a.F, M, C, q, E, a.k, a.vertex, a.pnorm, a.W, trace, a.mean,
                              a.cov, a.stats))
    times = []
    for call in calls:  # in this order: each part reads what the one before it wrote
        call()
        times.append(_timed(_repeat, call)[0] / PART_CALLS)
    return times


def _repeat(call, times: int = PART_CALLS) -> None:
    for _ in range(times):
        call()


def _timed(call, *args, **kwargs):
    """(CPU seconds, result) of one call(*args, **kwargs). The garbage collector is held
    off during the call, as timeit does, so that a collection of another solver's garbage
    (CVXPY makes much) is not charged to this one."""
    gc.disable()
    try:
        t = time.process_time()
        r = call(*args, **kwargs)
        return time.process_time() - t, r
    finally:
        gc.enable()


@contextmanager
def _own_times(backend):
    """A list that receives the solver's own time (s) of each call of REGISTRY[backend]
    made inside the block (empty for a native backend or a peer, which report none). The
    wrapper costs one Python call, well under a microsecond against calls of
    milliseconds."""
    seen = []
    inner = REGISTRY.get(backend)
    if inner is None:
        yield seen
        return

    def solve(Ys, M, criterion):
        sol = inner(Ys, M, criterion)
        native = sol.solver_time in (None, sol.solve_time)  # SLSQP: no time of its own
        seen.append(np.nan if native else sol.solver_time)
        return sol

    REGISTRY[backend] = solve
    try:
        yield seen
    finally:
        REGISTRY[backend] = inner


def _batch_problems(rng, config) -> dict:
    """{(n, N): (means (B, N, n), covs (B, N, n, n))}: batch_size random problems per
    shape of batch_shapes."""
    B = config["batch_size"]
    return {(n, N): (rng.standard_normal((B, N, n)),
                     instance(rng, B * N, n, "random").reshape(B, N, n, n))
            for n, N in config["batch_shapes"]}


def _batch_cell(means, covs, crit, config) -> list[dict]:
    """fuse_batch over all B problems and over the first batch_small (as many problems in
    all: B / batch_small calls a turn) with each native backend, and the batched-inverse
    floor, timed in turns, batch_repeats turns (a slow spell of the machine then falls on
    every one of them, not on one side of a ratio: a run that timed fuse_batch's repeats
    first and the floor's after gave 16.5x for one criterion and 8.5x for the other, 9.5x
    and 7.8x measured again); then loops of every backend's fo.bci on batch_check of the
    problems; gaps on those."""
    B, N, n = covs.shape[:3]
    small = config["batch_small"]
    sample = np.arange(config["batch_check"])  # the problems are independent draws
    natives = [b for b in config["backends"] if b in EXACT and (b != "closed-form" or N == 2)]
    timers = [_batched(means, covs, crit, b, sample, "batch", 1) for b in natives]
    timers += [_batched(means[:small], covs[:small], crit, b, sample, "batch-small",
                        B // small) for b in natives]
    timers.append(_inverse_floor(covs))
    for _ in range(config["batch_repeats"]):
        for _runs, turn in timers:
            turn()
    runs = [r for r, _ in timers]
    runs += _loop([(means[i], covs[i]) for i in sample], crit,
                  _solvers(config["backends"], (), N, more=False), "loop", config, first=False)
    return _rows(runs, _accuracy(covs[sample], [r.weights for r in runs], crit),
                 {"n": n, "N": N, "criterion": crit, "kind": f"random B={B}"})


def _batched(means, covs, crit, backend, sample, mode, calls):
    """(runs, turn): fuse_batch of all the problems given, after an untimed call of
    FIRST_BATCH problems; each turn() times `calls` calls; the weights of the problems in
    `sample` kept (NaN for those not in the batch), and a failure counted, from the last
    call (turns after a failure time nothing)."""
    B = len(means)
    runs = _Runs(_Solver("fo.fuse_batch", backend, fo.fuse_batch), mode, per_call=B)
    runs.weights = list(np.full((len(sample), covs.shape[1]), np.nan))

    def failed(exc: Exception) -> None:
        runs.failed, runs.first_failure = [True] * B, f"{type(exc).__name__}: {exc}"

    def turn() -> None:
        if runs.first_failure:
            return
        try:
            for _ in range(calls):
                t, r = _timed(fo.fuse_batch, means, covs, "bci", crit, backend)
                runs.times.append(t / B)
                runs.own.append(np.nan)
        except Exception as exc:  # noqa: BLE001 (a failure is what we count)
            failed(exc)
            return
        held = sample[sample < B]
        runs.weights[:len(held)] = list(r.weights[held])
        runs.failed = list(r.status != fo.Status.OPTIMAL)
        bad = np.flatnonzero(runs.failed)
        if len(bad):
            runs.first_failure = f"problem {bad[0]}: status {r.status[bad[0]].value}"

    try:
        fo.fuse_batch(means[:FIRST_BATCH], covs[:FIRST_BATCH], "bci", crit, backend)
    except Exception as exc:  # noqa: BLE001
        failed(exc)
    return runs, turn


def _inverse_floor(covs):
    """(runs, turn): CPU time per problem of one np.linalg.inv of all the stacked
    covariances, a call a turn: the least a batched fusion must spend to read its nodes'
    informations."""
    runs = _Runs(_Solver("np.linalg.inv", "numpy", np.linalg.inv), "inverse",
                 per_call=len(covs))
    np.linalg.inv(covs[:FIRST_BATCH])

    def turn() -> None:
        runs.times.append(_timed(np.linalg.inv, covs)[0] / len(covs))
        runs.own.append(np.nan)

    return runs, turn


# ------------------------------------------------------------------------- accuracy

def _accuracy(covs, weights: list, crit) -> list[tuple]:
    """(objective gaps, relative certificates, simplex violations), each (K,), of each of
    weights, a list of (K, N) arrays (NaN rows where a solver raised), on problems covs
    (K, N, n, n): the gaps of the module docstring, by numpy on the congruence-scaled
    problems, at the weights put on the simplex (negatives to 0, divided by their sum):
    SLSQP meets sum w = 1 only to its tolerance, and weights summing to more than one
    fuse more information than there is, which would look better than the optimum.
    The violation is |sum w - 1| + max(0, -min w) of the weights as returned. An empty
    weights list (a solver that keeps none) gives NaN."""
    Ys, M = (np.stack(a) for a in zip(*(conic_problem(c) for c in covs), strict=True))
    scale = np.abs if crit == "trace" else np.ones_like  # relative for trace only
    f, cert, violation = [], [], []
    for W in weights:
        W = np.asarray(W, dtype=float).reshape(len(covs), -1) if len(W) else \
            np.full(covs.shape[:2], np.nan)
        V = np.clip(W, 0.0, None)
        total = V.sum(-1, keepdims=True)
        ok = np.isfinite(W).all(-1) & (total[:, 0] > 0)
        V = np.where(ok[:, None], V / np.where(ok[:, None], total, 1.0), 1.0 / W.shape[1])
        ev = criteria.evaluate(Ys, V, crit, M)
        f.append(np.where(ok, ev.f, np.nan))
        cert.append(np.where(ok, criteria.gap(ev.g, V) / scale(ev.f), np.nan))
        violation.append(np.abs(W.sum(-1) - 1) + np.maximum(0.0, -W.min(-1)))
    best = np.fmin.reduce(f)  # NaN only where every solver raised
    return [((fb - best) / scale(best), c, v)
            for fb, c, v in zip(f, cert, violation, strict=True)]


def _rows(runs: list[_Runs], gaps: list, where: dict) -> list[dict]:
    """One CSV row per runs of a cell, with their gaps (of `_accuracy`)."""
    rows = []
    for r, (objective_gap, optimality_gap, violation) in zip(runs, gaps, strict=True):
        times, own = np.array(r.times) * 1e3, np.array(r.own) * 1e3
        rows.append({
            "mode": r.mode, "call": r.solver.call, "backend": r.solver.backend, **where,
            "per_call": r.per_call, "solves": len(times) * r.per_call,
            "first_ms": r.first * 1e3,
            "median_ms": _q(times, 50), "p90_ms": _q(times, 90),
            "solver_own_median_ms": _q(own, 50), "overhead_median_ms": _q(times - own, 50),
            "worst_objective_gap": _worst(objective_gap),
            "worst_optimality_gap": _worst(optimality_gap),
            "worst_simplex_violation": _worst(violation),
            "failures": int(np.sum(r.failed)), "first_failure": r.first_failure})
    return rows


def _instance_rows(runs: list[_Runs], gaps: list, where: dict) -> list[dict]:
    """One CSV row per solver and problem of a cell, with their gaps (of `_accuracy`)."""
    return [{"mode": r.mode, "call": r.solver.call, "backend": r.solver.backend, **where,
             "problem": k, "time_ms": 1e3 * r.problem_times[k],
             "objective_gap": objective_gap[k], "optimality_gap": optimality_gap[k],
             "failed": int(r.failed[k])}
            for r, (objective_gap, optimality_gap, _) in zip(runs, gaps, strict=True)
            for k in range(len(objective_gap))]
