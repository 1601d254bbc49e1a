"""The N-node study: outputs on a tiny configuration and the properties its rules must
show against the known truth."""

import json
import re

import numpy as np
import pytest
from conftest import tiny_run

import fusion_opt as fo
from studies import config as configs
from studies import nnode
from studies.__main__ import main

TINY = """
runs = 2
[static]
draws = 20
[sweeps]
N = [2, 5]
spread = [0.0, 0.5]
rho = [0.0, 0.9]
growth_assumed = [1.0, 2.0]
[dynamic]
N = [3]
steps = 30
burn_in = 5
[scaling]
N = [2, 4]
n = [2, 3]
backends = ["newton"]
repeats = 1
"""


SWEEPS = {"N": "N", "spread": "spread", "rho": "rho", "growth_assumed": "growth_assumed"}


def test_tiny_study_writes_every_table_as_csv_and_report_rebuilds_it(tmp_path):
    """nnode.md, a CSV per table (each sweep's MSE, ANEES and consistency, its paired MBCI
    minus BCI; the dynamic case; the scaling) and the figures; `report` rebuilds them from
    the store without flags and leaves meta.json alone."""
    folder = tiny_run(tmp_path, "nnode", TINY)
    text = (folder / "nnode.md").read_text()
    for heading in ("sweep over N", "sweep over rho", "sweep over spread",
                    "sweep over growth_assumed", "Dynamic", "Scaling"):
        assert heading in text
    assert "sweep over reported_share" not in text  # [sweeps] of the file replaced the default's
    for name in ("nnode_mse_anees_vs_N.png", "nnode_time_vs_N.png", "scaling.json",
                 "meta.json"):
        assert (folder / name).stat().st_size > 0
    csvs = {f"nnode_sweep_{s}.csv" for s in SWEEPS} | {
        f"nnode_sweep_{s}_paired.csv" for s in SWEEPS} | {"nnode_dynamic.csv",
                                                          "nnode_scaling.csv"}
    assert {p.name for p in folder.glob("*.csv")} == csvs
    rows = (folder / "nnode_sweep_rho.csv").read_text().splitlines()
    assert rows[0].startswith("rho,rule,mse_mean,mse_low,mse_high,anees_mean") and \
        "consistent_mean" in rows[0] and len(rows) == 1 + 2 * len(nnode.RULES)
    assert len((folder / "nnode_sweep_N_paired.csv").read_text().splitlines()) == 1 + 2 * 2
    assert (folder / "nnode_dynamic.csv").read_text().startswith("N,rule,mse_mean")
    assert "newton" in (folder / "nnode_scaling.csv").read_text()
    before = {p.name: p.read_bytes() for p in folder.iterdir() if p.suffix in (".md", ".csv")}
    meta = (folder / "meta.json").read_text()
    for name in before:
        (folder / name).unlink()
    assert main(["report", "nnode", "--out", str(tmp_path)]) == 0
    assert {name: (folder / name).read_bytes() for name in before} == before
    assert (folder / "meta.json").read_text() == meta


def test_a_failed_solve_shows_a_dash_in_the_scaling_table_never_nan(tmp_path):
    """_time_solve gives NaN where a backend failed: its cell and a slope of fewer than
    two timed sizes are "-" (an empty CSV cell), never "nan"."""
    times = {"vs_N": {"newton": {"2": 1e-4, "4": float("nan")}},
             "vs_n": {"newton": {"2": 1e-4, "3": 2e-4}}, "repeats": 1}
    (tmp_path / "scaling.json").write_text(json.dumps(times))
    text = "\n".join(nnode._scaling_table(tmp_path))
    assert "nan" not in text.lower()
    assert "| newton | 0.1 | - | - |" in text and "| newton | 0.1 | 0.2 | 1.71 |" in text
    assert nnode.slope([2.0, 4.0], [1e-4, float("nan")]) is None


def _static(**over):
    return configs.load("nnode")["static"] | over


def test_naive_equals_known_cross_without_correlation_and_equal_covariances():
    """rho = 0 and identical covariances (no misses, one base): BLUE is the naive rule."""
    cfg = _static(rho=0.0, growth_true=1.0, N=5)
    rng = np.random.default_rng(0)
    case = nnode.static_case(cfg, rng)
    case["covs"][:] = case["covs"][0]
    case["cross"][:] = 0.0
    case["cross"][np.arange(5), np.arange(5)] = case["covs"]
    means = rng.standard_normal((5, 4))
    kw = dict(p=case["p"], growth=1.0, backend="newton", cross=case["cross"])
    naive = nnode.fuse_rule("naive", means, case["covs"], **kw)
    known = nnode.fuse_rule("known cross", means, case["covs"], **kw)
    np.testing.assert_allclose(naive.mean, known.mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(naive.cov, known.cov, rtol=1e-10)
    np.testing.assert_allclose(naive.cov, case["covs"][0] / 5, rtol=1e-10)


@pytest.mark.parametrize("seed", range(3))
def test_mbci_equals_bci_when_the_growth_is_one(seed):
    cfg = _static(growth_assumed=1.0, draws=10)
    out = nnode.static_scores(cfg, np.random.default_rng(seed), "newton")
    for crit in ("trace", "logdet"):
        for key in ("mse", "mse_exact", "anees", "trace"):
            assert out[f"MBCI {crit}"][key] == out[f"BCI {crit}"][key]


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.95])
def test_known_cross_error_is_never_above_any_rule(rho):
    """Exactly (tr K S K^T) on every case, and on the Monte Carlo MSE up to its error."""
    for seed in range(5):
        cfg = _static(rho=rho, N=6, draws=400)
        out = nnode.static_scores(cfg, np.random.default_rng(seed), "newton")
        best = out["known cross"]
        for name, r in out.items():
            assert best["mse_exact"] <= r["mse_exact"] * (1 + 1e-9), name
            assert best["mse"] <= r["mse"] * 1.25 + 1e-12, name  # 400 draws: MC error


def test_ci_rules_are_consistent_and_naive_is_not_under_correlation():
    cfg = _static(rho=0.8, N=8)
    out = nnode.static_scores(cfg, np.random.default_rng(3), "newton")
    for name in ("BCI trace", "BCI logdet", "MBCI trace", "MBCI logdet", "fast CI", "IFCI",
                 "known cross"):
        assert out[name]["consistent"] == 1.0, name
    assert out["naive"]["consistent"] == 0.0


def test_dynamic_case_fuses_the_kalman_filters_reports_as_fuse_does():
    """The dynamic case's rows against a direct computation: Kalman filters written out
    here (not trackers.kalman) and fo.fuse on their estimates at every step."""
    dcfg = configs.load("nnode")["dynamic"] | {"steps": 15, "burn_in": 5}
    N, backend = 3, "clarabel"
    out = nnode.dynamic_scores(dcfg, N, np.random.default_rng(4), backend)
    sim = nnode.simulate_target(dcfg, N, np.random.default_rng(4))
    model, (m, P) = nnode.dynamic_model(dcfg), nnode.dynamic_prior(4)
    m, P = np.tile(m, (N, 1)), np.tile(P, (N, 1, 1))
    fused = {"BCI trace": [], "MBCI logdet": [], "naive": []}
    for t, scans in enumerate(sim["scans"]):
        m, P = m @ model.A.T, model.A @ P @ model.A.T + model.Q
        for i, y in enumerate(scans):
            if len(y):
                K = P[i] @ model.H.T @ np.linalg.inv(model.H @ P[i] @ model.H.T + model.R)
                m[i] = m[i] + K @ (y[0] - model.H @ m[i])
                P[i] = (np.eye(4) - K @ model.H) @ P[i]
        if t >= dcfg["burn_in"]:
            kw = {"p_detect": sim["p"], "chi": 1 / dcfg["growth_assumed"]}
            fused["BCI trace"].append(fo.bci(m, P, backend=backend).mean)
            fused["MBCI logdet"].append(fo.mbci(m, P, criterion="logdet", **kw).mean)
            fused["naive"].append(fo.fuse(m, P, method="naive").mean)
    truth = sim["truth"][dcfg["burn_in"]:]
    for name, means in fused.items():
        expected = np.mean(np.sum((np.array(means) - truth) ** 2, axis=1))
        assert out[name]["mse"] == pytest.approx(expected, rel=1e-8), name


@pytest.mark.parametrize("rho", [0.0, 0.6, 1.0])
def test_static_errors_have_the_joint_covariance(rho):
    cfg = _static(rho=rho, N=3, n=2)
    rng = np.random.default_rng(11)
    case = nnode.static_case(cfg, rng)
    e = nnode.draw_errors(case, 40_000, rng).reshape(40_000, -1)
    S = np.concatenate(np.concatenate(case["cross"], axis=1), axis=1)
    assert np.linalg.eigvalsh(S).min() >= -1e-12 * np.linalg.norm(S, 2)  # a valid joint
    np.testing.assert_allclose(np.cov(e.T), S, atol=0.05 * np.abs(S).max())


def test_a_burn_in_too_short_for_known_cross_says_so():
    """Early in a run the nodes' errors are linearly dependent (a shared prior, position-only
    detections), and known-cross refuses the singular joint: the run's error says why and
    which field to change (fuzz of 2026-11-26: it named only `cross`)."""
    dcfg = configs.load("nnode", quick=True)["dynamic"] | {"steps": 5, "burn_in": 1}
    with pytest.raises(fo.FusionInputError, match=r"not positive definite after "
                       r"dynamic.burn_in = 1 steps: until every node has made about two"):
        nnode.dynamic_scores(dcfg, 8, np.random.default_rng(0), "newton")


def test_a_threshold_below_the_filters_spread_says_how_far_apart_they_were():
    """dt = 1e4 s: the filters' position errors reach ~1e6 m, beyond the threshold of 1e6;
    the centre made no track of the N reports and the error gives their spread (fuzz H10:
    it asked "dynamic.threshold too small?" with no number)."""
    dcfg = configs.load("nnode", quick=True)["dynamic"] | {"steps": 30, "burn_in": 10,
                                                           "dt": 1e4}
    with pytest.raises(RuntimeError, match=r"'naive' made 0 tracks of the N = 2 estimates of "
                       r"the one target: their positions lie up to (\S+) m apart, beyond "
                       r"dynamic.threshold = 1e\+06") as err:
        nnode.dynamic_scores(dcfg, 2, np.random.default_rng(0), "newton")
    assert float(re.search(r"up to (\S+) m", str(err.value)).group(1)) > 1e6
