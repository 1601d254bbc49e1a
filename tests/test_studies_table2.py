"""Table 2 through the command line on a tiny scenario: its outputs, `report` from the
store, and every scenario field reaching the filters (resample_threshold did not)."""

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from studies import config as study_config
from studies import stats, table2
from studies.__main__ import main

TINY = """
runs = 2
backend = "newton"
[scenario]
n_steps = 30
n_particles = 4
"""


def _run(tmp_path, name, extra="") -> str:
    config = tmp_path / f"{name}.toml"
    config.write_text(TINY + extra)
    out = tmp_path / name
    assert main(["run", "table2", "--config", str(config), "--out", str(out), "--quiet",
                 "--workers", "1"]) == 0
    return (out / "table2" / "table2.csv").read_text()


def test_tiny_table2_writes_its_tables_figures_and_rebuilds_them(tmp_path):
    _run(tmp_path, "a")
    folder: Path = tmp_path / "a" / "table2"
    for name in ("table2.md", "table2.csv", "table2_paired.csv", "table2_node3.png",
                 "table2_node9.png", "meta.json"):
        assert (folder / name).stat().st_size > 0, name
    table = (folder / "table2.md").read_text()
    assert "| modified CI 9 |" in table and "bootstrap percentile" in table
    assert "9,mse," in (folder / "table2_paired.csv").read_text()
    (folder / "table2.md").unlink()
    assert main(["report", "table2", "--out", str(tmp_path / "a")]) == 0
    assert (folder / "table2.md").read_text() == table


def test_resample_threshold_reaches_the_filters(tmp_path):
    never = _run(tmp_path, "never", "resample_threshold = 0.0\n")
    always = _run(tmp_path, "always", "resample_threshold = 1.0\n")
    assert never != always


def test_spectral_norms_are_the_largest_eigenvalues_grouped_by_target():
    """The batched norms against eigvalsh, matrix by matrix (covariances are symmetric
    positive definite: the spectral norm is the largest eigenvalue), appended per target in
    the order matched; no match appends nothing."""
    rng = np.random.default_rng(7)
    A = rng.standard_normal((5, 4, 4))
    covs = list(A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(4))
    targets = [3, 1, 3, 0, 1]
    per_target = {k: defaultdict(list) for k in ("mncm", "mncm_pos")}
    table2._spectral_norms(per_target, targets, covs)
    for key, block in (("mncm", slice(0, 4)), ("mncm_pos", slice(0, 2))):
        want = defaultdict(list)
        for t, P in zip(targets, covs, strict=True):
            want[t].append(np.linalg.eigvalsh(P[block, block])[-1])
        assert list(per_target[key]) == [3, 1, 0]
        for t in want:
            np.testing.assert_allclose(per_target[key][t], want[t], rtol=1e-13)
    empty = {k: defaultdict(list) for k in ("mncm", "mncm_pos")}
    table2._spectral_norms(empty, [], [])
    assert not empty["mncm"] and not empty["mncm_pos"]


@pytest.mark.slow  # a whole run (3 s); the tables' handling of NaN is tested in stats'
def test_a_node_that_matched_no_target_has_no_mse_not_a_perfect_zero():
    """Fuzz F7: MSE and MNCM sum over the targets matched at least once, so a node that
    matched none scored 0.0, the best value, while its OSPA said it missed everything; it
    now has none in that run (NaN, left out of the tables' means; '-' when no run has one)."""
    cfg = study_config.load("table2", quick=True)
    cfg["scenario"].update(n_steps=10, meas_sd=1e30, n_particles=3)
    table2.check(cfg)
    result, _ = table2.run_one(cfg, 1, np.random.SeedSequence(1))
    row = result["RBMCDA 1"]
    assert all(np.isnan(row[k]) for k in ("mse", "mncm", "mse_pos", "mncm_pos"))
    assert row["ospa"] == cfg["metrics"]["cutoff"]  # every target missed
    assert stats.paired([np.nan], [1.0])["runs"] == 0
