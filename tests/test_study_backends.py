"""The backend benchmark runs end to end on a tiny config, measures every solver where it
applies, computes its gaps independently of the solvers; its peers are right (against
brute force on a grid and a second solver); the performance profile and the targets
table follow from hand-made tables."""

import csv
import itertools
import json
import re

import numpy as np
import pytest

import fusion_opt as fo
from fusion_opt import FusionSolverError
from fusion_opt.backends import REGISTRY, WeightSolution
from studies import backends, backends_report, config, peers
from studies.backends_report import BCI, CI, RAW


def _tiny(**over) -> dict:
    c = config.load("backends", quick=True)
    c.update(n=[2], N=[2, 3], instances=2, repeats=1, batch_size=30, batch_small=10,
             batch_shapes=[[3, 2], [4, 3]], batch_repeats=1, batch_check=3, large=[[3, 4]],
             large_instances=1)
    c.update(over)
    backends.check(c)
    return c


def _rows(path, name="backends.csv") -> list[dict]:
    with open(path / name, newline="") as fh:
        return list(csv.DictReader(fh))


def test_backends_study_writes_outputs(tmp_path):
    c = _tiny()
    backends.run(c, tmp_path, quick=True, progress=False)
    tables = ("targets", "time", "speedup", "parts", "pairs", "accuracy", "large", "batch")
    for name in ("backends.csv", "backends_instances.csv", "backends.md",
                 "backends_time_vs_N.png", "backends_profile.png", "machine.json",
                 *(f"backends_{t}.csv" for t in tables)):
        assert (tmp_path / name).stat().st_size > 0
    rows = _rows(tmp_path)
    single = [r for r in rows if r["mode"] == "single"]
    # each call once per cell where it applies: fo.ci, closed-form, minimize_scalar at N = 2
    want = set()
    for N in c["N"]:
        calls = [(BCI, b) for b in c["backends"] if b != "closed-form" or N == 2]
        calls += [(CI, b) for b in c["backends"] if N == 2]
        calls += [(RAW, b) for b in c["backends"] if b in REGISTRY]
        calls += [(p, "-") for p in c["peers"] if p != "minimize_scalar" or N == 2]
        want |= {(*call, N, crit, kind) for call in calls for crit in c["criteria"]
                 for kind in c["kinds"]}
    got = [(r["call"], r["backend"], int(r["N"]), r["criterion"], r["kind"]) for r in single]
    assert sorted(got) == sorted(want)
    assert all(int(r["solves"]) == c["instances"] for r in single)  # repeats = 1
    instances = _rows(tmp_path, "backends_instances.csv")
    large = [r for r in rows if r["mode"] == "large"]
    assert len(instances) == c["instances"] * len(single) + c["large_instances"] * len(large)
    exact = [r for r in rows if r["backend"] in ("newton", "closed-form")]
    assert max(float(r["worst_optimality_gap"]) for r in exact
               if r["worst_optimality_gap"]) <= 1e-10  # empty: not measured (parts rows)
    assert all(int(r["failures"]) == 0 for r in exact)
    certified = [r for r in single if r["call"] in (BCI, CI)]
    assert max(float(r["worst_objective_gap"]) for r in certified) < 1e-9  # all measured
    # the conic backends report their solver's own time
    assert all(np.isfinite(float(r["solver_own_median_ms"])) for r in single
               if r["backend"] == "clarabel")
    assert {(r["backend"], r["criterion"]) for r in large} == {
        (b, crit) for b in c["large_backends"] for crit in c["criteria"]}
    # fuse_batch (B and batch_small) per native backend, the floor, loops of fo.bci
    # newton's parts: each of them once per single cell, timed, a part of the whole call
    parts = [r for r in rows if r["mode"] == "parts"]
    cells = {(r["N"], r["criterion"], r["kind"]) for r in single}
    assert sorted((r["call"], r["N"], r["criterion"], r["kind"]) for r in parts) == sorted(
        (p, *cell) for p in backends_report.PART_NAMES for cell in cells)
    for cell in cells:
        t = {r["call"]: float(r["median_ms"]) for r in parts
             if (r["N"], r["criterion"], r["kind"]) == cell}
        assert all(0 < x < np.inf for x in t.values())
        assert t["solve"] < t["fo.bci (warm)"]
    batch = {(r["mode"], r["backend"], r["N"]) for r in rows if r["mode"] not in
             ("single", "large", "parts")}
    natives = {2: ("newton", "closed-form"), 3: ("newton",)}
    assert batch == {(m, b, str(N)) for N in (2, 3) for m, bs in
                     (("batch", natives[N]), ("batch-small", natives[N]),
                      ("inverse", ("numpy",)),
                      ("loop", [b for b in c["backends"] if b != "closed-form" or N == 2]))
                     for b in bs}
    text = (tmp_path / "backends.md").read_text()
    assert "## Targets" in text and "| fo.bci newton at n = 48" in text
    assert "## Where newton's time goes" in text
    assert "the call less its weight solve, as timed" in \
        (tmp_path / "backends_targets.csv").read_text()
    # a value that does not apply is an empty cell, as in the other studies' CSVs (fuzz4:
    # "nan" in every row), and reads back as NaN
    for name in ("backends.csv", "backends_instances.csv"):
        assert "nan" not in (tmp_path / name).read_text().lower()
    assert all(np.isnan(r["solver_own_median_ms"]) for r in backends_report._read_csv(
        tmp_path / "backends.csv") if r["backend"] == "newton" and r["mode"] == "single")
    # `report` rebuilds the tables from the CSVs alone, without measuring again
    targets = (tmp_path / "backends_targets.csv").read_text()
    for name in ("backends.md", "backends_targets.csv"):
        (tmp_path / name).unlink()
    backends.report(c, tmp_path, quick=True)
    assert (tmp_path / "backends.md").read_text() == text
    assert (tmp_path / "backends_targets.csv").read_text() == targets
    # the machine's pace at the start and end, stored and stated; a run stored before it
    # was measured (or whose machine.json lost it) is reported without it
    info = json.loads((tmp_path / "machine.json").read_text())
    pace = info["pace_us"]
    assert all(0 < pace[w][k] < 1e4 for w in ("start", "end")
               for k in ("python_loop", "numpy_inv_4x4"))
    stated = re.search(r"a fixed pure-Python loop (\S+) / (\S+) us", text)
    assert stated and float(stated[1]) == float(f"{pace['start']['python_loop']:.3g}")
    for damaged in ({k: v for k, v in info.items() if k != "pace_us"},
                    {**info, "pace_us": {"start": pace["start"]}}):
        (tmp_path / "machine.json").write_text(json.dumps(damaged))
        backends.report(c, tmp_path, quick=True)
        assert (tmp_path / "backends.md").read_text() == text.replace(
            text[text.index(" The machine's pace"):text.index(" us.\n") + 4], "")


def _vertex(Ys, M, criterion):
    """A spoiled backend: all the weight on node 0, reported as optimal."""
    w = np.zeros(len(Ys))
    w[0] = 1.0
    return WeightSolution(w, "optimal", 1, 0.0)


def test_a_spoiled_backend_shows_as_a_large_gap(tmp_path, monkeypatch):
    """The gaps are computed from the returned weights, not from what a backend says."""
    monkeypatch.setitem(REGISTRY, "slsqp", _vertex)
    c = _tiny(N=[3], criteria=["trace"], kinds=["random"], backends=["newton", "slsqp"],
              peers=[], large=[], batch_shapes=[])
    backends.run(c, tmp_path, quick=True, progress=False)
    single = {(r["call"], r["backend"]): r for r in _rows(tmp_path) if r["mode"] == "single"}
    assert float(single[RAW, "slsqp"]["worst_objective_gap"]) > 1e-3
    assert float(single[RAW, "slsqp"]["worst_optimality_gap"]) > 1e-3
    # newton's own weights, and the spoiled ones polished by Newton from a vertex: the
    # same optimum, to rounding (either may be the "best" by an ulp)
    assert float(single[BCI, "newton"]["worst_objective_gap"]) <= 1e-15
    assert float(single[BCI, "slsqp"]["worst_objective_gap"]) <= 1e-15


def test_a_failing_backend_is_counted_not_fatal(tmp_path, monkeypatch):
    def fails(Ys, M, criterion):
        raise FusionSolverError("slsqp", "status_8", "spoiled on purpose")

    monkeypatch.setitem(REGISTRY, "slsqp", fails)
    c = _tiny(N=[3], kinds=["random"], backends=["newton", "slsqp"], peers=[], large=[],
              batch_shapes=[[2, 3]])
    backends.run(c, tmp_path, quick=True, progress=False)
    rows = [r for r in _rows(tmp_path) if r["backend"] == "slsqp"]
    assert rows and all(int(r["failures"]) == c["instances"] if r["mode"] == "single"
                        else int(r["failures"]) == c["batch_check"] for r in rows)
    assert all("status_8" in r["first_failure"] for r in rows)
    assert all(r["worst_objective_gap"] == "" for r in rows)  # none: an empty cell
    assert "status_8" in (tmp_path / "backends.md").read_text()


@pytest.mark.parametrize("bad,message", [
    ({"backends": ["newton", "gurobi"]}, "backends[1] must be one of"),
    ({"peers": ["cvxopt"]}, "peers[0] must be one of"),
    ({"batch_check": 0}, "batch_check must be an integer >= 1"),
    ({"N": [1, 2]}, "N[0] must be an integer >= 2"),
    ({"kinds": ["random", "random"]}, "kinds lists ['random'] more than once"),
    ({"backends": ["closed-form"], "N": [3]}, "fuses N = 2 only"),
    ({"large": [[48]]}, "large[0] must be a list [n, N]"),
    ({"batch_shapes": [[4, 1]]}, "batch_shapes[0][1] (N) must be an integer >= 2"),
    ({"batch_shapes": [[4, 3], [4, 3]]}, "batch_shapes lists a shape more than once"),
    ({"batch_small": 3000}, "batch_small must be <= batch_size"),
    ({"batch_check": 3000}, "batch_check must be <= batch_size (2000), got 3000"),  # fuzz4
    ({"profile_tolerances": [0]}, "profile_tolerances[0] must be a finite number > 0"),
    ({"repeat_budget_ms": "20"}, "repeat_budget_ms must be a finite number > 0"),
    ({"large_backends": ["mosek"]}, "large_backends[0] must be one of"),
])
def test_check_names_the_bad_field(bad, message):
    with pytest.raises(config.ConfigError, match=re.escape(message)):
        backends.check(config.load("backends", quick=True) | bad)


def test_closed_form_and_pair_peers_are_skipped_beyond_pairs():
    c = config.load("backends", quick=True) | {"N": [3, 7]}
    backends.check(c)
    got = {(s.call, s.backend) for s in backends._solvers(c["backends"], c["peers"], 3)}
    assert not {s for s in got if "closed-form" in s or "minimize_scalar" in s or CI in s}
    assert (BCI, "newton") in got and ("scipy-slsqp", "-") in got


def test_ill_conditioned_instances_are_spd_and_ill_conditioned():
    P = backends.instance(np.random.default_rng(0), 5, 4, "ill-conditioned")
    assert np.allclose(P, np.swapaxes(P, -1, -2)) and np.linalg.eigvalsh(P).min() > 0
    assert np.linalg.cond(P).max() > 1e6


# --------------------------------------------------------------------------- the peers

def _pair_objective(Y_a, Y_b, w, criterion):
    """f at each of w (K,) by numpy, broadcast over the grid."""
    Y = w[:, None, None] * Y_a + (1 - w[:, None, None]) * Y_b
    if criterion == "trace":
        return np.trace(np.linalg.inv(Y), axis1=1, axis2=2)
    return -np.linalg.slogdet(Y)[1]


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_minimize_scalar_peer_matches_a_grid_and_never_beats_closed_form(criterion):
    rng = np.random.default_rng(7)
    for _ in range(5):
        means, covs = rng.standard_normal((2, 3)), backends.instance(rng, 2, 3, "random")
        peer = peers.minimize_scalar_peer(means[0], covs[0], means[1], covs[1], criterion)
        Y_a, Y_b = np.linalg.inv(covs)
        grid = np.linspace(0.0, 1.0, 200_001)  # step 5e-6 on w
        f_grid = _pair_objective(Y_a, Y_b, grid, criterion).min()
        f_peer = _pair_objective(Y_a, Y_b, peer.weights[:1], criterion)[0]
        assert peer.ok and peer.weights.sum() == pytest.approx(1.0, abs=1e-15)
        assert abs(f_peer - f_grid) <= 1e-6 * abs(f_grid)
        best = fo.ci(means[0], covs[0], means[1], covs[1], criterion, "closed-form")
        assert f_peer >= best.objective - 1e-12 * abs(best.objective)
        # the fused estimate is CI's at the peer's weight
        w = peer.weights[0]
        P = np.linalg.inv(w * Y_a + (1 - w) * Y_b)
        assert np.allclose(peer.cov, P) and np.allclose(
            peer.mean, P @ (w * Y_a @ means[0] + (1 - w) * Y_b @ means[1]))


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_slsqp_peer_is_on_the_simplex_and_near_a_simplex_grid_minimum(criterion):
    rng = np.random.default_rng(3)
    means, covs = rng.standard_normal((3, 2)), backends.instance(rng, 3, 2, "random")
    peer = peers.slsqp_peer(means, covs, criterion)
    w = peer.weights
    assert peer.ok and abs(w.sum() - 1) < 1e-9 and (w >= -1e-12).all() and (w <= 1).all()
    Ys = np.linalg.inv(covs)
    a, b = np.meshgrid(np.linspace(0, 1, 801), np.linspace(0, 1, 801))
    W = np.stack([a.ravel(), b.ravel(), 1 - a.ravel() - b.ravel()], 1)
    W = W[W[:, 2] >= 0]  # a grid of the simplex, step 1/800

    def f(W):
        Y = np.einsum("ki,ijl->kjl", W, Ys)
        return (np.trace(np.linalg.inv(Y), axis1=1, axis2=2) if criterion == "trace"
                else -np.linalg.slogdet(Y)[1])

    f_grid, f_peer = f(W).min(), f(w[None])[0]
    exact = fo.bci(means, covs, criterion).objective
    assert exact - 1e-12 * abs(exact) <= f_peer <= f_grid + 1e-9 * abs(f_grid)
    assert f_peer - exact <= 1e-5 * abs(exact)  # default tolerances: close, not exact


def test_fixed_weights_peer_is_ci_with_equal_weights():
    rng = np.random.default_rng(1)
    means, covs = rng.standard_normal((2, 3)), backends.instance(rng, 2, 3, "random")
    peer = peers.fixed_weights_peer(means, covs, "trace")
    Y_a, Y_b = np.linalg.inv(covs)
    P = np.linalg.inv(0.5 * Y_a + 0.5 * Y_b)  # Stone Soup's omega = 0.5
    assert np.array_equal(peer.weights, [0.5, 0.5]) and np.allclose(peer.cov, P)
    assert np.allclose(peer.mean, P @ (0.5 * Y_a @ means[0] + 0.5 * Y_b @ means[1]))


# ------------------------------------------------------------ profile and targets

def test_performance_profile_of_a_hand_made_table():
    inf = np.inf
    times = np.array([[1.0, 2.0, inf],   # best 1: ratios 1, 2, inf
                      [4.0, 2.0, 8.0],   # best 2: ratios 2, 1, 4
                      [inf, inf, inf],   # no solver: unsolved by all
                      [3.0, 3.0, 3.0]])  # a tie: ratio 1 for all
    rho = backends_report.performance_profile(times, [1.0, 1.5, 2.0, 4.0, 100.0])
    assert rho.tolist() == [[0.5, 0.5, 0.75, 0.75, 0.75],
                            [0.5, 0.5, 0.75, 0.75, 0.75],
                            [0.25, 0.25, 0.25, 0.5, 0.5]]


def _instance(call, backend, problem, time_ms, gap, failed=0, N=2):
    return {"mode": "single", "call": call, "backend": backend, "n": 2, "N": N,
            "criterion": "trace", "kind": "random", "problem": problem, "time_ms": time_ms,
            "objective_gap": gap, "optimality_gap": 0.0, "failed": failed}


def test_profile_times_count_failures_and_loose_answers_as_unsolved():
    rows = [_instance(BCI, "newton", 0, 1.0, 0.0), _instance(BCI, "newton", 1, 2.0, 0.0),
            _instance("minimize_scalar", "-", 0, 5.0, 1e-9),
            _instance("minimize_scalar", "-", 1, 5.0, 0.0, failed=1),
            _instance(CI, "newton", 0, 0.5, 0.0),  # fo.ci and polish=False: not profiled
            _instance(RAW, "clarabel", 0, 0.5, 0.0)]
    labels, times = backends_report.profile_times(rows, 1e-6)
    assert labels == ["newton", "minimize_scalar"]
    assert times.tolist() == [[1.0, 5.0], [2.0, np.inf]]
    assert backends_report.profile_times(rows, 1e-12)[1].tolist() == [[1.0, np.inf],
                                                                      [2.0, np.inf]]


def _row(mode, call, backend, n, N, criterion, median_ms, **more):
    base = {"mode": mode, "call": call, "backend": backend, "n": n, "N": N,
            "criterion": criterion, "kind": "random", "per_call": 1, "solves": 1,
            "median_ms": median_ms, "worst_objective_gap": 0.0,
            "worst_optimality_gap": 0.0, "failures": 0}
    return base | more


def _measured(fast_enough: bool) -> list[dict]:
    """A run in which every target is met (or, if not fast_enough, each missed by a
    little)."""
    k = 1.0 if fast_enough else 0.9
    rows = []
    for crit in ("trace", "logdet"):
        rows += [_row("single", BCI, "newton", 4, 3, crit, 0.01),
                 _row("single", BCI, "clarabel", 4, 3, crit, 1.0 * k),  # 100x
                 _row("single", BCI, "clarabel", 12, 3, crit, 0.2),  # n > 6: not a target
                 _row("single", BCI, "newton", 12, 3, crit, 0.01),
                 _row("single", CI, "closed-form", 4, 2, crit, 0.01),
                 _row("single", "minimize_scalar", "-", 4, 2, crit, 0.1 * k),  # 10x
                 _row("batch", "fo.fuse_batch", "newton", 4, 3, crit, 15e-3 / k,
                      per_call=10000),
                 _row("inverse", "np.linalg.inv", "numpy", 4, 3, crit, 1e-3,
                      per_call=10000),  # 15x
                 _row("batch-small", "fo.fuse_batch", "newton", 4, 3, crit, 45e-3 / k**2,
                      per_call=10),  # 3x the large batch's
                 _row("large", BCI, "newton", 48, 8, crit, 1.0),
                 _row("large", BCI, "clarabel", 48, 8, crit, 50.0 * k)]
        # the call less its solve: 15 us (16.5 us), of a warm 20 us
        rows += [_row("parts", part, "newton", 4, 3, crit, t) for part, t in
                 zip(backends_report.PART_NAMES, (20e-3, 3e-3, (5 - 1.5 * (1 - k) / 0.1)
                                                  * 1e-3, 4e-3), strict=True)]
    return rows


def test_targets_are_met_exactly_at_their_bounds_and_missed_below():
    instances = [_instance(CI, "closed-form", k, 0.01, 0.0) for k in range(3)]
    instances += [_instance("minimize_scalar", "-", k, 0.1, 1e-9) for k in range(3)]
    met = backends_report.targets(_measured(True), instances)
    assert [t[2] for t in met] == ["met"] * 7
    assert "worst 100x at (n, N) = (4, 3) trace; 2 of 2 points >= 100x" in met[0][1]
    assert met[1][1] == "trace 15 us; logdet 15 us"
    missed = backends_report.targets(_measured(False), instances)
    assert [t[2] for t in missed] == ["missed"] * 6 + ["met"]
    assert "worst 90x" in missed[0][1] and "trace 16.5 us" in missed[1][1]
    assert "trace 9x" in missed[2][1]
    # an objective worse than minimize_scalar's on one problem misses target 2
    worse = instances + [_instance(CI, "closed-form", 3, 0.01, 1e-9),
                         _instance("minimize_scalar", "-", 3, 0.1, 0.0)]
    assert backends_report.targets(_measured(True), worse)[2][2] == "missed"
    assert "on 1 of 4 pair problems" in backends_report.targets(_measured(True), worse)[2][1]
    # a newton failure or a loose certificate misses the exactness target
    spoiled = _measured(True) + [_row("single", BCI, "newton", 2, 2, "trace", 0.01,
                                      failures=1)]
    assert backends_report.targets(spoiled, instances)[-1][2] == "missed"
    assert [t[2] for t in backends_report.targets([], [])] == ["not measured"] * 7


def test_weights_off_the_simplex_are_put_on_it_before_the_gaps():
    """Weights summing to more than one fuse more information than there is: scaled up
    from the optimum they must not look better than it; their violation is reported."""
    rng = np.random.default_rng(4)
    covs = backends.instance(rng, 3, 2, "random")
    w = fo.bci(np.zeros((3, 2)), covs).weights
    (gap, cert, off), (gap_up, cert_up, off_up) = backends._accuracy(
        covs[None], [w[None], (1 + 1e-6) * w[None]], "trace")
    assert abs(gap_up[0]) <= 1e-14 and abs(gap[0]) <= 1e-14 and cert_up[0] <= 1e-12
    assert off[0] <= 1e-15 and off_up[0] == pytest.approx(1e-6, rel=1e-6)


def test_the_parts_table_leaves_the_solve_what_the_rest_of_the_call_does_not_take():
    # budget: Clarabel's 1 ms / 100 = 10 us; newton's benchmark 10 us, of which the solve
    # takes 4 at (4, 3) (allowed 4 us, speed-up 1x) and 2 at (4, 7) (the rest alone, 8 us
    # of the 5 us budget there, leaves nothing)
    rows = []
    for N, clarabel, solve in ((3, 1.0, 4e-3), (7, 0.5, 2e-3)):
        rows += [_row("single", BCI, "newton", 4, N, "trace", 0.01),
                 _row("single", BCI, "clarabel", 4, N, "trace", clarabel)]
        rows += [_row("parts", p, "newton", 4, N, "trace", t) for p, t in
                 zip(backends_report.PART_NAMES, (9e-3, 1e-3, solve, 2e-3), strict=True)]
    table = backends_report._parts_table(rows)
    assert table.rows == [
        [4, 3, "trace", "10", "9", "1", "4", "2", "2", "10", "4", "1"],
        [4, 7, "trace", "10", "9", "1", "2", "2", "4", "5", "-3", "none"]]
    assert "; at 1 of them the call less its weight solve, as timed, takes more than " \
        "Clarabel / 100" in backends_report.targets(rows, [])[0][1]
    # a store from before the parts were measured: no table, and the target says nothing
    # of them
    plain = [r for r in rows if r["mode"] != "parts"]
    assert backends_report._parts_table(plain).markdown() == ["Not measured in this run."]
    assert "weight solve" not in backends_report.targets(plain, [])[0][1]


def test_a_problem_newton_refuses_leaves_its_parts_unmeasured_not_the_run(tmp_path,
                                                                        monkeypatch):
    real = fo.bci

    def refuses(means, covs, criterion="trace", backend=None, **kwargs):
        if backend == "newton":
            raise fo.FusionInputError("refused on purpose")
        return real(means, covs, criterion, backend, **kwargs)

    monkeypatch.setattr(fo, "bci", refuses)
    c = _tiny(N=[3], kinds=["random"], criteria=["trace"], backends=["newton", "clarabel"],
              peers=[], large=[], batch_shapes=[[2, 3]])
    backends.run(c, tmp_path, quick=True, progress=False)
    parts = [r for r in _rows(tmp_path) if r["mode"] == "parts"]
    assert len(parts) == len(backends_report.PART_NAMES)
    assert all(r["median_ms"] == "" for r in parts)
    newton = [r for r in _rows(tmp_path) if (r["mode"], r["call"], r["backend"]) ==
              ("single", BCI, "newton")]
    assert [r["failures"] for r in newton] == [str(c["instances"])]
    table = (tmp_path / "backends_parts.csv").read_text().splitlines()
    assert table[1].startswith("2,3,trace,-,-,-,-,-,-,")


def test_each_problem_meets_the_solvers_in_an_order_of_its_own(monkeypatch):
    """Every solver once per problem, in a seeded order drawn per problem, so that no
    solver always follows the same one (the cold caches of a call depend on the call
    before it; a fixed rotation gave closed-form's fo.bci, which runs newton's code, the
    warm predecessor fo.ci newton on every problem, and a 1.2x lead over newton)."""
    seen = []
    monkeypatch.setattr(backends, "_solve", lambda r, *args, **kw: seen.append(r.solver))
    solvers = backends._solvers(["newton", "closed-form"], list(backends._PEERS), 2)
    problems = [(None, None)] * 40
    backends._loop(problems, "trace", solvers, "single", {}, first=False)
    orders = [seen[k * len(solvers):(k + 1) * len(solvers)] for k in range(len(problems))]
    assert all(sorted(map(id, o)) == sorted(map(id, solvers)) for o in orders)
    before = {id(o[i + 1]): set() for o in orders for i in range(len(o) - 1)}
    for o in orders:
        for a, b in itertools.pairwise(o):
            before[id(b)].add(id(a))
    assert min(map(len, before.values())) >= 3  # several predecessors each
    seen.clear()
    backends._loop(problems, "trace", solvers, "single", {}, first=False)
    assert [id(s) for s in seen] == [id(s) for o in orders for s in o]  # seeded
