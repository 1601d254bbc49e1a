"""Benchmark of the weight solvers: time, accuracy and certificate per backend and shape.

For every (n, N, criterion, kind) of the config, `instances` seeded problems (kind "random":
P_i = A A^T / n + 0.01 I with A standard normal; "ill-conditioned": eigenvalues log-uniform
over 1e-6..1e6 in a random rotation, each node scaled by 10^U(-3, 3)) are fused by every
configured backend of `fusion_opt.BACKENDS` ("closed-form" only where N = 2), backend after
backend on each problem (starting from another on each, `_loop`), in one process. What is
timed is what a user calls:

    fo.fuse(means, covs, "bci", criterion, backend, polish=False)

wall time per call, `repeats` calls per problem; the first call of each cell is reported
apart (first_ms: in the first cell of a shape it builds CVXPY's program for "clarabel" and
"scs", and Clarabel's template for "clarabel-direct"; the compiled kernels are loaded
before anything is timed, in kernel_load_s of machine.json).
The conic and SLSQP backends are also timed with the default polish (polished_median_ms).
solver_own_median_ms is the time the solver itself reports (Clarabel's, SCS's) in the
same timed calls (read by a wrapper around the backend's REGISTRY entry, which costs one
Python call) and overhead_median_ms the rest of each call; SLSQP and the native backends
report none (NaN).

Accuracy is computed outside the solvers, on the weights w each backend returned
(unpolished), never from what it reports: f and the certificate of DESIGN §1 by
`fusion_opt.criteria.evaluate` (numpy) on the congruence-scaled problem
`scaling.conic_problem(covs)`, where the weights and the relative gaps are those of the
original problem and the numbers are of order one even for the ill-conditioned kind. (The
conic backends solve that same scaled problem; "newton" does not, so a scaling error would
show as a gap between them.)

    worst_objective_gap    (f_b - f_best) / |f_best| (trace), f_b - f_best (logdet), f_best
                           the best backend's f on the same problem
    worst_optimality_gap   (g.w - min_i g_i) / |f| (trace), g.w - min_i g_i (logdet)

A failure is a call that raises, or one whose result with the default polish (what a user
gets) is not Status.OPTIMAL; first_failure says why the first one failed.

Then, on batch_pairs random pairwise problems per n of batch_n: `fo.fuse_batch` with each
configured native backend (one call over all B, wall time / B), beside a loop of `fo.fuse`
calls of every configured backend on batch_check of the same problems, with the gaps
above on those. Writes backends.csv, backends.md (speed-ups of newton over its peers
computed from the CSV), backends_time_vs_N.png and machine.json into out_dir.
"""

from __future__ import annotations

import csv
import gc
import json
import platform
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import fusion_opt as fo
from fusion_opt import criteria, programs
from fusion_opt.backends import EXACT, REGISTRY, clarabel_direct
from fusion_opt.scaling import conic_problem

from . import config as configs
from . import meta, plotting

COLUMNS = ("mode", "backend", "n", "N", "criterion", "kind", "solves", "first_ms",
           "median_ms", "p90_ms", "polished_median_ms", "solver_own_median_ms",
           "overhead_median_ms", "worst_objective_gap", "worst_optimality_gap", "failures",
           "first_failure")
REFERENCE = "newton"  # the backend whose speed-up over the others backends.md reports
FIRST_BATCH = 10  # problems of the untimed first fuse_batch call (loads, allocates)


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this benchmark
    cannot run: called on the whole merged configuration before anything runs.
    "closed-form" fuses pairs only; it is skipped in the cells where N != 2."""
    lists = {"n": 1, "N": 2, "batch_n": 1}  # list field -> its smallest value
    counts = ("instances", "repeats", "batch_pairs", "batch_repeats", "batch_check")
    configs.fields(config, "", ("seed", "criteria", "kinds", "backends", *lists, *counts))
    configs.integer("seed", config["seed"], low=0)
    for key, low in lists.items():
        for i, v in enumerate(configs.items(key, config[key])):
            configs.integer(f"{key}[{i}]", v, low=low)
    for key in counts:
        configs.integer(key, config[key], low=1)
    for key, options in (("criteria", ("trace", "logdet")),
                         ("kinds", ("random", "ill-conditioned")),
                         ("backends", fo.BACKENDS)):
        for i, v in enumerate(configs.items(key, config[key])):
            configs.choice(f"{key}[{i}]", v, options)
    for key in (*lists, "criteria", "kinds", "backends"):
        twice = sorted({v for v in config[key] if config[key].count(v) > 1})
        if twice:
            raise configs.ConfigError(f"{key} lists {twice} more than once")
    if set(config["backends"]) == {"closed-form"} and 2 not in config["N"]:
        raise configs.ConfigError(f"backends ['closed-form'] fuses N = 2 only, which N = "
                                  f"{config['N']} does not hold: nothing would be measured")


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
    rows = _measure(config, progress)
    with open(out_dir / "backends.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (out_dir / "backends.md").write_text(_markdown(rows, config, quick))
    _figure(rows, out_dir / "backends_time_vs_N.png")
    info = {"versions": meta.versions(), "machine": meta.machine(),
            "git_commit": meta.git_commit(), "numpy_config": _blas(),
            "python": platform.python_implementation(), "quick": quick,
            "kernel_load_s": load, "wall_time_s": time.perf_counter() - t0,
            "config": config}
    (out_dir / "machine.json").write_text(json.dumps(info, indent=2, default=str))


def report(config: dict, out_dir: Path, *, quick: bool) -> None:
    """Rebuild backends.md and the figure from backends.csv (no new measurement)."""
    out_dir = Path(out_dir)
    with open(out_dir / "backends.csv", newline="") as fh:
        rows = [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(fh)]
    (out_dir / "backends.md").write_text(_markdown(rows, config, quick))
    _figure(rows, out_dir / "backends_time_vs_N.png")


def _number(text: str):
    """A CSV cell back as the int, float or string it was written from."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _blas() -> str:
    import numpy

    cfg = numpy.show_config(mode="dicts")["Build Dependencies"]
    return f"{cfg['blas'].get('name')} {cfg['blas'].get('version')}"


def _load_kernels(config) -> float:
    """Seconds to load (or, on a new machine, compile) the compiled kernels every backend
    uses, by fusing a pair and a triple with each; then the per-shape caches are emptied,
    so that first_ms is the first call of a shape and nothing else."""
    t0 = time.perf_counter()
    for b in config["backends"]:
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

@dataclass
class _Runs:
    """What one backend gave on the problems of one cell: times (s per fusion) of the
    unpolished calls, with the solver's own time of each (NaN if it reports none), of
    the polished calls, weights (N,) per problem (NaN where it failed), failures; a
    call fuses `per_call` problems."""

    mode: str
    per_call: int = 1
    times: list = field(default_factory=list)
    own: list = field(default_factory=list)
    polished: list = field(default_factory=list)
    weights: list = field(default_factory=list)
    first: float = np.nan
    failures: int = 0
    first_failure: str = ""


def _measure(config, progress) -> list[dict]:
    """Every single-problem cell, then every batch cell, one row per backend each."""
    from tqdm import tqdm

    cells = [(n, N, crit, kind) for n in config["n"] for N in config["N"]
             for crit in config["criteria"] for kind in config["kinds"]]
    *seeds, batch_seed = np.random.SeedSequence(config["seed"]).spawn(len(cells) + 1)
    batch = [(n, crit) for n in config["batch_n"] for crit in config["criteria"]]
    rows = []
    with tqdm(total=len(cells) + len(batch), disable=not progress, desc="backends",
              unit="cell") as bar:
        for (n, N, crit, kind), ss in zip(cells, seeds, strict=True):
            rows += _single_cell(np.random.default_rng(ss), n, N, crit, kind, config)
            bar.update()
        pairs = _pairs(np.random.default_rng(batch_seed), config)
        for n, crit in batch:
            rows += _batch_cell(*pairs[n], n, crit, config)
            bar.update()
    return rows


def _single_cell(rng, n, N, crit, kind, config) -> list[dict]:
    """`instances` problems of one (n, N, criterion, kind), fused by every backend."""
    problems = [(rng.standard_normal((N, n)), instance(rng, N, n, kind))
                for _ in range(config["instances"])]
    runs = _loop(problems, crit, _backends(config, N), config["repeats"], "single")
    return _rows(runs, np.stack([c for _, c in problems]), crit,
                 {"n": n, "N": N, "criterion": crit, "kind": kind})


def _backends(config, N) -> list[str]:
    return [b for b in config["backends"] if b != "closed-form" or N == 2]


def _loop(problems, crit, backends, repeats, mode) -> list[tuple[str, _Runs]]:
    """(backend, its runs) of each problem (means (N, n), covs (N, n, n)) fused by each
    backend in turn, from the k-th backend on the k-th problem: the first call after
    another backend's finds cold caches (measured: 2.5x the time of the next for newton
    at n = 4 after Clarabel), and rotating shares that cost out evenly."""
    runs = [(b, _Runs(mode)) for b in backends]
    for k, (means, covs) in enumerate(problems):
        start = k % len(runs)
        for b, r in runs[start:] + runs[:start]:
            _fuse(r, means, covs, crit, b, repeats, first=k == 0)
    return runs


def _fuse(runs: _Runs, means, covs, crit, backend, repeats, first) -> None:
    """`repeats` timed calls of fuse(polish=False) on one problem (after one more, the
    first of the cell, when `first`) and, for a backend of REGISTRY, `repeats` with the
    default polish; the result appended to runs."""
    try:
        with _own_times(backend) as own:
            raw = [_timed(fo.fuse, means, covs, "bci", crit, backend, polish=False)
                   for _ in range(repeats + first)]
        polished = ([_timed(fo.fuse, means, covs, "bci", crit, backend)
                     for _ in range(repeats)] if backend in REGISTRY else raw)
    except Exception as exc:  # noqa: BLE001 (a failure is what we count)
        runs.failures += 1
        runs.first_failure = runs.first_failure or f"{type(exc).__name__}: {exc}"
        runs.weights.append(np.full(len(covs), np.nan))
        return
    if first:
        runs.first = raw[0][0]
    runs.times += [t for t, _ in raw[first:]]
    runs.own += own[first:] if own else [np.nan] * repeats
    if backend in REGISTRY:
        runs.polished += [t for t, _ in polished]
    runs.weights.append(raw[-1][1].weights)
    if polished[-1][1].status != fo.Status.OPTIMAL:
        runs.failures += 1
        runs.first_failure = runs.first_failure or f"status {polished[-1][1].status.value}"


def _timed(call, *args, **kwargs):
    """(wall seconds, result) of one call(*args, **kwargs). The garbage collector is held
    off during the call, as timeit does, so that a collection of another backend's garbage
    (CVXPY makes much) is not charged to this one."""
    gc.disable()
    try:
        t = time.perf_counter()
        r = call(*args, **kwargs)
        return time.perf_counter() - t, r
    finally:
        gc.enable()


@contextmanager
def _own_times(backend):
    """A list that receives the solver's own time (s) of each call of REGISTRY[backend]
    made inside the block (empty for a native backend, which reports none). The wrapper
    costs one Python call, well under a microsecond against calls of milliseconds."""
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


def _pairs(rng, config) -> dict:
    """{n: (means (B, 2, n), covs (B, 2, n, n))}: batch_pairs random pairs per n."""
    B = config["batch_pairs"]
    return {n: (rng.standard_normal((B, 2, n)),
                instance(rng, 2 * B, n, "random").reshape(B, 2, n, n))
            for n in config["batch_n"]}


def _batch_cell(means, covs, n, crit, config) -> list[dict]:
    """fuse_batch over all B pairs with each native backend, and a loop of fuse calls of
    every backend on batch_check of the pairs; gaps on those."""
    B = len(means)
    sample = np.arange(min(B, config["batch_check"]))  # the pairs are independent draws
    runs = [(b, _batched(means, covs, crit, b, config["batch_repeats"], sample))
            for b in config["backends"] if b in EXACT]
    runs += _loop([(means[i], covs[i]) for i in sample], crit, _backends(config, 2),
                  config["batch_repeats"], "loop")
    return _rows(runs, covs[sample], crit,
                 {"n": n, "N": 2, "criterion": crit, "kind": f"random B={B}"})


def _batched(means, covs, crit, backend, repeats, sample) -> _Runs:
    """fuse_batch of all B problems, `repeats` timed calls after an untimed one of
    FIRST_BATCH problems; the weights of the problems in `sample` kept."""
    runs = _Runs("batch", per_call=len(means))
    try:
        fo.fuse_batch(means[:FIRST_BATCH], covs[:FIRST_BATCH], "bci", crit, backend)
        for _ in range(repeats):
            t, r = _timed(fo.fuse_batch, means, covs, "bci", crit, backend)
            runs.times.append(t / len(means))
    except Exception as exc:  # noqa: BLE001 (a failure is what we count)
        runs.failures, runs.first_failure = len(means), f"{type(exc).__name__}: {exc}"
        runs.weights = list(np.full((len(sample), covs.shape[1]), np.nan))
        return runs
    runs.own = [np.nan] * repeats
    runs.weights = list(r.weights[sample])
    bad = np.flatnonzero(r.status != fo.Status.OPTIMAL)
    runs.failures = len(bad)
    runs.first_failure = f"problem {bad[0]}: status {r.status[bad[0]].value}" if len(bad) \
        else ""
    return runs


# ------------------------------------------------------------------------- accuracy

def _accuracy(covs, weights: list, crit) -> list[tuple[np.ndarray, np.ndarray]]:
    """(objective gaps (K,), relative certificates (K,)) of each of weights, a list of
    (K, N) arrays (NaN rows where a backend failed), on problems covs (K, N, n, n): the
    gaps of the module docstring, by numpy on the congruence-scaled problems."""
    Ys, M = (np.stack(a) for a in zip(*(conic_problem(c) for c in covs), strict=True))
    scale = np.abs if crit == "trace" else np.ones_like  # relative for trace only
    f, cert = [], []
    for W in weights:
        W = np.asarray(W, dtype=float)
        ok = np.isfinite(W).all(-1)
        ev = criteria.evaluate(Ys, np.where(ok[:, None], W, 1.0 / W.shape[1]), crit, M)
        f.append(np.where(ok, ev.f, np.nan))
        cert.append(np.where(ok, criteria.gap(ev.g, W) / scale(ev.f), np.nan))
    best = np.fmin.reduce(f)  # NaN only where every backend failed
    return [((fb - best) / scale(best), c) for fb, c in zip(f, cert, strict=True)]


def _rows(runs: list, covs, crit, where: dict) -> list[dict]:
    """One CSV row per (backend, runs) of runs on problems covs (K, N, n, n)."""
    gaps = _accuracy(covs, [r.weights for _, r in runs], crit)
    rows = []
    for (b, r), (objective_gap, optimality_gap) in zip(runs, gaps, strict=True):
        times, own = np.array(r.times) * 1e3, np.array(r.own) * 1e3
        rows.append({
            "mode": r.mode, "backend": b, **where, "solves": len(times) * r.per_call,
            "first_ms": r.first * 1e3, "median_ms": _q(times, 50), "p90_ms": _q(times, 90),
            "polished_median_ms": _q(np.array(r.polished) * 1e3, 50),
            "solver_own_median_ms": _q(own, 50), "overhead_median_ms": _q(times - own, 50),
            "worst_objective_gap": _worst(objective_gap),
            "worst_optimality_gap": _worst(optimality_gap),
            "failures": r.failures, "first_failure": r.first_failure})
    return rows


def _q(values, q) -> float:
    """The q-th percentile of the finite values (NaN if there is none)."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else np.nan


def _worst(values) -> float:
    """The largest finite value (NaN if there is none)."""
    return _q(values, 100)


# ------------------------------------------------------------------------- the report

def _markdown(rows, config, quick) -> str:
    single = [r for r in rows if r["mode"] == "single"]
    backends = list(dict.fromkeys(r["backend"] for r in single))
    return "\n".join([
        f"# Backend benchmark{' (quick)' if quick else ''}", "",
        f"{config['instances']} seeded problems per (n, N, criterion, kind), kinds "
        f"{', '.join(config['kinds'])}; every backend fuses each problem in turn, "
        f"{config['repeats']} timed call(s) of `fo.fuse(..., polish=False)` each, in one "
        "process; everything below was measured by this run (studies/backends.py says "
        "how).", "",
        *_time_table(single, backends), "", *_speedup_table(single, backends), "",
        *_accuracy_table(single, backends), "", *_batch_table(rows, config)]) + "\n"


def _time_table(single, backends) -> list[str]:
    lines = ["## Time per fusion (ms)", "",
             "Median over the problems and calls of a cell, the mean of the kinds' "
             "medians; after the slash, the same with the default polish (conic and SLSQP "
             "backends).", "",
             "| n | N | criterion | " + " | ".join(backends) + " |",
             "|---|---|---|" + "---|" * len(backends)]
    for key, cell in _cells(single):
        cols = []
        for b in backends:
            polished = _pooled(cell, b, "polished_median_ms")
            cols.append(_fmt(_pooled(cell, b, "median_ms"), ".3g")
                        + (f" / {polished:.3g}" if np.isfinite(polished) else ""))
        lines.append("| " + " | ".join(map(str, key)) + " | " + " | ".join(cols) + " |")
    return lines


def _speedup_table(single, backends) -> list[str]:
    peers = [b for b in backends if b not in EXACT]
    if REFERENCE not in backends or not peers:
        return [f"## Speed-up of {REFERENCE}", "", f"Not measured: the run had no "
                f"{REFERENCE} or no peer to compare it with."]
    ratios = {b: {key: _pooled(cell, b, "median_ms") / _pooled(cell, REFERENCE, "median_ms")
                  for key, cell in _cells(single)} for b in peers}
    lines = [f"## Speed-up of {REFERENCE}", "",
             f"Median time of each peer over that of {REFERENCE}, both without polish, on "
             f"the same problems (the peer's weights are then less accurate than "
             f"{REFERENCE}'s: see the accuracy table).", ""]
    lines += [_speedup_line(b, r) for b, r in ratios.items()]
    lines += ["", "| n | N | criterion | " + " | ".join(f"over {b}" for b in peers) + " |",
              "|---|---|---|" + "---|" * len(peers)]
    for key, _ in _cells(single):
        lines.append("| " + " | ".join(map(str, key)) + " | "
                     + " | ".join(_fmt(ratios[b][key], ".3g", "x") for b in peers) + " |")
    return lines


def _speedup_line(peer, ratios: dict) -> str:
    """One sentence on ratios {(n, N, criterion): peer's time over REFERENCE's}."""
    r = {key: x for key, x in ratios.items() if np.isfinite(x)}
    if not r:
        return f"- {peer}: no cell where both it and {REFERENCE} solved anything."
    lo, hi = min(r, key=r.get), max(r, key=r.get)
    return (f"- {REFERENCE} is {r[lo]:.3g} to {r[hi]:.3g} times faster than {peer} (median "
            f"{np.median(list(r.values())):.3g}x over {len(r)} cells; least at (n, N) = "
            f"({lo[0]}, {lo[1]}) {lo[2]}, most at ({hi[0]}, {hi[1]}) {hi[2]}).")


def _accuracy_table(single, backends) -> list[str]:
    lines = ["## Accuracy, failures and call costs (over all cells)", "",
             "Gaps of the unpolished weights (module docstring of studies/backends.py), "
             "worst over all problems; a failure is a call that raised or whose polished "
             "result is not certified optimal. First call: the first of each shape (n, N, "
             "criterion), which builds CVXPY's program (clarabel, scs) or Clarabel's "
             "template (clarabel-direct). Overhead: the call's wall "
             "time over the solver's own, median per cell (n <= 6).", "",
             "| backend | solves | worst objective gap to best | worst optimality gap | "
             "failures | first call ms (median / worst shape) | overhead ms (median / worst "
             "cell) |", "|---|---|---|---|---|---|---|"]
    why = []
    for b in backends:
        got = [r for r in single if r["backend"] == b]
        over = [r["overhead_median_ms"] for r in got if r["n"] <= 6]
        first = [_worst([r["first_ms"] for r in cell if r["backend"] == b])
                 for _, cell in _cells(got)]
        lines.append(f"| {b} | {sum(r['solves'] for r in got)} | "
                     f"{_fmt(_worst([r['worst_objective_gap'] for r in got]), '.2e')} | "
                     f"{_fmt(_worst([r['worst_optimality_gap'] for r in got]), '.2e')} | "
                     f"{sum(r['failures'] for r in got)} | {_median_worst(first)} | "
                     f"{_median_worst(over)} |")
        why += [f"- {b} at (n, N) = ({r['n']}, {r['N']}), {r['criterion']}, {r['kind']}: "
                f"{r['first_failure']}" for r in got if r["first_failure"]][:1]
    return lines + (["", "First failure of each backend that failed:", *why] if why else [])


def _fmt(x, spec: str, unit: str = "") -> str:
    """x formatted, or "-" where nothing was measured (NaN)."""
    return f"{x:{spec}}{unit}" if np.isfinite(x) else "-"


def _median_worst(values) -> str:
    return f"{_q(values, 50):.3g} / {_worst(values):.3g}" if np.isfinite(values).any() \
        else "-"


def _batch_table(rows, config) -> list[str]:
    batch = [r for r in rows if r["mode"] in ("batch", "loop")]
    ref = next((r["backend"] for r in batch if r["mode"] == "batch"), None)
    lines = ["## Pairwise problems: fo.fuse_batch against a loop of fo.fuse", "",
             f"{config['batch_pairs']} random pairs per n; fuse_batch fuses all of them in "
             f"one call (wall time / B, {config['batch_repeats']} call(s)); the loop calls "
             f"fuse (polish=False) on {config['batch_check']} of them, which the "
             "gaps are computed on. Failures: problems not certified optimal, of the B "
             "for fuse_batch, of the loop's for fuse.", ""]
    if ref is None:
        return lines + ["Not measured: the run had no native backend (newton, closed-form)."]
    lines += [f"| n | criterion | call | microseconds per fusion (median / p90) | fuse_batch "
              f"{ref} is faster by | worst objective gap | worst optimality gap | "
              "failures |", "|---|---|---|---|---|---|---|---|"]
    for n, crit in dict.fromkeys((r["n"], r["criterion"]) for r in batch):
        cell = [r for r in batch if (r["n"], r["criterion"]) == (n, crit)]
        t_ref = next(r["median_ms"] for r in cell if (r["mode"], r["backend"])
                     == ("batch", ref))
        for r in cell:
            call = f"fuse_batch {r['backend']}" if r["mode"] == "batch" \
                else f"fuse loop {r['backend']}"
            lines.append(f"| {n} | {crit} | {call} | {_fmt(1e3 * r['median_ms'], '.3g')} / "
                         f"{_fmt(1e3 * r['p90_ms'], '.3g')} | "
                         f"{_fmt(r['median_ms'] / t_ref, '.3g', 'x')} | "
                         f"{_fmt(r['worst_objective_gap'], '.1e')} | "
                         f"{_fmt(r['worst_optimality_gap'], '.1e')} | {r['failures']} |")
    return lines


def _cells(single):
    """((n, N, criterion), rows of that cell over the kinds), in the order run."""
    keys = dict.fromkeys((r["n"], r["N"], r["criterion"]) for r in single)
    return [(key, [r for r in single if (r["n"], r["N"], r["criterion"]) == key])
            for key in keys]


def _pooled(cell, backend, key) -> float:
    """Mean over kinds of a per-kind statistic (NaN if the backend did not run)."""
    vals = [r[key] for r in cell if r["backend"] == backend and np.isfinite(r[key])]
    return float(np.mean(vals)) if vals else np.nan


def _figure(rows, path: Path) -> None:
    """Median time per fusion (polish=False) against N, one panel per n: a colour and
    marker per backend (hollow, so that equal times stay visible), solid for trace and
    dashed for logdet; the legend beside the last panel."""
    single = [r for r in rows if r["mode"] == "single"]
    ns = sorted({r["n"] for r in single})
    backends = list(dict.fromkeys(r["backend"] for r in single))
    fig, axes = plotting.new_figure(1, len(ns), width=3.0 * len(ns) + 1.8)
    legend = {}
    for ax, n in zip(axes, ns, strict=True):
        cells = _cells([r for r in single if r["n"] == n])
        for i, b in enumerate(backends):
            for crit, line in (("trace", "-"), ("logdet", "--")):
                pts = [(key[1], _pooled(cell, b, "median_ms")) for key, cell in cells
                       if key[2] == crit]
                pts = [(N, t) for N, t in pts if np.isfinite(t)]
                if pts:
                    legend[f"{b} ({crit})"], = ax.plot(
                        *zip(*pts, strict=True), line, color=f"C{i}", marker="oxs^vD"[i % 6],
                        ms=4, fillstyle="none", lw=1)
        plotting.log_axes(ax, sorted({r["N"] for r in single if r["n"] == n}), "N (nodes)")
        ax.set_title(f"n = {n}")
    axes[0].set_ylabel("median time per fusion (ms)")
    axes[-1].legend(legend.values(), legend.keys(), loc="upper left", fontsize=6,
                    bbox_to_anchor=(1.02, 1.0), frameon=False)
    plotting.save(fig, path)
