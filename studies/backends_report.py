"""The report of the backend benchmark (studies/backends.py), rebuilt from its two
measurement CSVs: backends.md with a CSV per table, the targets of issue 11, the
Dolan-More performance profile and the figures."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion_opt.backends import EXACT

from . import plotting, stats
from .peers import PEERS

BCI, CI, RAW = "fo.bci", "fo.ci", "fo.fuse(polish=False)"
REFERENCE = "newton"  # the backend whose speed-up over the others backends.md reports
ROUNDING = 1e-12  # objective gaps within this are equal (relative; nats for logdet)
CERTIFIED = 1e-10  # Status.OPTIMAL's bound on the relative certificate
# the calls of backends.py's newton parts rows: the whole call, then the parts it is made of
PART_NAMES = ("fo.bci (warm)", "checks and factors", "solve", "assembly")


def report(config: dict, out_dir: Path, *, quick: bool) -> None:
    """Rebuild backends.md, its table CSVs and the figures from backends.csv and
    backends_instances.csv (no new measurement)."""
    out_dir = Path(out_dir)
    rows = _read_csv(out_dir / "backends.csv")
    instances = _read_csv(out_dir / "backends_instances.csv")
    sections = _sections(rows, instances, config, quick, *_run_info(out_dir))
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
    """rows (dicts, or lists in the order of columns when plain) as CSV at path; a value
    that does not apply (NaN: a native backend's own solver time) is an empty cell, as in
    the other studies' CSVs (fuzz4: 'nan' in every row of a run)."""
    with open(path, "w", newline="") as fh:
        if plain:
            writer = csv.writer(fh)
            writer.writerow(columns)
        else:
            writer = csv.DictWriter(fh, fieldnames=columns)
            writer.writeheader()
            rows = [stats.blank_nan(row) for row in rows]
        writer.writerows(rows)


# the columns of the measurement CSVs that hold text, where an empty cell is "" (no
# failure), not a number that does not apply
_TEXT = frozenset({"mode", "call", "backend", "criterion", "kind", "first_failure"})


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v if k in _TEXT else _number(v) for k, v in row.items()}
                for row in csv.DictReader(fh)]


def _number(text: str):
    """A CSV cell back as the int, float or string it was written from; empty: NaN."""
    if text == "":
        return np.nan
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _run_info(out_dir: Path) -> tuple[float, str]:
    """kernel_load_s of the run's machine.json (NaN if there is none) and a sentence on the
    machine's pace at the start and end of the measurement ("" in a run before it was
    measured, or if machine.json does not hold it whole)."""
    try:
        info = json.loads((out_dir / "machine.json").read_text())
    except (OSError, ValueError, RecursionError):
        return np.nan, ""
    try:
        load = float(info["kernel_load_s"])
    except (KeyError, TypeError, ValueError):
        load = np.nan
    try:
        p = {(when, what): float(info["pace_us"][when][what]) for when in ("start", "end")
             for what in ("python_loop", "numpy_inv_4x4")}
    except (KeyError, TypeError, ValueError):
        return load, ""
    return load, (" The machine's pace, to compare runs made in different hours (CPU time "
                  "per call, least of 5 rounds, at the start / end of the measurement): "
                  f"a fixed pure-Python loop {p['start', 'python_loop']:.3g} / "
                  f"{p['end', 'python_loop']:.3g} us, np.linalg.inv of a 4 x 4 "
                  f"{p['start', 'numpy_inv_4x4']:.3g} / {p['end', 'numpy_inv_4x4']:.3g} us.")


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
    return [_target_clarabel(rows), _target_fixed(rows), _target_pairs(rows, instances),
            *_target_batch(rows), _target_large(rows), _target_exact(rows)]


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
    allowed = {key: x[-1] for key, x in _budgets(rows).items() if key in r}
    over = [f"at {sum(x <= 0 for x in allowed.values())} of them the call less its weight "
            "solve, as timed, takes more than Clarabel / 100"] if allowed else []
    return _verdict(target, [f"worst {r[worst]:.3g}x at (n, N) = ({worst[0]}, {worst[1]}) "
                             f"{worst[2]}", f"{sum(x >= 100 for x in r.values())} of "
                             f"{len(r)} points >= 100x", *over], [x >= 100 for x in r.values()])


def _target_fixed(rows) -> list[str]:
    """Issue 11's second point: the call less its weight solve (checks and factors,
    assembly, and the Python around them, warm, as the parts table times them) at (4, 3)."""
    fixed = {key[2]: x[0] - x[2] for key, x in _budgets(rows).items() if key[:2] == (4, 3)}
    return _verdict("fo.bci newton at (n, N) = (4, 3): the call less its weight solve "
                    "(checks, factors, assembly, Python; warm) <= 15 us",
                    [f"{c} {x:.3g} us" for c, x in fixed.items()],
                    [x <= 15 for x in fixed.values()])


def _budgets(rows) -> dict:
    """{(n, N, criterion): (microseconds of each of PART_NAMES, then newton's benchmark
    time, the budget (Clarabel's benchmark time / 100) and the solve allowed (the budget
    less newton's benchmark time less its solve))} for the cells with rows of mode
    "parts"."""
    single = dict(_cells([r for r in rows if r["mode"] == "single"]))
    out = {}
    for key, cell in _cells([r for r in rows if r["mode"] == "parts"]):
        parts = [1e3 * _pooled(cell, (p, REFERENCE), "median_ms") for p in PART_NAMES]
        bench = 1e3 * _pooled(single.get(key, []), (BCI, REFERENCE), "median_ms")
        budget = 10.0 * _pooled(single.get(key, []), (BCI, "clarabel"), "median_ms")
        out[key] = (*parts, bench, budget, budget - (bench - parts[2]))
    return out


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


def _sections(rows, instances, config, quick, kernel_load, pace) -> list:
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
         f"{kernel_load:.3g} s before timing.{pace}", "", "## Targets (issue 11)", ""],
        _Table("targets", ["target", "measured", "verdict"], targets(rows, instances)),
        ["", "## Time per fusion, the user's call (ms)", "",
         "fo.bci per backend and each peer; median over the problems and calls of a cell, "
         "the mean of the kinds' medians.", ""],
        _time_table(single),
        ["", "![Time per fusion against N](backends_time_vs_N.png)", "",
         f"## Speed-up of {REFERENCE}", "", f"Median time of each over that of fo.bci "
         f"{REFERENCE}, both the user's call, on the same problems.", ""],
        _speedup_table(single),
        ["", f"## Where {REFERENCE}'s time goes", "",
         "Microseconds per call, the mean of the kinds' medians. Benchmark: fo.bci newton "
         "in the rotation above (the table of times); warm: the same call repeated 20 "
         "times in a row; then the three parts of its compiled call, timed apart and "
         "warm: checks and factors (`prepare`), the weight solve, the assembly of the "
         "fused estimate and its certificate; rest: warm less the parts (Python, "
         "dispatch). Budget: Clarabel's benchmark time / 100, the target; solve allowed: "
         "the budget less the benchmark time's part that is not the solve (benchmark - "
         "solve); speed-up needed: of the solve alone, to meet the target with "
         "everything else as measured (none: the rest of the call, as the benchmark "
         "times it, is over the budget; part of what a call right after another "
         "solver's pays is the solve's own cache misses, so a faster solve would save "
         "some of that too).", ""],
        _parts_table(rows),
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
        _batch_table([r for r in rows if r["mode"] not in ("single", "large", "parts")])]


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


def _parts_table(rows) -> _Table:
    """newton's time by part per cell (rows of mode "parts") against the target's budget."""
    table = _Table("parts", ["n", "N", "criterion", "benchmark", "warm",
                             "checks and factors", "solve", "assembly", "rest", "budget",
                             "solve allowed", "speed-up needed (x)"], [])
    for key, (warm, checks, solve, assembly, bench, budget, allowed) in _budgets(rows).items():
        table.rows.append([
            *key, *(_fmt(x, ".3g") for x in (bench, warm, checks, solve, assembly,
                                             warm - checks - solve - assembly, budget,
                                             allowed)),
            "none" if allowed <= 0 else _fmt(solve / allowed, ".3g")])
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


def _q(values, q) -> float:
    """The q-th percentile of the finite values (NaN if there is none)."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else np.nan


def _worst(values) -> float:
    """The largest finite value (NaN if there is none)."""
    return _q(values, 100)


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
