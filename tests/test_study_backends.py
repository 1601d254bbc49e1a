"""The backend benchmark runs end to end on a tiny config, measures every configured
backend where it applies, and computes its gaps independently of the backends."""

import csv

import numpy as np
import pytest

from fusion_opt import FusionSolverError
from fusion_opt.backends import REGISTRY, WeightSolution
from studies import backends, config


def _tiny(**over) -> dict:
    c = config.load("backends", quick=True)
    c.update(n=[2], N=[2, 3], instances=2, repeats=1, batch_pairs=50, batch_n=[3],
             batch_repeats=1, batch_check=3)
    c.update(over)
    backends.check(c)
    return c


def _rows(path) -> list[dict]:
    with open(path / "backends.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_backends_study_writes_outputs(tmp_path):
    c = _tiny()
    backends.run(c, tmp_path, quick=True, progress=False)
    for name in ("backends.csv", "backends.md", "backends_time_vs_N.png", "machine.json"):
        assert (tmp_path / name).stat().st_size > 0
    rows = _rows(tmp_path)
    single = [r for r in rows if r["mode"] == "single"]
    # every backend once per cell where it applies ("closed-form" at N = 2 only)
    want = {(b, N, crit, kind) for b in c["backends"] for N in c["N"]
            for crit in c["criteria"] for kind in c["kinds"] if b != "closed-form" or N == 2}
    got = [(r["backend"], int(r["N"]), r["criterion"], r["kind"]) for r in single]
    assert sorted(got) == sorted(want)
    assert all(int(r["solves"]) == c["instances"] * c["repeats"] for r in single)
    newton = [r for r in rows if r["backend"] == "newton"]
    assert max(float(r["worst_optimality_gap"]) for r in newton) <= 1e-10
    assert all(int(r["failures"]) == 0 for r in newton)
    assert max(float(r["worst_objective_gap"]) for r in single) < 1e-6
    # the conic backends report their solver's own time and a polished time
    clarabel = [r for r in single if r["backend"] == "clarabel"]
    assert all(np.isfinite(float(r[k])) for r in clarabel
               for k in ("solver_own_median_ms", "overhead_median_ms", "polished_median_ms"))
    # fuse_batch per native backend and a loop of fuse per backend, per n and criterion
    batch = {(r["mode"], r["backend"], r["criterion"]) for r in rows if r["mode"] != "single"}
    assert batch == {(m, b, crit) for crit in c["criteria"] for m, bs in
                     (("batch", ("newton", "closed-form")), ("loop", c["backends"]))
                     for b in bs}
    assert "newton is" in (tmp_path / "backends.md").read_text()
    # `report` rebuilds the table from the CSV alone, without measuring again
    table = (tmp_path / "backends.md").read_text()
    (tmp_path / "backends.md").unlink()
    backends.report(c, tmp_path, quick=True)
    assert (tmp_path / "backends.md").read_text() == table


def _vertex(Ys, M, criterion):
    """A spoiled backend: all the weight on node 0, reported as optimal."""
    w = np.zeros(len(Ys))
    w[0] = 1.0
    return WeightSolution(w, "optimal", 1, 0.0)


def test_a_spoiled_backend_shows_as_a_large_gap(tmp_path, monkeypatch):
    """The gaps are computed from the returned weights, not from what a backend says."""
    monkeypatch.setitem(REGISTRY, "slsqp", _vertex)
    c = _tiny(N=[3], criteria=["trace"], kinds=["random"], backends=["newton", "slsqp"])
    backends.run(c, tmp_path, quick=True, progress=False)
    single = {r["backend"]: r for r in _rows(tmp_path) if r["mode"] == "single"}
    assert float(single["slsqp"]["worst_objective_gap"]) > 1e-3
    assert float(single["slsqp"]["worst_optimality_gap"]) > 1e-3
    assert float(single["newton"]["worst_objective_gap"]) == 0.0


def test_a_failing_backend_is_counted_not_fatal(tmp_path, monkeypatch):
    def fails(Ys, M, criterion):
        raise FusionSolverError("slsqp", "status_8", "spoiled on purpose")

    monkeypatch.setitem(REGISTRY, "slsqp", fails)
    c = _tiny(N=[3], kinds=["random"], backends=["newton", "slsqp"])
    backends.run(c, tmp_path, quick=True, progress=False)
    rows = [r for r in _rows(tmp_path) if r["backend"] == "slsqp"]
    assert rows and all(int(r["failures"]) == c["instances"] if r["mode"] == "single"
                        else int(r["failures"]) == c["batch_check"] for r in rows)
    assert all("status_8" in r["first_failure"] for r in rows)
    assert all(r["worst_objective_gap"] == "nan" for r in rows)
    assert "status_8" in (tmp_path / "backends.md").read_text()


@pytest.mark.parametrize("bad,message", [
    ({"backends": ["newton", "gurobi"]}, "backends[1] must be one of"),
    ({"batch_check": 0}, "batch_check must be an integer >= 1"),
    ({"N": [1, 2]}, "N[0] must be an integer >= 2"),
    ({"kinds": ["random", "random"]}, "kinds lists ['random'] more than once"),
    ({"backends": ["closed-form"], "N": [3]}, "fuses N = 2 only"),
])
def test_check_names_the_bad_field(bad, message):
    with pytest.raises(config.ConfigError, match=message.replace("[", r"\[")):
        backends.check(config.load("backends", quick=True) | bad)


def test_closed_form_with_only_larger_N_is_accepted_and_skipped():
    c = config.load("backends", quick=True) | {"N": [3, 7]}
    backends.check(c)
    assert backends._backends(c, 3) == [b for b in c["backends"] if b != "closed-form"]


def test_ill_conditioned_instances_are_spd_and_ill_conditioned():
    P = backends.instance(np.random.default_rng(0), 5, 4, "ill-conditioned")
    assert np.allclose(P, np.swapaxes(P, -1, -2)) and np.linalg.eigvalsh(P).min() > 0
    assert np.linalg.cond(P).max() > 1e6
