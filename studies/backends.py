"""Benchmark of the weight solvers: time, accuracy and certificate per backend and shape.

For every (n, N, criterion, kind) of the config, `instances` seeded problems (kind "random":
P_i = A A^T / n + 0.01 I with A standard normal; "ill-conditioned": eigenvalues log-uniform
over 1e-6..1e6 in a random rotation, each node scaled by 10^U(-3, 3)) are scaled as `fuse`
scales them and handed to each backend (`fusion_opt.backends.REGISTRY`). It times the
backend call only (the first solve of each shape, which compiles CVXPY's program, apart),
and compares, on the backend's own weights mapped onto the simplex and not polished:

    objective gap to the best backend   (f_b - f_best) / |f_best| (trace), f_b - f_best (logdet)
    optimality gap                       the certificate of DESIGN §1, relative as newton's

A failure is an exception or a status other than "optimal". Then `fuse_batch` times B
pairwise problems at each n of batch_n. Writes backends.csv, backends.md,
backends_time_vs_N.png and machine.json into out_dir.
"""

from __future__ import annotations

import csv
import json
import platform
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from fusion_opt import bci, criteria, fuse_batch, programs
from fusion_opt.backends import REGISTRY, newton
from fusion_opt.scaling import conic_problem
from fusion_opt.simplex import to_simplex

from . import config as configs
from . import meta, plotting

COLUMNS = ("mode", "backend", "n", "N", "criterion", "kind", "solves", "first_ms",
           "median_ms", "p90_ms", "solver_own_median_ms", "overhead_median_ms",
           "worst_objective_gap", "worst_optimality_gap", "failures")


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this benchmark
    cannot run: called on the whole merged configuration before anything runs."""
    lists = {"n": 1, "N": 2, "batch_n": 1}  # list field -> its smallest value
    counts = {"instances": 1, "repeats": 1, "batch_pairs": 1, "batch_repeats": 1}
    configs.fields(config, "", ("seed", "criteria", "kinds", "backends", *lists, *counts),
                   ("batch_check",))
    configs.integer("seed", config["seed"], low=0)
    for key, low in lists.items():
        for i, v in enumerate(configs.items(key, config[key])):
            configs.integer(f"{key}[{i}]", v, low=low)
    for key, low in (counts | {"batch_check": 1}).items():
        if key in config:
            configs.integer(key, config[key], low=low)
    for key, options in (("criteria", ("trace", "logdet")),
                         ("kinds", ("random", "ill-conditioned")), ("backends", REGISTRY)):
        for i, v in enumerate(configs.items(key, config[key])):
            configs.choice(f"{key}[{i}]", v, options)


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
    rows = _single_rows(config, progress) + _batch_rows(config)
    with open(out_dir / "backends.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (out_dir / "backends.md").write_text(_markdown(rows, config, quick))
    _figure(rows, out_dir / "backends_time_vs_N.png")
    info = {"versions": meta.versions(), "machine": meta.machine(),
            "git_commit": meta.git_commit(), "numpy_config": _blas(),
            "python": platform.python_implementation(), "quick": quick,
            "wall_time_s": time.perf_counter() - t0, "config": config}
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


def _single_rows(config, progress) -> list[dict]:
    from tqdm import tqdm

    programs.clear_cache()  # so "first" includes CVXPY's compilation of every shape
    cells = [(n, N, crit, kind) for n in config["n"] for N in config["N"]
             for crit in config["criteria"] for kind in config["kinds"]]
    seeds = np.random.SeedSequence(config["seed"]).spawn(len(cells))
    rows = []
    for (n, N, crit, kind), ss in tqdm(list(zip(cells, seeds, strict=True)), disable=not progress,
                                       desc="backends", unit="cell"):
        rng = np.random.default_rng(ss)
        problems = [SimpleNamespace(**dict(zip(("Ys", "M"), conic_problem(instance(rng, N, n, kind)))))
                    for _ in range(config["instances"])]
        rows += _cell(problems, n, N, crit, kind, config)
    return rows


def _cell(problems, n, N, crit, kind, config) -> list[dict]:
    """Time every backend on the problems of one cell; one row per backend."""
    backends = [b for b in config["backends"] if b != "closed-form" or N == 2]
    f = {b: np.full(len(problems), np.nan) for b in backends}
    stats = {b: {"times": [], "own": [], "first": np.nan, "gap": 0.0, "failures": 0}
             for b in backends}
    for k, sp in enumerate(problems):
        for b in backends:
            st = stats[b]
            try:
                for r in range(config["repeats"] + (k == 0)):
                    t = time.perf_counter()
                    sol = REGISTRY[b](sp.Ys, sp.M, crit)
                    t = time.perf_counter() - t
                    if k == 0 and r == 0:
                        st["first"] = t
                    else:
                        st["times"].append(t)
                        # a native backend's own time is its wall time: no overhead to show
                        native = sol.solver_time in (None, sol.solve_time)
                        st["own"].append(np.nan if native else sol.solver_time)
            except Exception:  # noqa: BLE001 (a failure is what we count)
                st["failures"] += 1
                continue
            st["failures"] += sol.status != "optimal"
            w = to_simplex(sol.w)
            ev = criteria.evaluate(sp.Ys, w, crit, sp.M)
            f[b][k] = ev.f
            st["gap"] = max(st["gap"], float(newton.relative_gap(ev.f, ev.g, w, crit)))
    best = np.nanmin(np.stack(list(f.values())), axis=0)
    denom = np.abs(best) if crit == "trace" else 1.0
    rows = []
    for b in backends:
        st, times = stats[b], np.array(stats[b]["times"]) * 1e3
        own = np.array(st["own"]) * 1e3
        rows.append({
            "mode": "single", "backend": b, "n": n, "N": N, "criterion": crit, "kind": kind,
            "solves": len(times), "first_ms": st["first"] * 1e3,
            "median_ms": _q(times, 50), "p90_ms": _q(times, 90),
            "solver_own_median_ms": _q(own, 50),
            "overhead_median_ms": _q(times - own, 50) if own.size else np.nan,
            "worst_objective_gap": float(np.nanmax((f[b] - best) / denom)),
            "worst_optimality_gap": st["gap"], "failures": st["failures"]})
    return rows


def _q(values, q) -> float:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else np.nan


def _batch_rows(config) -> list[dict]:
    """fuse_batch on batch_pairs pairwise random problems per n and criterion."""
    rows = []
    rng = np.random.default_rng(np.random.SeedSequence(config["seed"]).spawn(1)[0])
    B = config["batch_pairs"]
    for n in config["batch_n"]:
        covs = instance(rng, 2 * B, n, "random").reshape(B, 2, n, n)
        means = rng.standard_normal((B, 2, n))
        for crit in config["criteria"]:
            fuse_batch(means[:10], covs[:10], "ci", crit, "closed-form")
            times = []
            for _ in range(config["batch_repeats"]):
                r = fuse_batch(means, covs, "ci", crit, "closed-form")
                times.append(r.solve_time)
            # Accuracy against `fuse` with Clarabel, problem by problem, on a sample.
            idx = rng.choice(B, size=min(B, config.get("batch_check", 20)), replace=False)
            ref = np.array([bci(means[i], covs[i], crit, "clarabel").objective for i in idx])
            diff = r.objective[idx] - ref
            t = np.array(times) / B * 1e3
            rows.append({
                "mode": "batch", "backend": "closed-form", "n": n, "N": 2, "criterion": crit,
                "kind": f"random B={B}", "solves": B * len(times), "first_ms": np.nan,
                "median_ms": _q(t, 50), "p90_ms": _q(t, 90), "solver_own_median_ms": np.nan,
                "overhead_median_ms": np.nan,
                "worst_objective_gap": float(np.max(diff / np.abs(ref) if crit == "trace"
                                                    else diff)),
                "worst_optimality_gap": float(np.max(r.gap / np.abs(r.objective)))
                if crit == "trace" else float(np.max(r.gap)),
                "failures": int((r.status != "optimal").sum())})
    return rows


def _markdown(rows, config, quick) -> str:
    single = [r for r in rows if r["mode"] == "single"]
    backends = list(dict.fromkeys(r["backend"] for r in single))
    lines = [f"# Backend benchmark{' (quick)' if quick else ''}", "",
             f"{config['instances']} instances per (n, N, criterion, kind), kinds "
             f"{', '.join(config['kinds'])}; {config['repeats']} timed solves each. "
             "Median / 90th-percentile ms per solve of the backend call on the scaled "
             "problem, over both kinds; first = the first solve of the shape (CVXPY "
             "compiles). Gaps as in the module docstring of studies/backends.py.", "",
             "| n | N | criterion | " + " | ".join(
                 f"{b} median / p90 (first)" for b in backends)
             + f" | newton speed-up over clarabel ({' / '.join(config['kinds'])}) |",
             "|---|---|---|" + "---|" * (len(backends) + 1)]
    for key in dict.fromkeys((r["n"], r["N"], r["criterion"]) for r in single):
        cell = [r for r in single if (r["n"], r["N"], r["criterion"]) == key]
        med = {b: _pooled(cell, b, "median_ms") for b in backends}
        cols = []
        for b in backends:
            got = [r for r in cell if r["backend"] == b]
            cols.append(f"{med[b]:.3g} / {max(r['p90_ms'] for r in got):.3g} "
                        f"({max(r['first_ms'] for r in got):.3g})" if got else "-")
        speed = " / ".join(f"{_speedup(cell, kind):.1f}x" for kind in config["kinds"])
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | " + " | ".join(cols)
                     + f" | {speed} |")
    lines += ["", "## Accuracy and failures (worst over all cells)", "",
              "| backend | solves | worst objective gap to best | worst optimality gap | "
              "failures | ms over the solver's own time, n <= 6: median / worst cell |",
              "|---|---|---|---|---|---|"]
    for b in backends:
        got = [r for r in single if r["backend"] == b]
        over = [r["overhead_median_ms"] for r in got if r["n"] <= 6]
        over_txt = f"{_q(over, 50):.3g} / {np.nanmax(over):.3g}" if np.isfinite(over).any() \
            else "-"
        lines.append(f"| {b} | {sum(r['solves'] for r in got)} | "
                     f"{max(r['worst_objective_gap'] for r in got):.2e} | "
                     f"{max(r['worst_optimality_gap'] for r in got):.2e} | "
                     f"{sum(r['failures'] for r in got)} | {over_txt} |")
    lines += ["", "## fuse_batch, pairwise (closed form, vectorised over B)", "",
              "| n | criterion | problems | microseconds per fusion (median / p90) | "
              "worst objective gap to clarabel | worst optimality gap | failures |",
              "|---|---|---|---|---|---|---|"]
    for r in (r for r in rows if r["mode"] == "batch"):
        lines.append(f"| {r['n']} | {r['criterion']} | {r['kind']} | "
                     f"{1e3 * r['median_ms']:.2f} / {1e3 * r['p90_ms']:.2f} | "
                     f"{r['worst_objective_gap']:.1e} | {r['worst_optimality_gap']:.1e} | "
                     f"{r['failures']} |")
    return "\n".join(lines) + "\n"


def _speedup(cell, kind) -> float:
    """Median time of "clarabel" over that of "newton" for one kind of one cell."""
    med = {r["backend"]: r["median_ms"] for r in cell if r["kind"] == kind}
    return med.get("clarabel", np.nan) / med.get("newton", np.nan)


def _pooled(cell, backend, key) -> float:
    """Mean over kinds of a per-kind statistic (NaN if the backend did not run)."""
    vals = [r[key] for r in cell if r["backend"] == backend]
    return float(np.mean(vals)) if vals else np.nan


def _figure(rows, path: Path) -> None:
    single = [r for r in rows if r["mode"] == "single"]
    ns = sorted({r["n"] for r in single})
    fig, axes = plotting.new_figure(1, len(ns), width=3.2 * len(ns))
    for ax, n in zip(axes, ns, strict=True):
        for b in dict.fromkeys(r["backend"] for r in single):
            for crit, style in (("trace", "-o"), ("logdet", "--s")):
                pts = sorted({r["N"] for r in single if r["n"] == n and r["backend"] == b
                              and r["criterion"] == crit})
                if not pts:
                    continue
                t = [_pooled([r for r in single if (r["n"], r["N"], r["criterion"])
                              == (n, N, crit)], b, "median_ms") for N in pts]
                ax.plot(pts, t, style, ms=3, label=f"{b} ({crit})")
        plotting.log_axes(ax, sorted({r["N"] for r in single if r["n"] == n}), "N (nodes)")
        ax.set_title(f"n = {n}")
    axes[0].set_ylabel("median time per solve (ms)")
    axes[-1].legend(fontsize=6)
    plotting.save(fig, path)
