"""Campaign (slow): over 10^4 hard problems through every backend of fo.BACKENDS and both
criteria, every result checked against exact arithmetic; and the batched Newton method
at B = 10^5 (issue 9, "Correct on every input").

Problems: the kinds of `conftest.extreme_instance` ("random", "diagonal",
"near-identical", "ill-conditioned", "commuting"), conditions to 1e12, node scales from
1e-300 to 1e300 and up to 1e16 apart within a problem; a quarter of the native batches
are MBCI with p in [0, 1] and chi down to 1e-3. Each backend fuses them with
`fo.fuse_batch`, and each problem again alone with `fo.fuse`. Failures counted by kind:

    error             FusionInputError on a valid input (a conic solver's FusionSolverError
                      is counted apart as solver_error, at most SOLVER_ERROR_SHARE of its
                      problems; a native backend's is a failure, solver_error)
    nonfinite, asymmetric, not_pd, off_simplex, objective_vs_cov   (test_fuzz.check_estimate)
    batch_mismatch    a fuse_batch problem differs from fo.fuse by more than 1e-9 relative
    worse_than_best_node, objective_vs_exact, unverified_improvement (item 9)
    mean_vs_exact     the fused mean off P(w) sum_i w_i Y_i m_i (exact, at the returned
                      weights) by more than test_fuzz.mean_error's bound
    certificate       status "optimal" with an exact relative certificate above 1e-10
                      beyond what the input's own rounding explains (below)
    gap_understated   the reported gap below the exact one, beyond the same

The certificate is recomputed independently of the library by `test_fuzz.Exact`: 80-digit
decimal arithmetic on the inputs exactly as given (no rounding to double anywhere, so the
condition of the nodes costs digits of the 80, not correctness; 80 and 120 digits agree,
test_fuzz.test_exact_reference_is_converged). It is the certificate of the returned
weights for the input as given. A double-precision solver works on the input as rounded
by its Cholesky factors (each node moved by about eps of its norm); where that moves the
exact certificate by more than 1e-10 (nodes ill-conditioned in random rotations: up to
1e-5 at condition 1e12), no double-precision solver can certify the input as given to
1e-10. So a certificate above 1e-10 is measured against `test_fuzz.sensitivity`, the
largest move of the exact certificate over two random perturbations of that size (twenty
where two do not explain it), and fails only if it exceeds ten times that. The summary
reports the worst exact certificate of the optimal results per backend, criterion and kind
(well-conditioned kinds show the solvers' own accuracy), how many optimal results lie above
1e-10 (each explained by its input's sensitivity; the largest ratio of the excess to it)
and the results that are not optimal: a single node returned by the best-vertex rule (the
fused optimum not verifiably better, `assemble.py`) or not.

The summary is printed (pytest -s) and written to campaign.json in pytest's tmp dir.
"""

from __future__ import annotations

import collections
import json
import time
from decimal import Decimal

import numpy as np
import pytest
from conftest import extreme_instance, instance
from test_fuzz import (
    CRITERIA,
    OPTIMAL_RTOL,
    Exact,
    check_estimate,
    exact_scales,
    mean_error,
    sensitivity,
)

import fusion_opt as fo

pytestmark = pytest.mark.slow

KINDS = ("random", "diagonal", "near-identical", "ill-conditioned", "commuting")
# (backend, shapes (N, n), problems per shape and criterion)
PLAN = [
    ("newton", [(2, 2), (2, 4), (3, 3), (3, 4), (5, 2), (5, 6), (8, 3), (8, 4)], 1000),
    ("closed-form", [(2, 1), (2, 2), (2, 3), (2, 4), (2, 6)], 400),
    ("clarabel", [(3, 3), (5, 4), (2, 6), (8, 2)], 100),
    ("clarabel-direct", [(3, 3), (5, 4), (2, 6), (8, 2)], 100),
    ("scs", [(3, 3), (5, 4), (2, 6), (8, 2)], 100),
    ("slsqp", [(3, 3), (5, 4), (2, 6), (8, 2)], 100),
]
BATCH_RTOL = 1e-9
NATIVE = ("newton", "closed-form")  # never a FusionSolverError: each one is a failure
SOLVER_ERROR_SHARE = 0.05  # of a conic backend's problems (counted in the summary)


def _problems(rng, B, N, n, mbci):
    """kinds (B,), means (B, N, n), covs (B, N, n, n) and MBCI's p_detect and chi (B, N)
    (None for BCI): node scales spread up to 1e16 around 10^U(-300, 300), the largest
    entry at most 1e300."""
    kinds, covs = [], []
    for _ in range(B):
        kind = str(rng.choice(KINDS))
        log10_cond = float(rng.uniform(0, 12)) if kind != "random" else 0.0
        spread = float(rng.choice([0.0, 4.0, 16.0]))
        base = rng.uniform(-300 + spread / 2 + 2, 300 - log10_cond - spread / 2 - 1)
        kinds.append(kind)
        covs.append(extreme_instance(rng, N, n, kind, log10_cond=log10_cond, base=base,
                                     spread=spread))
    means = rng.standard_normal((B, N, n)) * 10.0 ** rng.uniform(-100, 100, (B, 1, 1))
    args = {}
    if mbci:
        args = {"p_detect": rng.uniform(0, 1, (B, N)),
                "chi": 10.0 ** -rng.uniform(0, 3, (B, N))}
    return kinds, means, np.stack(covs), args


class Tally:
    """Counts per (backend, criterion): instances, statuses, failures by kind, the worst
    exact certificate of optimal results per kind of problem, wall time."""

    def __init__(self):
        self.rows = collections.defaultdict(lambda: {
            "instances": 0, "optimal": 0, "inaccurate_single_node": 0,
            "inaccurate_fused": 0, "solver_error": 0, "failures": collections.Counter(),
            "optimal_above_1e-10_by_sensitivity": 0, "worst_certificate": {},
            "largest_excess_over_sensitivity": 0.0, "kinds_above_1e-10": collections.Counter(),
            "batch_not_bitwise": 0, "batch_solver_error": 0,
            "seconds": 0.0})
        self.examples, self.not_optimal = [], []

    def fail(self, key, kind, detail):
        self.rows[key]["failures"][kind] += 1
        if len(self.examples) < 20:
            self.examples.append({"where": "/".join(key), "failure": kind,
                                  "detail": str(detail)[:300]})

    def summary(self) -> dict:
        out = {}
        for (backend, criterion), row in sorted(self.rows.items()):
            row = dict(row)
            row["failures"] = dict(row["failures"])
            row["kinds_above_1e-10"] = dict(row["kinds_above_1e-10"])
            out[f"{backend}/{criterion}"] = row
        return out


def _batch_rel(a, b) -> float:
    """Largest difference relative to the size of b (arrays or scalars)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), np.finfo(float).tiny))


def _audit(tally, key, kind, r_b, r_one, means, covs, criterion, scales):
    """Every check of the module docstring on one problem: r_b the problem's part of the
    batch result (a FusionResult-like namespace), r_one fo.fuse's result."""
    N, n = covs.shape[:2]
    trace = criterion == "trace"
    row = tally.rows[key]
    row["instances"] += 1
    if r_one is not None:
        diffs = [_batch_rel(getattr(r_b, k), getattr(r_one, k))
                 for k in ("weights", "mean", "cov", "objective")]
        if max(diffs) > BATCH_RTOL or r_b.status != r_one.status:
            tally.fail(key, "batch_mismatch", diffs)
        elif max(diffs) > 0:
            row["batch_not_bitwise"] += 1
    try:
        check_estimate(r_b, N, n, trace)
    except (AssertionError, np.linalg.LinAlgError) as exc:
        tally.fail(key, _estimate_failure(r_b, exc), exc)
        return
    rel_reported = r_b.gap / abs(r_b.objective) if trace else r_b.gap
    optimal = r_b.status == fo.Status.OPTIMAL
    single = bool((r_b.weights == 1.0).any())
    ex = Exact(covs, scales)
    f, rel = ex.at(r_b.weights, trace)
    if optimal:
        row["optimal"] += 1
    else:
        row["inaccurate_single_node" if single else "inaccurate_fused"] += 1
        if len(tally.not_optimal) < 30:
            tally.not_optimal.append({"where": "/".join(key), "kind": kind, "N": N, "n": n,
                                      "single_node": single, "gap": rel_reported,
                                      "exact_gap": float(rel)})
    best = min(ex.vertices(trace))
    scale = float(abs(f)) if trace else max(float(abs(f)), 1.0)
    tol = max(1e-9, 64 * n * np.finfo(float).eps * np.linalg.cond(covs).max()) * scale
    if abs(float(f) - r_b.objective) > tol:
        tally.fail(key, "objective_vs_exact", (r_b.objective, float(f)))
    if r_b.objective > float(best) + tol:
        tally.fail(key, "worse_than_best_node", (r_b.objective, float(best)))
    if not single and not f < best:
        tally.fail(key, "unverified_improvement", (float(f), float(best)))
    err, bound = mean_error(r_b, means, covs, ex)
    if err > bound:
        tally.fail(key, "mean_vs_exact", (float(err), float(bound)))
    rel = float(rel)
    if optimal:
        worst = row["worst_certificate"]
        worst[kind] = max(worst.get(kind, 0.0), rel)
    over = max(rel - OPTIMAL_RTOL if optimal else 0.0,
               rel - 2 * rel_reported - OPTIMAL_RTOL / 2)
    if over > 0:  # (its own generator: the problems drawn do not depend on the checks)
        rng = np.random.default_rng(0)
        moved = sensitivity(covs, r_b.weights, trace, rng, scales)
        if over > moved:  # two random directions can miss the sensitive one: look harder
            moved = max(moved, sensitivity(covs, r_b.weights, trace, rng, scales, 20))
        if over > 10 * moved:
            failure = "certificate" if rel > OPTIMAL_RTOL and optimal else "gap_understated"
            tally.fail(key, failure, (kind, rel, rel_reported, moved))
        elif optimal and rel > OPTIMAL_RTOL:
            row["optimal_above_1e-10_by_sensitivity"] += 1
            row["largest_excess_over_sensitivity"] = max(
                row["largest_excess_over_sensitivity"], over / moved)
            row["kinds_above_1e-10"][kind] += 1


def _estimate_failure(r, exc) -> str:
    if not all(np.isfinite(np.asarray(getattr(r, k), dtype=float)).all()
               for k in ("weights", "mean", "cov", "objective", "gap")):
        return "nonfinite"
    if not np.array_equal(r.cov, r.cov.T):
        return "asymmetric"
    if isinstance(exc, np.linalg.LinAlgError):
        return "not_pd"
    w = r.weights
    if (w < 0).any() or abs(w.sum() - 1.0) > 4 * len(w) * np.finfo(float).eps:
        return "off_simplex"
    return "objective_vs_cov"


class _One:
    """Problem b of a BatchFusionResult, with FusionResult's attribute names."""

    def __init__(self, r, b):
        self.weights, self.mean, self.cov = r.weights[b], r.mean[b], r.cov[b]
        self.objective, self.gap, self.status = float(r.objective[b]), float(r.gap[b]), \
            r.status[b]
        self.weights_are = r.weights_are


def _run(tally, backend, criterion, N, n, B, mbci, rng):
    """B problems through fuse_batch and fo.fuse, each audited (instances counts only the
    audited ones). A FusionSolverError of a native backend is a failure; a conic solver's
    is counted (solver_error, batch_solver_error: the batch stops at its first), and the
    campaign bounds their share (SOLVER_ERROR_SHARE)."""
    kinds, means, covs, args = _problems(rng, B, N, n, mbci)
    method = "mbci" if mbci else "bci"
    key, native = (backend, criterion), backend in NATIVE
    row = tally.rows[key]
    t0 = time.perf_counter()
    try:
        r = fo.fuse_batch(means, covs, method, criterion, backend, **args)
    except fo.FusionSolverError as exc:
        r = None  # then only problem by problem: no batch to compare with
        row["batch_solver_error"] += 1
        if native:
            tally.fail(key, "solver_error", exc)
    row["seconds"] += time.perf_counter() - t0
    for b in range(B):
        one_args = {k: v[b] for k, v in args.items()}
        scales = exact_scales(args["p_detect"][b], args["chi"][b], N) if mbci else None
        try:
            t0 = time.perf_counter()
            one = fo.fuse(means[b], covs[b], method, criterion, backend, **one_args)
            row["seconds"] += time.perf_counter() - t0
        except fo.FusionSolverError as exc:
            row["solver_error"] += 1
            assert backend in str(exc)
            if native:
                tally.fail(key, "solver_error", exc)
            continue
        except fo.FusionInputError as exc:
            row["instances"] += 1
            tally.fail(key, "error", exc)
            continue
        if r is None:
            _audit(tally, key, kinds[b], one, None, means[b], covs[b], criterion, scales)
        else:
            _audit(tally, key, kinds[b], _One(r, b), one, means[b], covs[b], criterion, scales)


def test_campaign_every_backend_and_criterion(tmp_path):
    t_start = time.perf_counter()
    tally = Tally()
    rng = np.random.default_rng(2026)
    for backend, shapes, per_shape in PLAN:
        for criterion in CRITERIA:
            for N, n in shapes:
                native = backend in NATIVE
                chunks = 4 if native else 1
                for c in range(chunks):
                    _run(tally, backend, criterion, N, n, per_shape // chunks,
                         native and c == 0, rng)
    summary = {"instances": sum(r["instances"] for r in tally.rows.values()),
               "wall_seconds": round(time.perf_counter() - t_start, 1),
               "rows": tally.summary(), "failure_examples": tally.examples,
               "not_optimal_examples": tally.not_optimal}
    text = json.dumps(summary, indent=1, default=float)
    (tmp_path / "campaign.json").write_text(text)
    print("\n" + _table(summary) + f"\n(JSON: {tmp_path / 'campaign.json'})")
    for example in tally.not_optimal:
        print("not optimal:", example)
    assert summary["instances"] >= 10_000
    failures = {k: r["failures"] for k, r in summary["rows"].items() if r["failures"]}
    assert not failures, (failures, tally.examples)
    for key, r in summary["rows"].items():  # a conic solver may fail, but rarely
        tried = r["instances"] + r["solver_error"]
        assert r["solver_error"] <= SOLVER_ERROR_SHARE * tried, (key, r["solver_error"], tried)


def _table(summary) -> str:
    lines = [f"campaign: {summary['instances']} problems in {summary['wall_seconds']} s",
             f"{'backend/criterion':24} {'n':>5} {'opt':>5} {'1node':>5} {'fused':>5} "
             f"{'serr':>4} {'>1e-10*':>7} {'time s':>7}  worst exact certificate of optimal "
             "results by kind; failures"]
    for key, r in summary["rows"].items():
        worst = ", ".join(f"{k} {v:.1e}" for k, v in sorted(r["worst_certificate"].items()))
        lines.append(
            f"{key:24} {r['instances']:5d} {r['optimal']:5d} "
            f"{r['inaccurate_single_node']:5d} {r['inaccurate_fused']:5d} "
            f"{r['solver_error']:4d} {r['optimal_above_1e-10_by_sensitivity']:7d} "
            f"{r['seconds']:7.1f}  {worst}; {r['failures'] or 'none'}")
        if r["optimal_above_1e-10_by_sensitivity"]:
            lines.append(f"{'':24} optimal above 1e-10 by kind {r['kinds_above_1e-10']}, "
                         f"largest (certificate - 1e-10) / sensitivity "
                         f"{r['largest_excess_over_sensitivity']:.2g}")
    lines.append("opt: optimal; 1node: optimal_inaccurate, a single node by the best-vertex "
                 "rule; fused: optimal_inaccurate otherwise; serr: FusionSolverError; "
                 ">1e-10*: optimal results whose exact certificate exceeds 1e-10 within 10x "
                 "their input's own sensitivity")
    return "\n".join(lines)


# --- the batched Newton method at B = 10^5 (issue 9, item 2) ----------------------------

def _batch(n, N, kind):
    """The B = 10^5 batch of issue 9, item 2: conftest.instance with a seed per shape."""
    rng = np.random.default_rng([n, N, len(kind)])
    covs = instance(rng, 100_000 * N, n, kind).reshape(100_000, N, n, n)
    return rng.standard_normal((100_000, N, n)), covs


@pytest.mark.parametrize("kind", ["random", "ill-conditioned"])
@pytest.mark.parametrize("n,N", [(4, 3), (6, 8)])
def test_batched_newton_at_B_1e5(n, N, kind):
    """Issue 9, item 2: every problem optimal, also on "ill-conditioned" (eigenvalues over
    1e-6..1e6, nodes 1e6 apart)."""
    means, covs = _batch(n, N, kind)
    for criterion in CRITERIA:
        t0 = time.perf_counter()
        r = fo.fuse_batch(means, covs, "bci", criterion)
        seconds = time.perf_counter() - t0
        bad = np.flatnonzero(r.status != fo.Status.OPTIMAL)
        print(f"\nB = 1e5, (n, N) = ({n}, {N}), {kind}, {criterion}: {len(bad)} not optimal "
              f"{bad.tolist()}, largest iteration count {r.iterations.max()}, {seconds:.1f} s")
        assert bad.tolist() == []


def test_the_best_vertex_rule_verifies_small_improvements_at_condition_3e8():
    """Problems 46723 and 57613 of the (4, 3) "ill-conditioned" batch: the SQP's optimum
    beats the best node by 4.8e-6 and 5.9e-7 in log det, which the first test of
    assemble.py cannot verify (its bound, c n eps times the condition 3e8 of the best node,
    is 2 x 2.5e-6 and 2 x 1.0e-6) and the difference in the node's whitened coordinates
    does (bounds 1.3e-11 and 2.2e-11); exact arithmetic confirms the improvement."""
    means, covs = _batch(4, 3, "ill-conditioned")
    index = [46723, 57613]
    r = fo.fuse_batch(means[index], covs[index], "bci", "logdet")
    assert (r.status == fo.Status.OPTIMAL).all() and (r.weights < 1).all()
    for b, i in enumerate(index):
        ex = Exact(covs[i])
        f, _ = ex.at(r.weights[b], False)
        assert f < min(ex.vertices(False)) - Decimal("1e-7")
