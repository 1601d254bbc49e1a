"""Benchmark of the weight solvers against each other and against the peers a user would
otherwise use: time, accuracy and certificate per solver and shape, and the issue's targets.

For every (n, N, criterion, kind) of the config, `instances` seeded problems (kind "random":
P_i = A A^T / n + 0.01 I with A standard normal; "ill-conditioned": eigenvalues log-uniform
over 1e-6..1e6 in a random rotation, each node scaled by 10^U(-3, 3)) are solved by every
solver in turn (starting from another on each problem, `_loop`), in one process. A solver
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
kernel_load_s of machine.json). solver_own_median_ms is the time the solver itself reports
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

Then the `large` shapes (n = 48, N = 8) with large_backends only; and, per shape of
batch_shapes, `fo.fuse_batch` of batch_size random problems with each native backend (one
call, CPU time / B), of the first batch_small of them, the batched-inverse floor (one
`np.linalg.inv` of the stacked (B, N, n, n) covariances, per problem), and loops of fo.bci
on batch_check of them, on which the gaps are computed. Writes backends.csv (a row per
solver and cell), backends_instances.csv (a row per solver and problem), backends.md
with a CSV beside it for each of its tables (backends_<table>.csv),
backends_time_vs_N.png, backends_profile.png and machine.json; `report` rebuilds every
table and figure from the two measurement CSVs.
"""

from __future__ import annotations

import csv
import gc
import json
import platform
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.optimize import minimize, minimize_scalar

import fusion_opt as fo
from fusion_opt import criteria, programs
from fusion_opt.backends import EXACT, REGISTRY, clarabel_direct
from fusion_opt.scaling import conic_problem

from . import config as configs
from . import meta, plotting

COLUMNS = ("mode", "call", "backend", "n", "N", "criterion", "kind", "per_call", "solves",
           "first_ms", "median_ms", "p90_ms", "solver_own_median_ms", "overhead_median_ms",
           "worst_objective_gap", "worst_optimality_gap", "worst_simplex_violation",
           "failures", "first_failure")
INSTANCE_COLUMNS = ("mode", "call", "backend", "n", "N", "criterion", "kind", "problem",
                    "time_ms", "objective_gap", "optimality_gap", "failed")
BCI, CI, RAW = "fo.bci", "fo.ci", "fo.fuse(polish=False)"
PEERS = ("minimize_scalar", "scipy-slsqp", "fixed-weights", "fast-ci")
REFERENCE = "newton"  # the backend whose speed-up over the others backends.md reports
FIRST_BATCH = 10  # problems of the untimed first fuse_batch call (loads, allocates)
ROUNDING = 1e-12  # objective gaps within this are equal (relative; nats for logdet)
CERTIFIED = 1e-10  # Status.OPTIMAL's bound on the relative certificate


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
    if config["batch_small"] > config["batch_size"]:
        raise configs.ConfigError(f"batch_small must be <= batch_size "
                                  f"({config['batch_size']}), got {config['batch_small']}")
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
    if set(config["backends"]) == {"closed-form"} and 2 not in config["N"]:
        raise configs.ConfigError(f"backends ['closed-form'] fuses N = 2 only, which N = "
                                  f"{config['N']} does not hold: nothing would be measured")


def _check_shapes(key: str, shapes) -> None:
    """shapes: a list of distinct [n, N] with n >= 1 and N >= 2 (empty: none run)."""
    if not isinstance(shapes, list):
        raise configs.ConfigError(f"{key} must be a list of [n, N], got {shapes!r}")
    for i, shape in enumerate(shapes):
        if not isinstance(shape, list) or len(shape) != 2:
            raise configs.ConfigError(f"{key}[{i}] must be a list [n, N], got {shape!r}")
        configs.integer(f"{key}[{i}][0] (n)", shape[0], low=1)
        configs.integer(f"{key}[{i}][1] (N)", shape[1], low=2)
    if len({tuple(s) for s in shapes}) != len(shapes):
        raise configs.ConfigError(f"{key} lists a shape more than once: {shapes!r}")


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
    rows, instances = _measure(config, progress)
    _write_csv(out_dir / "backends.csv", COLUMNS, rows)
    _write_csv(out_dir / "backends_instances.csv", INSTANCE_COLUMNS, instances)
    info = {"versions": meta.versions(), "machine": meta.machine(),
            "git_commit": meta.git_commit(), "numpy_config": _blas(),
            "python": platform.python_implementation(), "quick": quick,
            "kernel_load_s": load, "measure_wall_time_s": time.perf_counter() - t0,
            "config": config}
    (out_dir / "machine.json").write_text(json.dumps(info, indent=2, default=str))
    report(config, out_dir, quick=quick)


def report(config: dict, out_dir: Path, *, quick: bool) -> None:
    """Rebuild backends.md, its table CSVs and the figures from backends.csv and
    backends_instances.csv (no new measurement)."""
    out_dir = Path(out_dir)
    rows = _read_csv(out_dir / "backends.csv")
    instances = _read_csv(out_dir / "backends_instances.csv")
    sections = _sections(rows, instances, config, quick, _kernel_load(out_dir))
    lines = []
    for part in sections:
        if isinstance(part, _Table):
            lines += part.markdown()
            _write_csv(out_dir / f"backends_{part.name}.csv", part.header, part.rows,
                       plain=True)
        else:
            lines += part
    (out_dir / "backends.md").write_text("\n".join(lines) + "\n")
    _time_figure(rows, config, out_dir / "backends_time_vs_N.png")
    _profile_figure(instances, config, out_dir / "backends_profile.png")


def _write_csv(path: Path, columns, rows, plain: bool = False) -> None:
    """rows (dicts, or lists in the order of columns when plain) as CSV at path."""
    with open(path, "w", newline="") as fh:
        if plain:
            writer = csv.writer(fh)
            writer.writerow(columns)
        else:
            writer = csv.DictWriter(fh, fieldnames=columns)
            writer.writeheader()
        writer.writerows(rows)


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def _number(text: str):
    """A CSV cell back as the int, float or string it was written from."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _kernel_load(out_dir: Path) -> float:
    """kernel_load_s of the run's machine.json (NaN if there is none)."""
    try:
        return float(json.loads((out_dir / "machine.json").read_text())["kernel_load_s"])
    except (OSError, ValueError, KeyError, TypeError):
        return np.nan


def _blas() -> str:
    import numpy

    cfg = numpy.show_config(mode="dicts")["Build Dependencies"]
    return f"{cfg['blas'].get('name')} {cfg['blas'].get('version')}"


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


# ------------------------------------------------------------------------------ peers

class PeerResult(NamedTuple):
    """What a peer gives: weights (N,), fused mean (n,) and cov (n, n), and whether its
    optimiser reported success."""

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    ok: bool


def _user_objective(criterion: str) -> Callable:
    """f(Y) of the fused information Y, written the way a user writes it: the inverse,
    then its trace or log det."""
    if criterion == "trace":
        return lambda Y: np.trace(np.linalg.inv(Y))
    return lambda Y: np.linalg.slogdet(np.linalg.inv(Y))[1]


def _peer_result(w, Ys, means, ok) -> PeerResult:
    """The fused estimate at weights w (N,) of informations Ys (N, n, n), means (N, n)."""
    P = np.linalg.inv(np.tensordot(w, Ys, 1))
    return PeerResult(w, P @ np.einsum("i,ijk,ik->j", w, Ys, means), P, ok)


def minimize_scalar_peer(m_a, P_a, m_b, P_b, criterion) -> PeerResult:
    """Pairwise CI by scipy's bounded scalar minimiser on w in [0, 1] (default tolerance)."""
    Y_a, Y_b = np.linalg.inv(P_a), np.linalg.inv(P_b)
    f = _user_objective(criterion)
    res = minimize_scalar(lambda w: f(w * Y_a + (1 - w) * Y_b), bounds=(0, 1),
                          method="bounded")
    return _peer_result(np.array([res.x, 1 - res.x]), np.stack([Y_a, Y_b]),
                        np.stack([m_a, m_b]), bool(res.success))


def slsqp_peer(means, covs, criterion) -> PeerResult:
    """BCI by scipy's SLSQP from uniform weights, sum w = 1 and 0 <= w_i <= 1, default
    options, finite-difference gradient."""
    Ys = np.linalg.inv(covs)
    N, f = len(covs), _user_objective(criterion)
    res = minimize(lambda w: f(np.tensordot(w, Ys, 1)), np.full(N, 1.0 / N),
                   method="SLSQP", bounds=[(0.0, 1.0)] * N,
                   constraints={"type": "eq", "fun": lambda w: w.sum() - 1.0})
    return _peer_result(res.x, Ys, means, bool(res.success))


def fixed_weights_peer(means, covs, criterion) -> PeerResult:
    """CI with w_i = 1/N (for a pair, Stone Soup's default omega = 0.5)."""
    return _peer_result(np.full(len(covs), 1.0 / len(covs)), np.linalg.inv(covs), means,
                        True)


def fast_ci_peer(means, covs, criterion):
    """Fast CI (Niehsen 2002) as fusion-opt offers it."""
    return fo.fuse(means, covs, "fast-ci", criterion)


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
    return _rows(runs, gaps, where), _instance_rows(runs, gaps, where)


def _loop(problems, crit, solvers, mode, config, first) -> list[_Runs]:
    """The runs of each solver on problems (means (N, n), covs (N, n, n)), each solved by
    every solver in turn, from the k-th solver on the k-th problem: the first call after
    another solver's finds cold caches (measured: 2.5x the time of the next for newton
    at n = 4 after Clarabel), and rotating shares that cost out evenly. With `first`, one
    more call on the first problem, reported apart (the shape's first call)."""
    runs = [_Runs(s, mode) for s in solvers]
    for k, (means, covs) in enumerate(problems):
        start = k % len(runs)
        for r in runs[start:] + runs[:start]:
            _solve(r, means, covs, crit, config, first=first and k == 0)
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
    all: repeats x B / batch_small calls) with each native backend, the batched-inverse
    floor, and loops of every backend's fo.bci on batch_check of the problems; gaps on
    those."""
    B, N, n = covs.shape[:3]
    small = config["batch_small"]
    sample = np.arange(min(B, config["batch_check"]))  # the problems are independent draws
    natives = [b for b in config["backends"] if b in EXACT and (b != "closed-form" or N == 2)]
    repeats = config["batch_repeats"]
    runs = [_batched(means, covs, crit, b, repeats, sample, "batch") for b in natives]
    runs += [_batched(means[:small], covs[:small], crit, b, repeats * B // small, sample,
                      "batch-small") for b in natives]
    runs.append(_inverse_floor(covs, repeats))
    runs += _loop([(means[i], covs[i]) for i in sample], crit,
                  _solvers(config["backends"], (), N, more=False), "loop", config, first=False)
    return _rows(runs, _accuracy(covs[sample], [r.weights for r in runs], crit),
                 {"n": n, "N": N, "criterion": crit, "kind": f"random B={B}"})


def _batched(means, covs, crit, backend, repeats, sample, mode) -> _Runs:
    """fuse_batch of all the problems given, `repeats` timed calls after an untimed one
    of FIRST_BATCH problems; the weights of the problems in `sample` kept (NaN for those
    not in the batch)."""
    B = len(means)
    runs = _Runs(_Solver("fo.fuse_batch", backend, fo.fuse_batch), mode, per_call=B)
    runs.weights = list(np.full((len(sample), covs.shape[1]), np.nan))
    try:
        fo.fuse_batch(means[:FIRST_BATCH], covs[:FIRST_BATCH], "bci", crit, backend)
        for _ in range(repeats):
            t, r = _timed(fo.fuse_batch, means, covs, "bci", crit, backend)
            runs.times.append(t / B)
    except Exception as exc:  # noqa: BLE001 (a failure is what we count)
        runs.failed, runs.first_failure = [True] * B, f"{type(exc).__name__}: {exc}"
        return runs
    runs.own = [np.nan] * repeats
    held = sample[sample < B]
    runs.weights[:len(held)] = list(r.weights[held])
    runs.failed = list(r.status != fo.Status.OPTIMAL)
    bad = np.flatnonzero(runs.failed)
    runs.first_failure = f"problem {bad[0]}: status {r.status[bad[0]].value}" if len(bad) \
        else ""
    return runs


def _inverse_floor(covs, repeats) -> _Runs:
    """CPU time per problem of one np.linalg.inv of all the stacked covariances: the
    least a batched fusion must spend to read its nodes' informations."""
    runs = _Runs(_Solver("np.linalg.inv", "numpy", np.linalg.inv), "inverse",
                 per_call=len(covs))
    np.linalg.inv(covs[:FIRST_BATCH])
    runs.times = [_timed(np.linalg.inv, covs)[0] / len(covs) for _ in range(repeats)]
    runs.own = [np.nan] * repeats
    return runs


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


def _q(values, q) -> float:
    """The q-th percentile of the finite values (NaN if there is none)."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else np.nan


def _worst(values) -> float:
    """The largest finite value (NaN if there is none)."""
    return _q(values, 100)


# ----------------------------------------------------------------- profile, targets

def performance_profile(times: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """Dolan-More performance profile: times (P, S) of S solvers on P problems (inf where
    a solver failed or did not run) -> rho (S, len(taus)), the fraction of the P problems
    each solver solved within tau times the least time any solver took on the problem
    (a problem no solver solved counts as unsolved by all)."""
    times = np.asarray(times, dtype=float)
    best = times.min(axis=1, keepdims=True)
    ratio = np.where(np.isfinite(best), times / np.where(np.isfinite(best), best, 1.0),
                     np.inf)
    return (ratio[:, :, None] <= np.asarray(taus)[None, None, :]).mean(axis=0)


def profile_times(instances: list[dict], tolerance: float) -> tuple[list[str], np.ndarray]:
    """(labels, times (P, S)) of the user's calls (fo.bci and the peers) on the problems
    of the grid: a solver's time where it did not fail and its objective gap is within
    tolerance, inf otherwise (and where it did not run)."""
    rows = [r for r in instances if r["mode"] == "single" and r["call"] != CI
            and r["call"] != RAW]
    labels = list(dict.fromkeys(_label(r) for r in rows))
    keys = list(dict.fromkeys(_problem(r) for r in rows))
    index, col = {k: i for i, k in enumerate(keys)}, {s: j for j, s in enumerate(labels)}
    times = np.full((len(keys), len(labels)), np.inf)
    for r in rows:
        if not r["failed"] and r["objective_gap"] <= tolerance:
            times[index[_problem(r)], col[_label(r)]] = r["time_ms"]
    return labels, times


def _problem(r) -> tuple:
    return r["n"], r["N"], r["criterion"], r["kind"], r["problem"]


def _label(r) -> str:
    """A solver's name in tables and figures: the backend for fo.bci, the call for a
    peer, and "backend (fo.ci)" or "backend (polish=False)" for the other calls."""
    if r["call"] == BCI or r["call"] == "fo.fuse_batch":
        return r["backend"]
    if r["call"] == CI:
        return f"{r['backend']} (fo.ci)"
    if r["call"] == RAW:
        return f"{r['backend']} (polish=False)"
    return r["call"]


def targets(rows: list[dict], instances: list[dict]) -> list[list[str]]:
    """[target, measured, "met" / "missed" / "not measured"] for each target of issue 11,
    from the rows of backends.csv and backends_instances.csv."""
    return [_target_clarabel(rows), _target_pairs(rows, instances), *_target_batch(rows),
            _target_large(rows), _target_exact(rows)]


def _verdict(target: str, measured: list[str], ok: list[bool]) -> list[str]:
    if not ok:
        return [target, "not measured in this run", "not measured"]
    return [target, "; ".join(measured), "met" if all(ok) else "missed"]


def _ratios(rows, mode, slow: tuple, fast: tuple, keep=lambda key: True) -> dict:
    """{(n, N, criterion): pooled median time of solver slow over solver fast}, each
    given as (call, backend), on the cells of `mode` both ran in."""
    cells = _cells([r for r in rows if r["mode"] == mode])
    out = {key: _pooled(cell, slow, "median_ms") / _pooled(cell, fast, "median_ms")
           for key, cell in cells if keep(key)}
    return {key: x for key, x in out.items() if np.isfinite(x)}


def _target_clarabel(rows) -> list[str]:
    r = _ratios(rows, "single", (BCI, "clarabel"), (BCI, "newton"), lambda k: k[0] <= 6)
    target = "fo.bci newton >= 100x faster than fo.bci clarabel at every grid point n <= 6"
    if not r:
        return _verdict(target, [], [])
    worst = min(r, key=r.get)
    return _verdict(target, [f"worst {r[worst]:.3g}x at (n, N) = ({worst[0]}, {worst[1]}) "
                             f"{worst[2]}", f"{sum(x >= 100 for x in r.values())} of "
                             f"{len(r)} points >= 100x"], [x >= 100 for x in r.values()])


def _target_pairs(rows, instances) -> list[str]:
    r = _ratios(rows, "single", ("minimize_scalar", "-"), (CI, "closed-form"),
                lambda k: k[:2] == (4, 2))
    worse = _excess_over(instances, (CI, "closed-form"), ("minimize_scalar", "-"))
    measured = [f"{k[2]} {x:.3g}x" for k, x in r.items()]
    if len(worse):
        measured.append(f"objective worse than minimize_scalar's by more than {ROUNDING:g} "
                        f"on {int(np.sum(worse > ROUNDING))} of {len(worse)} pair problems "
                        f"(largest excess {np.max(worse):.2g})")
    ok = [x >= 10 for x in r.values()] + ([bool(np.all(worse <= ROUNDING))] if r else [])
    return _verdict("fo.ci closed-form at n = 4 >= 10x faster than minimize_scalar, "
                    "objective never worse", measured, ok)


def _excess_over(instances, solver: tuple, peer: tuple) -> np.ndarray:
    """objective gap of solver minus that of peer on every grid problem both solved."""
    gap = {s: {_problem(r): r["objective_gap"] for r in instances if r["mode"] == "single"
               and (r["call"], r["backend"]) == s and not r["failed"]} for s in (solver, peer)}
    both = [k for k in gap[solver] if k in gap[peer]]
    return np.array([gap[solver][k] - gap[peer][k] for k in both])


def _target_batch(rows) -> list[list[str]]:
    at = {c: [r for r in rows if (r["n"], r["N"], r["criterion"]) == (4, 3, c)]
          for c in ("trace", "logdet")}
    at = {c: cell for c, cell in at.items() if np.isfinite(_one(cell, "batch", REFERENCE))}
    floor = {c: _one(cell, "batch", REFERENCE) / _one(cell, "inverse", "numpy")
             for c, cell in at.items()}
    small = {c: _one(cell, "batch-small", REFERENCE) / _one(cell, "batch", REFERENCE)
             for c, cell in at.items()}
    B = {m: {_one(cell, m, b, "per_call") for cell in at.values()}
         for m, b in (("batch", REFERENCE), ("batch-small", REFERENCE))}
    at_B = [f"at B = {', '.join(map(str, sorted(B['batch'])))}"] if at else []
    at_small = [f"at B = {', '.join(map(str, sorted(B['batch-small'])))}"] if at else []
    return [_verdict("fuse_batch newton at (n, N) = (4, 3), B = 10^4: <= 15x the batched-"
                     "inverse floor per problem",
                     at_B + [f"{c} {x:.3g}x" for c, x in floor.items()],
                     [x <= 15 for x in floor.values()]),
            _verdict("fuse_batch newton at (4, 3): per problem at B = 10 no more than 3x "
                     "that at B = 10^4", at_small + [f"{c} {x:.3g}x" for c, x in small.items()],
                     [x <= 3 for x in small.values()])]


def _target_large(rows) -> list[str]:
    r = _ratios(rows, "large", (BCI, "clarabel"), (BCI, "newton"), lambda k: k[:2] == (48, 8))
    return _verdict("fo.bci newton at n = 48, N = 8 >= 50x faster than fo.bci clarabel",
                    [f"{k[2]} {x:.3g}x" for k, x in r.items()], [x >= 50 for x in r.values()])


def _target_exact(rows) -> list[str]:
    got = [r for r in rows if r["backend"] in EXACT and r["mode"] in
           ("single", "large", "batch", "loop")]
    if not got:
        return _verdict("newton, closed-form exact and certified", [], [])
    objective = _worst([r["worst_objective_gap"] for r in got])
    certificate = _worst([r["worst_optimality_gap"] for r in got])
    failures = sum(r["failures"] for r in got)
    return _verdict(
        f"newton and closed-form objectives within {ROUNDING:g} of the best solver's; "
        f"every result certified (relative certificate <= {CERTIFIED:g})",
        [f"worst objective gap {objective:.2g}", f"worst certificate {certificate:.2g}",
         f"{failures} results of fo.bci, fo.ci or fuse_batch not certified optimal"],
        [objective <= ROUNDING, certificate <= CERTIFIED, failures == 0])


# ------------------------------------------------------------------------- the report

@dataclass
class _Table:
    """A table of backends.md, also written as backends_<name>.csv."""

    name: str
    header: list
    rows: list

    def markdown(self) -> list[str]:
        if not self.rows:
            return ["Not measured in this run."]
        return ["| " + " | ".join(self.header) + " |", "|" + "---|" * len(self.header),
                *("| " + " | ".join(map(str, row)) + " |" for row in self.rows)]


def _sections(rows, instances, config, quick, kernel_load) -> list:
    """backends.md as a list of text blocks (lists of lines) and _Tables."""
    single = [r for r in rows if r["mode"] == "single"]
    grid = len({_problem(r) for r in instances if r["mode"] == "single"})
    return [
        [f"# Backend benchmark{' (quick)' if quick else ''}", "",
         f"{config['instances']} seeded problems per (n, N, criterion, kind), kinds "
         f"{', '.join(config['kinds'])} ({grid} in all). Every solver solves each problem "
         "in turn, in one process: each backend's fo.bci (the user's call, default "
         "options) and, for pairs, fo.ci; fo.fuse(polish=False) for the conic and SLSQP "
         "backends (their own weights); the peers (minimize_scalar for pairs, scipy-slsqp, "
         f"fixed-weights, fast-ci). {config['repeats']} timed calls per problem and "
         f"solver, fewer (at least one) beyond {config['repeat_budget_ms']:g} ms. Times "
         "are CPU time (time.process_time, one BLAS thread). Everything below was measured "
         "by this run (studies/backends.py says how); the compiled kernels loaded in "
         f"{kernel_load:.3g} s before timing.", "", "## Targets (issue 11)", ""],
        _Table("targets", ["target", "measured", "verdict"], targets(rows, instances)),
        ["", "## Time per fusion, the user's call (ms)", "",
         "fo.bci per backend and each peer; median over the problems and calls of a cell, "
         "the mean of the kinds' medians.", ""],
        _time_table(single),
        ["", "![Time per fusion against N](backends_time_vs_N.png)", "",
         f"## Speed-up of {REFERENCE}", "", f"Median time of each over that of fo.bci "
         f"{REFERENCE}, both the user's call, on the same problems.", ""],
        _speedup_table(single),
        ["", "## Performance profile", "",
         f"Dolan-More profile of the user's calls over the {grid} problems: the fraction "
         "of problems a call solved (did not fail, objective within the tolerance of the "
         "best) within tau times the least CPU time any call took on that problem; "
         "closed-form and minimize_scalar solve pairs only.", "",
         "![Performance profile](backends_profile.png)", "",
         "## Pairs: fo.ci against minimize_scalar", "",
         "Median ms of fo.ci per backend and of the minimize_scalar peer; worst excess: "
         "the largest objective gap of fo.ci closed-form minus minimize_scalar's over the "
         "problems (negative: closed-form better on every problem).", ""],
        _pairs_table(single, instances),
        ["", "## Accuracy, failures and call costs (grid problems)", "",
         "Objective gap to the best solver per problem (relative for trace, nats for "
         "logdet; for the heuristics, their excess over the optimum) and the relative "
         "certificate of the returned weights, put on the simplex; their simplex "
         "violation as returned, |sum w - 1| + max(0, -min w); a failure is a call that "
         "raised, an fo result not certified optimal or a scipy result without success. "
         "First call: "
         "the first of each shape (n, N, criterion); overhead: the call's CPU time less "
         "the solver's own reported time (a wall time, so approximate), median per cell "
         "(n <= 6).", ""],
        _accuracy_table(single, instances), *_first_failures(single),
        ["", "## Large problems", "", f"{config['large_instances']} problem(s) per "
         "(shape, criterion, kind), fo.bci only; ratio: time over fo.bci newton's.", ""],
        _large_table([r for r in rows if r["mode"] == "large"]),
        ["", "## Batches: fo.fuse_batch, the inverse floor and loops of fo.bci", "",
         f"fo.fuse_batch of B = {config['batch_size']} random problems in one call and of "
         f"the first {config['batch_small']}, CPU time per problem; the floor: one "
         "np.linalg.inv of the stacked (B, N, n, n) covariances, per problem; loops of "
         f"fo.bci on {config['batch_check']} of the problems, on which the gaps are "
         "computed. Failures: problems not certified optimal.", ""],
        _batch_table([r for r in rows if r["mode"] not in ("single", "large")])]


def _user_solvers(rows) -> list[tuple]:
    """(call, backend) of fo.bci per backend then of each peer, in the order run."""
    return [s for s in dict.fromkeys((r["call"], r["backend"]) for r in rows)
            if s[0] not in (CI, RAW)]


def _time_table(single) -> _Table:
    solvers = _user_solvers(single)
    return _Table("time", ["n", "N", "criterion", *(_label(_key(s)) for s in solvers)],
                  [[*key, *(_fmt(_pooled(cell, s, "median_ms"), ".3g") for s in solvers)]
                   for key, cell in _cells(single)])


def _key(solver: tuple) -> dict:
    return {"call": solver[0], "backend": solver[1]}


def _speedup_table(single) -> _Table:
    ref = (BCI, REFERENCE)
    peers = [s for s in _user_solvers(single) if s != ref]
    table = _Table("speedup", ["n", "N", "criterion",
                               *(f"over {_label(_key(s))} (x)" for s in peers)], [])
    for key, cell in _cells(single):
        t = _pooled(cell, ref, "median_ms")
        table.rows.append([*key, *(_fmt(_pooled(cell, s, "median_ms") / t, ".3g")
                                   for s in peers)])
    return table


def _pairs_table(single, instances) -> _Table:
    pairs = [r for r in single if r["N"] == 2]
    solvers = [s for s in dict.fromkeys((r["call"], r["backend"]) for r in pairs)
               if s[0] == CI] + [("minimize_scalar", "-")]
    table = _Table("pairs", ["n", "criterion", *(f"{_label(_key(s))} ms" for s in solvers),
                             "minimize_scalar / closed-form fo.ci (x)",
                             "worst excess of closed-form over minimize_scalar"], [])
    for (n, _, crit), cell in _cells(pairs):
        mine = [r for r in instances if (r["n"], r["N"], r["criterion"]) == (n, 2, crit)]
        excess = _excess_over(mine, (CI, "closed-form"), ("minimize_scalar", "-"))
        ratio = _pooled(cell, solvers[-1], "median_ms") / _pooled(cell, (CI, "closed-form"),
                                                                     "median_ms")
        table.rows.append([n, crit, *(_fmt(_pooled(cell, s, "median_ms"), ".3g")
                                      for s in solvers), _fmt(ratio, ".3g"),
                           _fmt(_worst(excess), ".2g")])
    return table


def _accuracy_table(single, instances) -> _Table:
    table = _Table("accuracy", ["solver", "criterion", "timed calls", "failures",
                                "objective gap median", "p95", "worst",
                                "worst optimality gap", "worst simplex violation",
                                "first call ms (median / worst)",
                                "overhead ms (median / worst cell)"], [])
    grid = [r for r in instances if r["mode"] == "single"]
    for s in dict.fromkeys((r["call"], r["backend"]) for r in single):
        for crit in dict.fromkeys(r["criterion"] for r in single):
            got = [r for r in single if (r["call"], r["backend"], r["criterion"])
                   == (*s, crit)]
            if not got:
                continue
            gaps = [r["objective_gap"] for r in grid if (r["call"], r["backend"],
                    r["criterion"]) == (*s, crit)]
            first = [r["first_ms"] for r in got]
            over = [r["overhead_median_ms"] for r in got if r["n"] <= 6]
            table.rows.append([
                _label(_key(s)), crit, sum(r["solves"] for r in got),
                sum(r["failures"] for r in got), _fmt(_q(gaps, 50), ".2g"),
                _fmt(_q(gaps, 95), ".2g"), _fmt(_worst(gaps), ".2g"),
                _fmt(_worst([r["worst_optimality_gap"] for r in got]), ".2g"),
                _fmt(_worst([r["worst_simplex_violation"] for r in got]), ".2g"),
                _median_worst(first), _median_worst(over)])
    return table


def _first_failures(single) -> list[list[str]]:
    why = {}
    for r in single:
        if r["first_failure"]:
            why.setdefault(_label(r), f"- {_label(r)} at (n, N) = ({r['n']}, {r['N']}), "
                                      f"{r['criterion']}, {r['kind']}: {r['first_failure']}")
    return [["", "First failure of each solver that failed:", *why.values()]] if why else []


def _large_table(large) -> _Table:
    table = _Table("large", ["n", "N", "criterion", "solver", "median ms", "first call ms",
                             "ratio to newton (x)", "worst objective gap",
                             "worst optimality gap", "failures"], [])
    for key, cell in _cells(large):
        t = _pooled(cell, (BCI, REFERENCE), "median_ms")
        for s in dict.fromkeys((r["call"], r["backend"]) for r in cell):
            got = [r for r in cell if (r["call"], r["backend"]) == s]
            table.rows.append([
                *key, _label(_key(s)), _fmt(_pooled(cell, s, "median_ms"), ".3g"),
                _fmt(_worst([r["first_ms"] for r in got]), ".3g"),
                _fmt(_pooled(cell, s, "median_ms") / t, ".3g"),
                _fmt(_worst([r["worst_objective_gap"] for r in got]), ".2g"),
                _fmt(_worst([r["worst_optimality_gap"] for r in got]), ".2g"),
                sum(r["failures"] for r in got)])
    return table


def _batch_table(batch) -> _Table:
    table = _Table("batch", ["n", "N", "criterion", "call", "microseconds per fusion "
                             "(median / p90)", f"over fuse_batch {REFERENCE} (x)",
                             "over the inverse floor (x)", "worst objective gap",
                             "worst optimality gap", "failures"], [])
    names = {"batch": "fuse_batch B={B} {b}", "batch-small": "fuse_batch B={B} {b}",
             "inverse": "np.linalg.inv B={B} (floor)", "loop": "loop of {call} {b}"}
    for n, N, crit in dict.fromkeys((r["n"], r["N"], r["criterion"]) for r in batch):
        cell = [r for r in batch if (r["n"], r["N"], r["criterion"]) == (n, N, crit)]
        ref, floor = _one(cell, "batch", REFERENCE), _one(cell, "inverse", "numpy")
        for r in cell:
            table.rows.append([
                n, N, crit, names[r["mode"]].format(B=r["per_call"], b=r["backend"],
                                                  call=r["call"]),
                f"{_fmt(1e3 * r['median_ms'], '.3g')} / {_fmt(1e3 * r['p90_ms'], '.3g')}",
                _fmt(r["median_ms"] / ref, ".3g"), _fmt(r["median_ms"] / floor, ".3g"),
                _fmt(r["worst_objective_gap"], ".1e"), _fmt(r["worst_optimality_gap"], ".1e"),
                r["failures"]])
    return table


def _one(rows, mode, backend, key="median_ms") -> float:
    """key of the first row of mode and backend in rows (NaN if there is none)."""
    return next((r[key] for r in rows if (r["mode"], r["backend"]) == (mode, backend)),
                np.nan)


def _fmt(x, spec: str, unit: str = "") -> str:
    """x formatted, or "-" where nothing was measured (NaN)."""
    return f"{x:{spec}}{unit}" if np.isfinite(x) else "-"


def _median_worst(values) -> str:
    return f"{_q(values, 50):.3g} / {_worst(values):.3g}" if np.isfinite(values).any() \
        else "-"


def _cells(rows):
    """((n, N, criterion), rows of that cell over the kinds), in the order run."""
    keys = dict.fromkeys((r["n"], r["N"], r["criterion"]) for r in rows)
    return [(key, [r for r in rows if (r["n"], r["N"], r["criterion"]) == key])
            for key in keys]


def _pooled(cell, solver: tuple, key) -> float:
    """Mean over kinds of a per-kind statistic of solver (call, backend) (NaN if it did
    not run)."""
    vals = [r[key] for r in cell if (r["call"], r["backend"]) == solver
            and np.isfinite(r[key])]
    return float(np.mean(vals)) if vals else np.nan


# ------------------------------------------------------------------------ the figures

def _style(i: int, peer: bool) -> dict:
    """Colour, marker and line of the i-th solver: solid for backends, dashed for peers."""
    return {"color": f"C{i % 10}", "marker": "osx^vD<>ph"[i % 10], "ms": 4,
            "fillstyle": "none", "lw": 1, "ls": "--" if peer else "-"}


LEGEND = "solid: fusion-opt backends (fo.bci); dashed: peers"


def _time_figure(rows, config, path: Path) -> None:
    """Median CPU time of the user's call against N, a panel per (criterion, n): a colour
    and marker per solver (hollow, so that equal times stay visible), peers dashed; one
    legend below the panels."""
    single = [r for r in rows if r["mode"] == "single"]
    ns, crits = (list(dict.fromkeys(r[k] for r in single)) for k in ("n", "criterion"))
    solvers = _user_solvers(single)
    fig, axes = plotting.panels(len(crits), len(ns), 3.0 * len(ns), 2.6 * len(crits) + 1.2)
    lines = {}
    for (i, crit), (j, n) in ((a, b) for a in enumerate(crits) for b in enumerate(ns)):
        ax = axes[i * len(ns) + j]
        cells = _cells([r for r in single if (r["n"], r["criterion"]) == (n, crit)])
        for k, s in enumerate(solvers):
            pts = [(key[1], _pooled(cell, s, "median_ms")) for key, cell in cells]
            pts = [(N, t) for N, t in pts if np.isfinite(t)]
            if pts:
                lines[_label(_key(s))], = ax.plot(*zip(*pts, strict=True),
                                                  label=_label(_key(s)),
                                                  **_style(k, s[1] == "-"))
        plotting.log_axes(ax, sorted({key[1] for key, _ in cells}), "N (nodes)")
        ax.set_ylabel("CPU time per fusion (ms)", fontsize=8)
        ax.set_title(f"n = {n}, {crit}", fontsize=9)
    plotting.legend_below(fig, list(lines.values()), ncol=5, title=LEGEND, title_fontsize=8)
    fig.suptitle(f"Median CPU time of the user's call ({_count(single, config)} problems, "
                 f"seed {config['seed']})", fontsize=11)
    plotting.save(fig, path)


def _count(single, config) -> int:
    """How many problems the grid of single rows held."""
    return len({(r["n"], r["N"], r["criterion"], r["kind"]) for r in single}) \
        * config["instances"]


def _profile_figure(instances, config, path: Path) -> None:
    """The performance profile of the user's calls, a panel per profile tolerance; one
    legend below the panels."""
    tolerances = config["profile_tolerances"]
    fig, axes = plotting.panels(1, len(tolerances), 4.6 * len(tolerances), 4.2)
    lines, problems = {}, 0
    for ax, tol in zip(axes, tolerances, strict=True):
        labels, times = profile_times(instances, tol)
        problems = len(times)
        with np.errstate(invalid="ignore"):  # inf / inf where no call solved a problem
            ratios = times / times.min(axis=1, keepdims=True)
        finite = ratios[np.isfinite(ratios)]
        taus = np.geomspace(1.0, 1.2 * finite.max() if finite.size else 10.0, 400)
        rho = performance_profile(times, taus)
        for k, (label, curve) in enumerate(zip(labels, rho, strict=True)):
            lines[label], = ax.plot(taus, curve, drawstyle="steps-post", label=label,
                                    **{**_style(k, label in PEERS), "marker": None})
        ax.set(xscale="log", ylim=(-0.02, 1.02),
               xlabel="tau: CPU time / least CPU time on the problem (ratio)",
               ylabel="fraction of problems solved within tau")
        ax.set_title(f"solved: objective within {tol:g} of the best", fontsize=9)
        ax.grid(alpha=0.3, which="major")
    plotting.legend_below(fig, list(lines.values()), ncol=5, title=LEGEND, title_fontsize=8)
    fig.suptitle(f"Performance profile of the user's calls ({problems} problems, seed "
                 f"{config['seed']})", fontsize=11)
    plotting.save(fig, path)
