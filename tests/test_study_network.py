"""The network example study: a tiny run through the command line and its report from the
store, refused configurations, the id-switch score on a hand-built case, and the
throughput benchmark's synthetic groups (the scenario's own tests are in
test_trackers_scenarios.py)."""

import numpy as np
import pytest
from conftest import config_with, refused_run, tiny_run

import fusion_opt as fo
from studies import config as configs
from studies import network
from studies.__main__ import main

TINY = """
runs = 2
[scenario]
n_steps = 12
n_targets = 4
births = [0.0]
[tracker]
n_particles = 4
[benchmark]
sources = [2, 3]
targets_at_sources = 5
targets = [4, 8]
sources_at_targets = 2
warmup = 1
steps = 2
"""
OUTPUTS = ("network.md", "network.csv", "network_throughput.csv", "network_tracks.png",
           "network_throughput.png", "throughput.json", "meta.json")


def test_tiny_run_writes_tables_and_figures_and_report_rebuilds_them(tmp_path):
    folder = tiny_run(tmp_path, "network", TINY, OUTPUTS)
    table = (folder / "network.md").read_text()
    for row in ("| 16 | RBMCDA | monitoring |", "| A | CI | 1 |", "| top | MBCI | 2 |",
                "| top | naive | 2 |", "| sources | 3 | mbci |", "| targets | 8 | bci |"):
        assert row in table, row
    csv = (folder / "network.csv").read_text().splitlines()
    assert csv[0].startswith("node,rule,level,ospa_mean") and len(csv) == 1 + 16 + 4 * 4
    tables = {name: (folder / name).read_text() for name in
              ("network.csv", "network_throughput.csv")}
    meta = (folder / "meta.json").read_text()
    for name in ("network.md", "network_tracks.png", *tables):
        (folder / name).unlink()
    assert main(["report", "network", "--out", str(tmp_path)]) == 0
    assert (folder / "network.md").read_text() == table
    assert {name: (folder / name).read_text() for name in tables} == tables
    assert (folder / "network_tracks.png").stat().st_size > 0
    assert (folder / "meta.json").read_text() == meta  # report writes report.json instead
    assert (folder / "report.json").exists()


def test_cli_refuses_a_bad_field_by_name(tmp_path, capsys):
    err = refused_run(tmp_path, capsys, "network", "[network]\nthreshold = -1.0\n")
    assert "network.threshold must be a finite number > 0" in err


@pytest.mark.parametrize("path, value, message", [
    (("scenario", "p_detect"), [0.9, 1.5], r"\[scenario\] p_detect\[1\] must be .* got 1.5$"),
    (("scenario", "clutter_rate"), [0.1, 0.2], r"\[scenario\] clutter_rate must give one rate"),
    (("scenario", "heading_offset"), 2.0, r"\[scenario\] heading_offset must be"),
    (("scenario", "region"), [[1.0, 0.0], [0.0, 1.0]], r"\[scenario\] region must be"),
    (("scenario", "speeed"), 1.0, r"\[scenario\] has unknown field\(s\) \['speeed'\]"),
    (("tracker", "n_particles"), 0, "tracker.n_particles must be an integer >= 1"),
    (("network", "level1", "A"), [1, 17], r"network.level1.A\[1\] must be an integer"),
    (("network", "level2", "top"), ["A", "Z"], r"network.level2.top\[1\] must be one of"),
    (("network", "min_sources", "level2"), 4, "network.min_sources.level2 must be"),
    (("network", "memory"), 0, "network.memory must be an integer >= 1"),
    (("rules", "CI"), {"method": "ci", "criterion": "trace"}, "rules.CI.method must be"),
    (("rules", "MBCI"), {"method": "mbci"}, r"\[rules.MBCI\] lacks field\(s\) \['criterion'\]"),
    (("rules", "naive"), {"method": "naive", "criterion": "trace"},
     "rules.naive.criterion applies to"),
    (("fusion", "growth"), 0.9, "fusion.growth must be a finite number >= 1"),
    (("metrics", "alpha"), 3.0, "metrics.alpha must be"),
    (("figure", "nodes"), ["A", "Q"], r"figure.nodes\[1\] must be one of"),
    (("benchmark", "sources"), [1, 4], r"benchmark.sources\[0\] must be an integer >= 2"),
    (("benchmark", "methods"), ["naive"], r"benchmark.methods\[0\] must be one of"),
    # past float64's range, or squared past it (fuzz of 2026-11-26: an OverflowError, an
    # uncaught FusionInputError on infinite positions)
    (("benchmark", "threshold"), 10**400, "benchmark.threshold must be a finite number > 0"),
    (("benchmark", "noise_sd"), 1e300, "benchmark.noise_sd must be a finite number >= 1e-100"),
    (("benchmark", "spacing"), 1e308, "benchmark.spacing must be a finite number >= 1e-100"),
    (("backend",), "closed-form", "backend 'closed-form' fuses two estimates only"),
    (("seed",), -1, "seed must be an integer >= 0"),
])
def test_check_refuses_a_bad_field_naming_it(path, value, message):
    with pytest.raises(configs.ConfigError, match=message):
        network.check(config_with("network", path, value))


def test_check_refuses_an_unknown_field():
    config = config_with("network", ("tracker", "particles"), 10)
    with pytest.raises(configs.ConfigError, match=r"\[tracker\] has unknown field\(s\) "
                                                    r"\['particles'\]"):
        network.check(config)


def test_default_configuration_passes():
    network.check(configs.load("network"))
    network.check(configs.load("network", quick=True))


def _estimates(points, ids) -> fo.Estimates:
    means = np.zeros((len(ids), 4))
    means[:, :2] = np.reshape(points, (-1, 2))
    return fo.Estimates(means, np.tile(np.eye(4), (len(ids), 1, 1)), ids)


def test_id_switches_on_a_hand_built_case():
    """Targets 0 (y = 0) and 1 (y = 1) over 6 steps, target 2 alive at steps 0-1 and never
    estimated; c = 0.5. Matched ids by hand: target 0 gets 1, 1, 2, 2, 2 (unmatched at step
    5, its estimate 0.6 off): 1 switch; target 1 gets 2, 2, 1, (unmatched at 3), 1, 7:
    2 switches (the gap at step 3 is no switch); target 2: 0. Mean over 3 targets = 1."""
    T = 6
    truth = np.full((3, T, 4), np.nan)
    truth[0, :, :2] = np.column_stack([np.arange(T), np.zeros(T)])
    truth[1, :, :2] = np.column_stack([np.arange(T), np.ones(T)])
    truth[2, :2, :2] = [[10.0, 10.0], [10.0, 10.0]]
    truth[:, :, 2:] = np.where(np.isnan(truth[:, :, :1]), np.nan, 0.0)
    alive = ~np.isnan(truth[..., 0])
    series = [_estimates([[0.1, 0.0], [0.0, 1.1]], [1, 2]),
              _estimates([[1.0, 1.0], [1.1, 0.0]], [2, 1]),  # listed swapped, same match
              _estimates([[2.0, 0.1], [2.0, 0.9]], [2, 1]),  # the ids swap
              _estimates([[3.0, 0.0], [50.0, 50.0]], [2, 9]),  # target 1 missed, a false one
              _estimates([[4.0, 0.0], [4.0, 1.0]], [2, 1]),
              _estimates([[5.6, 0.0], [5.0, 1.0]], [3, 7])]  # id 3 beyond c from target 0
    ids = network.matched_ids(series, network.matches(series, truth, alive, 0.5), 3)
    assert ids == [[1, 1, 2, 2, 2], [2, 2, 1, 1, 7], []]
    assert network.id_switches(ids, alive) == pytest.approx(1.0)


def test_second_level_mbci_takes_the_detection_of_any_of_its_nodes():
    config = configs.load("network")
    net = network.build_network(config, [np.random.default_rng(k) for k in range(16)])
    p = config["scenario"]["p_detect"]
    top = net.processing["MBCI top"]
    expected = 1 - np.prod([1 - p[k - 1] for k in config["network"]["level1"]["B"]])
    assert top.p_detect["MBCI B"] == pytest.approx(expected)
    assert net.processing["MBCI A"].p_detect["RBMCDA 4"] == p[3]
    assert top.chi == pytest.approx(1 / config["fusion"]["growth"])
    assert net.processing["naive top"].sources == ("naive A", "naive B", "naive C")


def test_benchmark_groups_are_the_targets():
    bm = configs.load("network")["benchmark"] | {"p_detect": [0.9, 0.99], "warmup": 1,
                                                 "steps": 3}
    cell = network.time_node(bm, "mbci", 3, 10, np.random.default_rng(0))
    assert 9 <= cell["tracks_per_step"] <= 10  # one fused track per target, not per report
    assert 0 < cell["median_ms"] <= cell["p90_ms"]


def test_an_input_the_library_refuses_is_one_line_not_a_traceback(tmp_path, capsys,
                                                                   monkeypatch):
    """A FusionInputError from a study's own computation (its configuration checked, but an
    input the library refuses) ends the command with its message, exit status 2."""
    def refused(*args, **kwargs):
        raise fo.FusionInputError("means has a non-finite value inf at index (1, 0)")

    monkeypatch.setattr(network, "benchmark", refused)
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    assert main(["run", "network", "--config", str(cfg), "--out", str(tmp_path), "--quiet",
                 "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1] == (
        "error: means has a non-finite value inf at index (1, 0)") and "Traceback" not in err
