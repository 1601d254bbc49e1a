"""Scenario simulators: DESIGN §3 defaults, truth kinematics, detection and clutter rates;
the crossing targets of the network example."""

import dataclasses
import warnings

import numpy as np
import pytest
from scipy.stats import binomtest

from fusion_opt import FusionInputError
from trackers import scenarios
from trackers.scenarios import CLUTTER, MAX_REACH, Table1Config, check_reach, simulate_table1


def test_table1_defaults_are_design_values():
    c = scenarios.Table1Config()
    assert (c.dt, c.n_steps, c.q, c.r, c.x0) == (0.025, 960, 0.1, 0.05, (-4.0, -0.2, 1.0, 0.0))
    assert c.p_detect == (0.9, 0.7) and c.clutter_fraction == 0.5
    assert c.region == ((-5.0, 5.0), (-4.0, 4.0)) and c.clutter_density == 1 / 80
    assert (c.n_particles, c.clutter_prior, c.prior_cov, c.resample_threshold) == (20, 0.5, 0.1,
                                                                                    0.25)
    starts = [w[:2] for w in c.turn_windows]
    assert starts == [(1.0, 3.0), (3.5, 5.5), (8.0, 10.5), (14.0, 16.5), (19.0, 21.0),
                      (21.5, 23.5)]
    np.testing.assert_allclose([w[2] for w in c.turn_windows],
                               np.pi * np.array([1 / 4.2, -1 / 4.2, -1 / 5.2, -1 / 5.2,
                                                 -1 / 4.2, 1 / 4.2]))


def test_table1_truth_and_measurements():
    cfg = scenarios.Table1Config()
    data = scenarios.simulate_table1(cfg, np.random.default_rng(0))
    T = cfg.n_steps
    np.testing.assert_allclose(data.times, cfg.dt * np.arange(1, T + 1))
    # before the first turn the target moves straight from x0: x(t) = x0 + t v0
    k = data.times < 1.0 - 1e-9
    x0 = np.array(cfg.x0)
    np.testing.assert_allclose(data.truth[k, :2], x0[:2] + data.times[k, None] * x0[2:],
                               atol=1e-12)
    # no process noise: turning only rotates the velocity, the speed stays |v0| = 1
    np.testing.assert_allclose(np.linalg.norm(data.truth[:, 2:], axis=1), 1.0, atol=1e-9)
    inside = np.zeros(T, bool)
    for start, end, _ in cfg.turn_windows:
        inside |= (data.times >= start - 1e-9) & (data.times <= end + 1e-9)
    assert np.all(data.turn_rates[~inside] == 0.0)
    for p_d, node in zip(cfg.p_detect, data.nodes, strict=True):
        assert len(node.scans) == T
        assert all(len(s) <= 1 for s in node.scans)
        np.testing.assert_array_equal(np.concatenate(node.scans), node.values)
        np.testing.assert_allclose(node.time, data.times[node.step])
        assert binomtest(len(node.values), T, p_d).pvalue > 1e-3
        clutter = node.origin == CLUTTER
        assert binomtest(int(clutter.sum()), len(clutter), 0.5).pvalue > 1e-3
        assert np.all(np.abs(node.values[clutter]) <= [5.0, 4.0])
        resid = node.values[~clutter] - data.truth[node.step[~clutter], :2]
        assert np.all(node.origin[~clutter] == 0)
        assert np.var(resid) == pytest.approx(cfg.r, rel=0.15)


def test_table1_nodes_are_independent_streams_and_reproducible():
    cfg = scenarios.Table1Config(n_steps=100)
    a = scenarios.simulate_table1(cfg, np.random.default_rng(5))
    b = scenarios.simulate_table1(cfg, np.random.default_rng(5))
    np.testing.assert_array_equal(a.nodes[1].values, b.nodes[1].values)
    # adding a third node does not change the first two nodes' measurements
    c = scenarios.simulate_table1(dataclasses.replace(cfg, p_detect=(0.9, 0.7, 0.5)),
                                  np.random.default_rng(5))
    np.testing.assert_array_equal(a.nodes[0].values, c.nodes[0].values)
    np.testing.assert_array_equal(a.truth, c.truth)


def test_table2_schedule_and_measurements():
    cfg = scenarios.Table2Config()
    assert cfg.p_detect == (0.8, 0.8, 0.9, 0.75, 0.95, 0.9, 0.85)
    assert (cfg.birth_prob, cfg.lifetime_shape, cfg.lifetime_scale) == (0.01, 2.0, 0.5)
    assert (cfg.clutter_prior, cfg.clutter_density, cfg.clutter_rate) == (0.05, 1 / 16, 0.1)
    data = scenarios.simulate_table2(cfg, np.random.default_rng(1))
    t = data.times
    expected = np.select([t <= 1.0 + 1e-9, t <= 3.0 + 1e-9, t <= 3.5 + 1e-9, t <= 4.0 + 1e-9],
                         [1, 4, 3, 2], 1)
    np.testing.assert_array_equal(data.n_alive, expected)
    # target 4 circles with a = 1 and speed 1: radius 1 around (-1, 0)
    circ = data.truth[3, data.alive[3], :2]
    np.testing.assert_allclose(np.linalg.norm(circ - [-1.0, 0.0], axis=1), 1.0, atol=1e-9)
    assert np.all(np.isnan(data.truth[~data.alive]))
    for p_d, node in zip(cfg.p_detect, data.nodes, strict=True):
        target = node.origin != CLUTTER
        assert binomtest(int(target.sum()), cfg.n_steps, p_d).pvalue > 1e-3
        assert np.all(data.alive[node.origin[target], node.step[target]])
        resid = node.values[target] - data.truth[node.origin[target], node.step[target], :2]
        assert np.std(resid) == pytest.approx(cfg.meas_sd, rel=0.15)
        assert np.all(np.abs(node.values[~target]) <= 2.0)
        assert len(node.scans) == cfg.n_steps
    n_clutter = sum(int(np.sum(n.origin == CLUTTER)) for n in data.nodes)
    assert abs(n_clutter - 7 * 50) < 4 * np.sqrt(7 * 50)  # Poisson(0.1) per step, 7 nodes


def test_config_overrides_and_validation():
    cfg = dataclasses.replace(scenarios.Table1Config(), dt=0.05, p_detect=(1.0,))
    assert scenarios.simulate_table1(cfg, np.random.default_rng(0)).nodes[0].values.shape == (
        960, 2)
    with pytest.raises(ValueError, match=r"p_detect\[1\] must be a probability"):
        scenarios.Table1Config(p_detect=(0.9, 1.2))
    with pytest.raises(ValueError, match="dt must be a finite positive"):
        scenarios.Table2Config(dt=0.0)
    with pytest.raises(ValueError, match="region must be"):
        scenarios.Table1Config(region=((1.0, -1.0), (0.0, 1.0)))
    with pytest.raises(ValueError, match="death must be > birth"):
        scenarios.TargetSpec((0, 0, 0, 0), 2.0, 1.0)
    with pytest.raises(ValueError, match=r"targets\[0\]: death must be > birth"):
        scenarios.Table2Config(targets=({"x0": (0, 0, 0, 0), "birth": 2.0, "death": 1.0},))
    with pytest.raises(ValueError, match="rng must be a numpy.random.Generator"):
        scenarios.simulate_table2(scenarios.Table2Config(), 42)


def test_table2_targets_from_toml_tables():
    tables = [{"x0": [0.0, 0.0, 1.0, 0.0], "birth": 0.0, "death": 1.0},
              {"x0": [1.0, 1.0, 0.0, 1.0], "birth": 0.5, "death": 1.0,
               "turn_windows": [[0.6, 0.8, 1.0]]}]
    cfg = scenarios.Table2Config(targets=tables, n_steps=100)
    assert cfg.targets[1] == scenarios.TargetSpec((1.0, 1.0, 0.0, 1.0), 0.5, 1.0,
                                                  ((0.6, 0.8, 1.0),))
    data = scenarios.simulate_table2(cfg, np.random.default_rng(0))
    np.testing.assert_array_equal(data.n_alive[[0, 49, 50, 99]], [1, 1, 2, 2])
    with pytest.raises(ValueError, match=r"targets\[0\] is not a valid TargetSpec"):
        scenarios.Table2Config(targets=[{"x0": [0, 0, 0, 0], "born": 0.0}])


def _numeric_fields(cls):
    """Names of the fields of a config whose default is a number or holds numbers."""
    return [f.name for f in dataclasses.fields(cls)
            if f.name not in ("truth_process_noise", "targets")]


def _poisoned(value, bad):
    """``value`` (a number or nested tuples of numbers) with its first number replaced."""
    if isinstance(value, tuple):
        return (_poisoned(value[0], bad),) + value[1:]
    return bad


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, True, None, "0.5", 1 + 0j])
@pytest.mark.parametrize("cls", [scenarios.Table1Config, scenarios.Table2Config])
def test_every_numeric_config_field_refuses_non_finite_and_non_numbers(cls, bad):
    """Regression: NaN passed every check written as `x < 0` (NaN < 0 is False), e.g.
    turn_noise_sd, clutter_fraction, x0, turn_windows, clutter_rate; booleans passed as 1."""
    default = cls()
    for name in _numeric_fields(cls):
        value = _poisoned(getattr(default, name), bad)
        with pytest.raises(FusionInputError, match=name):
            cls(**{name: value})


@pytest.mark.parametrize("bad", [np.nan, np.inf, True, None, "1", 1j])
@pytest.mark.parametrize("field", ["x0", "birth", "death", "turn_windows", "turn_rate"])
def test_target_spec_refuses_non_finite_and_non_numbers(field, bad):
    good = {"x0": (0.0, 1.0, 1.0, 0.0), "birth": 0.0, "death": 1.0,
            "turn_windows": ((0.2, 0.4, 1.0),), "turn_rate": 0.5}
    value = _poisoned(good[field], bad)
    with pytest.raises(FusionInputError, match=field):
        scenarios.TargetSpec(**(good | {field: value}))
    with pytest.raises(FusionInputError, match=rf"targets\[0\]: {field}"):
        scenarios.Table2Config(targets=(good | {field: value},))


def test_configs_refuse_no_nodes_and_non_boolean_flags():
    """Regression: p_detect=() made a scenario with no nodes; a number passed as the
    truth_process_noise flag."""
    for cls in (scenarios.Table1Config, scenarios.Table2Config):
        with pytest.raises(FusionInputError, match="p_detect must hold one detection"):
            cls(p_detect=())
        with pytest.raises(FusionInputError, match="p_detect must have 1 dimension"):
            cls(p_detect=0.9)
        with pytest.raises(FusionInputError, match="truth_process_noise must be True or False"):
            cls(truth_process_noise=1)
        with pytest.raises(FusionInputError, match="n_particles must be an integer"):
            cls(n_particles=True)
    with pytest.raises(FusionInputError, match="targets must be a sequence"):
        scenarios.Table2Config(targets=None)


def _segments_cross(p, q, r, s) -> bool:
    """Whether segments pq and rs cross (strictly, by orientation tests)."""
    def side(a, b, c):
        return np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
    return side(p, q, r) * side(p, q, s) < 0 and side(r, s, p) * side(r, s, q) < 0


def _crossings(a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    """Points where the polylines a (m, 2) and b (k, 2) cross (segment midpoints)."""
    return [(a[i] + a[i + 1] + b[j] + b[j + 1]) / 4
            for i in range(len(a) - 1) for j in range(len(b) - 1)
            if _segments_cross(a[i], a[i + 1], b[j], b[j + 1])]


def test_scenario_has_twenty_targets_whose_paths_cross_in_the_middle():
    sc = scenarios.CrossingConfig()
    data = scenarios.simulate_crossing(sc, np.random.default_rng(0))
    assert data.truth.shape[0] == 20 and data.alive.any(axis=1).all()
    paths = [data.truth[j, data.alive[j], :2][::4] for j in range(20)]  # every 0.2 s
    points = {(i, j): _crossings(paths[i], paths[j])
              for i in range(20) for j in range(i + 1, 20)}
    crossing = [pair for pair, pts in points.items() if pts]
    assert len(crossing) >= 150  # of 190 pairs: nearly every pair of paths crosses
    middle = [np.linalg.norm(p) for pts in points.values() for p in pts]
    assert np.median(middle) < 0.6 * sc.start_radius
    # and at least 10 pairs meet: closer than the association threshold at one step
    d = np.linalg.norm(data.truth[:, None, :, :2] - data.truth[None, :, :, :2], axis=-1)
    meet = (np.nan_to_num(d, nan=np.inf) < 0.3).any(axis=-1)  # (20, 20)
    assert np.triu(meet, k=1).sum() >= 10


def test_scenario_measurements_follow_the_detection_model():
    sc = scenarios.CrossingConfig(p_detect=(1.0, 0.5), clutter_rate=(0.0, 3.0))
    data = scenarios.simulate_crossing(sc, np.random.default_rng(1))
    origins = [node.origin for node in data.nodes]
    assert np.array_equal(np.sort(origins[0]), np.sort(np.nonzero(data.alive)[0]))
    n_targets = data.alive.sum()
    assert abs((origins[1] >= 0).sum() / n_targets - 0.5) < 0.05
    assert abs((origins[1] < 0).sum() / sc.n_steps - 3.0) < 0.3


@pytest.mark.parametrize("field, value, match", [
    ("clutter_rate", (1.0,), "one rate per node"), ("heading_offset", 2.0, "heading_offset"),
    ("births", (), "births must not be empty"), ("p_detect", (0.5, 1.5) + (0.5,) * 14,
                                                  r"p_detect\[1\]"),
    ("n_targets", 0, "n_targets"),
])
def test_crossing_config_refuses_bad_fields_by_name(field, value, match):
    with pytest.raises(FusionInputError, match=match):
        scenarios.CrossingConfig(**{field: value})


def test_a_table1_without_turn_windows_takes_any_turn_noise():
    """No window, no drawn rate: the check of turn_noise_sd has nothing to bound (it took
    the max of no rates)."""
    assert scenarios.Table1Config(turn_windows=(), turn_noise_sd=1e300).turn_windows == ()


@pytest.mark.parametrize("make, match", [
    (lambda: scenarios.Table1Config(n_steps=10**12), r"n_steps = 1000000000000: about"),
    (lambda: scenarios.Table2Config(n_steps=2, clutter_rate=1e12), "clutter_rate: about"),
    (lambda: scenarios.CrossingConfig(n_targets=10**12), "n_targets and clutter_rate: about"),
    (lambda: scenarios.Table2Config(targets=[scenarios.TargetSpec((0, 0, 1, 0), -1e300, 1)]),
     "targets and clutter_rate: about"),
    (lambda: scenarios.Table1Config(n_steps=5, dt=1e300), "too long a step"),
    (lambda: scenarios.Table1Config(region=((-1.7e308, 1.7e308), (0, 1))), "width overflows"),
    # fuzz E2 (an OverflowError from meas_sd**2) and E8 (refused when simulated, naming dt)
    (lambda: scenarios.Table2Config(meas_sd=1e200), r"meas_sd = 1e\+200: its square"),
    (lambda: scenarios.Table2Config(meas_sd=1e-200), r"meas_sd = 1e-200: its square"),
    (lambda: scenarios.CrossingConfig(meas_sd=1e200), r"meas_sd = 1e\+200: its square"),
    (lambda: scenarios.Table1Config(turn_noise_sd=1e300), r"turn_noise_sd = 1e\+300: the drawn"),
    (lambda: scenarios.Table2Config(turn_noise_sd=1e150), r"turn_noise_sd = 1e\+150: the drawn")])
def test_configs_whose_runs_float64_or_memory_cannot_hold_are_refused(make, match):
    """Regression: each asked for terabytes (or was OOM-killed: a target born at -1e3 s is
    propagated from there at dt = 1e-6), returned NaN truth, or raised OverflowError when
    simulated; now the configuration is refused before anything is allocated."""
    with pytest.raises(FusionInputError, match=match):
        make()


def test_reach_is_accepted_up_to_the_bound_and_refused_past_it():
    """check_reach: max|position| + speed x duration against MAX_REACH sds; a Table 1
    target just inside runs its scenario with finite measurements."""
    sd = 0.5
    check_reach("p", [MAX_REACH * sd - 30.0, 0.0], 2.0, 15.0, sd, "sd")
    with pytest.raises(FusionInputError, match=r"p: the target reaches 5e\+11 m"):
        check_reach("p", [MAX_REACH * sd - 30.0, 0.0], 2.0, 15.5, sd, "sd")
    with pytest.raises(FusionInputError, match="p: the target reaches inf m"):
        check_reach("p", [1e308, 0.0], 1e308, 10.0, sd, "sd")
    cfg = Table1Config(x0=(1e11, -0.2, 1.0, 0.0), n_steps=20)
    data = simulate_table1(cfg, np.random.default_rng(0))
    assert all(np.isfinite(node.values).all() for node in data.nodes)


def test_integers_past_int64_and_steps_past_float64_are_handled_by_name():
    """Fuzz N7: dt or r of 2^70 (a TOML integer) reached numpy as an object (TypeError);
    N8: dt = 1e-308 made a birth's step t / dt infinite and round() raised OverflowError
    in the simulators. Now a float field given an int holds it as a float (refused past
    float64), and a target born beyond the run is simply never alive in it."""
    cfg = Table1Config(r=2**70)
    assert cfg.r == float(2**70) and type(cfg.r) is float
    # fuzz O6: numpy integers too (np.int32 dt x n_steps wrapped to -960 and passed);
    # O3: an int of 5,001 digits is named by its size (its repr raised ValueError)
    assert type(scenarios.Table2Config(meas_sd=np.int64(2**32)).meas_sd) is float
    # held as 2.1e9 s, not wrapped: its turns of 1.6e9 rad are refused (fuzz U8)
    with pytest.raises(FusionInputError, match="turn rate 0 = 0.7479.*dt = 2.14748e[+]09 is too "
                                               "long a step"):
        Table1Config(dt=np.int32(2**31 - 1))
    with pytest.raises(FusionInputError, match="dt = an integer of about 5001 digits is beyond"):
        Table1Config(dt=10**5000)
    for make, match in ((lambda: Table1Config(dt=2**70), "dt = 1.18059e[+]21 is too long"),
                        (lambda: scenarios.Table2Config(dt=2**70), "dt = 1.18059e[+]21"),
                        (lambda: Table1Config(r=10**400), r"r = 10000000\.\.\. \(401 digits\) "
                                                          "is beyond float64's range"),
                        (lambda: scenarios.CrossingConfig(dt=10**400), "dt = 1000")):
        with pytest.raises(FusionInputError, match=match):
            make()
    rng = np.random.default_rng(0)
    t2 = scenarios.simulate_table2(scenarios.Table2Config(dt=1e-308, n_steps=20), rng)
    cross = scenarios.simulate_crossing(scenarios.CrossingConfig(dt=1e-308), rng)
    births = ([tg.birth for tg in scenarios.Table2Config().targets],
              scenarios.CrossingConfig().targets()[1])
    for data, born in zip((t2, cross), births, strict=True):
        # a target born at 0 lives through the run; one born at t > 0 is far past it
        np.testing.assert_array_equal(data.alive.all(axis=1), np.asarray(born) == 0)
        np.testing.assert_array_equal(data.alive.any(axis=1), np.asarray(born) == 0)


def test_float_fields_given_as_other_real_numbers_hold_their_nearest_float():
    """Fuzz U4: a Fraction passed the field checks and reached np.sqrt and np.cos as an
    object (TypeError); a float16 dt overflowed in float16 inside the reach check. Every
    real number in a float field is held as the nearest float64; a long double beyond
    float64's range, or nonzero below it, is refused by name."""
    from fractions import Fraction

    assert Table1Config(r=Fraction(1, 2)).r == 0.5
    cfg = scenarios.CrossingConfig(heading_offset=Fraction(1, 3))
    assert type(cfg.heading_offset) is float and cfg.heading_offset == 1 / 3
    assert np.isfinite(cfg.targets()[0]).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cfg = Table1Config(dt=np.float16(0.025), r=np.float32(0.5))
    assert (cfg.dt, cfg.r) == (float(np.float16(0.025)), 0.5)
    assert type(cfg.dt) is float and type(cfg.r) is float
    for huge in (np.longdouble("1e400"), np.longdouble("1e-400")):
        if np.finfo(np.longdouble).max <= np.finfo(np.float64).max:
            continue  # long double is float64 here: nothing beyond its range to give
        with pytest.raises(FusionInputError, match="q = .* is beyond float64's range"):
            Table1Config(q=huge)


@pytest.mark.parametrize("targets", [np.array(0.5), np.ma.masked_array(1.0),
                                     np.array(None, dtype=object)])
def test_a_0d_array_of_targets_is_refused_by_name(targets):
    """Fuzz U5: a 0-d array has __iter__ but raises TypeError when iterated."""
    with pytest.raises(FusionInputError, match="targets must be a sequence of TargetSpec"):
        scenarios.Table2Config(targets=targets)
