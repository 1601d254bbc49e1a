"""The backend benchmark study runs end to end on a tiny config and writes its files."""

import csv

import numpy as np

from studies import backends, config


def test_backends_study_writes_outputs(tmp_path):
    c = config.load("backends", quick=True)
    c.update(n=[2], N=[2, 3], instances=2, repeats=1, batch_pairs=50, batch_n=[3],
             batch_repeats=1, batch_check=3)
    backends.run(c, tmp_path, quick=True, progress=False)
    for name in ("backends.csv", "backends.md", "backends_time_vs_N.png", "machine.json"):
        assert (tmp_path / name).stat().st_size > 0
    rows = list(csv.DictReader(open(tmp_path / "backends.csv")))
    single = [r for r in rows if r["mode"] == "single"]
    assert {r["backend"] for r in single} == set(c["backends"])
    assert all(int(r["failures"]) == 0 for r in rows)
    assert max(float(r["worst_objective_gap"]) for r in single) < 1e-6
    batch = [r for r in rows if r["mode"] == "batch"]
    assert len(batch) == 2 and all(np.isfinite(float(r["median_ms"])) for r in batch)
    # `report` rebuilds the table from the CSV alone, without measuring again
    table = (tmp_path / "backends.md").read_text()
    (tmp_path / "backends.md").unlink()
    backends.report(c, tmp_path, quick=True)
    assert (tmp_path / "backends.md").read_text() == table


def test_ill_conditioned_instances_are_spd_and_ill_conditioned():
    P = backends.instance(np.random.default_rng(0), 5, 4, "ill-conditioned")
    assert np.allclose(P, np.swapaxes(P, -1, -2)) and np.linalg.eigvalsh(P).min() > 0
    assert np.linalg.cond(P).max() > 1e6
