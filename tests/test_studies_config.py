"""Every configuration error is refused before anything runs or is created: one line,
naming the study and the field as the user wrote it, no traceback."""

import re
from importlib import resources
from pathlib import Path

import pytest

from studies import config as configs
from studies import runner
from studies.__main__ import STUDIES, _module, main

RUNS = "runs must be an integer >= 2 and <= 10000 (a 95% interval needs two or more runs), got"
CASES = [  # (study, TOML file, what the one line must say)
    ("table1", "[fusion]\ngrowth = 0.5\n", "table1: fusion.growth must be a finite number "
     ">= 1 (the paper's chi^-1"),
    ("table1", "[fusion]\ngrowth = nan\n", "fusion.growth must be a finite number >= 1"),
    ("table1", "[fusion]\nchi_inv = 1.1\n", "unknown field(s) ['chi_inv']; known: ['growth', "
     "'window'] (chi_inv is now growth"),
    ("table1", 'backend = "gurobi"\n', "backend must be one of ['newton'"),
    ("table1", "[fusion]\nchi = 2.0\n", "[fusion] has unknown field(s) ['chi']"),
    ("table1", "[scenario]\ndt = nan\n", "scenario.dt must be a finite number, got nan"),
    ("table1", "[scenario]\nr = inf\n", "scenario.r must be a finite number, got inf"),
    ("table1", "runs = -3\n", f"{RUNS} -3"),
    ("table1", "fusion = 3\n", "[fusion] must be a table, got 3"),
    ("table1", "[fusion]\nwindow = [15.0, 13.0]\n", "fusion.window must be [start, end]"),
    ("table1", "[fusion]\nwindow = [15.0]\n", "fusion.window must be a list of 2 values"),
    ("table1", '[scenario]\ndt = "fast"\n', "scenario.dt must be a finite number, got 'fast'"),
    ("table1", "[scenario]\nn_steps = 10.5\n", "scenario.n_steps must be an integer"),
    ("table1", "[scenario]\nx0 = [1, 2, 'a', 4]\n", "scenario.x0[2] must be a finite number"),
    ("table1", "[scenario]\np_detect = [0.9, 0.7, 0.5]\n", "p_detect must hold 2"),
    ("table1", "[scenario]\nn_stepz = 5\n", "unknown field(s) ['n_stepz']"),
    ("table1", "[scenario]\ndt = -1.0\n", "dt must be a finite positive number"),
    ("table1", "[scenario]\ntruth_process_noise = 1\n", "must be true or false"),
    ("table1", "runz = 5\n", "unknown field(s) ['runz']"),
    ("table1", "runs = 10000000000000\n", f"{RUNS} 1"),
    ("table1", "runs = 0\n", f"{RUNS} 0"),
    ("table2", "runs = 1\n", f"{RUNS} 1"),
    ("table1", 'runs = "5"\n', f"{RUNS} '5'"),
    ("table1", "seed = -1\n", "seed must be an integer >= 0, got -1"),
    ("table1", "[check]\nsteps = -1\n", "check.steps must be an integer >= 0 and <= 960, got -1"),
    ("table1", '[check]\nbackend = "gurobi"\n', "check.backend must be one of ['newton'"),
    ("table1", "runs = [\n", "--config"),
    # fuzz of 2026-11-29: Python's TOML parser recursed into a RecursionError traceback
    ("table1", "runs = " + "[" * 5000 + "]" * 5000 + "\n",
     "nested deeper than Python's parser can follow"),
    ("table2", '[network]\nassociation = "closest"\n', "network.association must be one of"),
    ("table2", "[network]\nthreshold = -0.3\n", "network.threshold must be a finite number > 0"),
    ("table2", '[network.neighbours]\n"8" = [1, 2, 9]\n',
     "network.neighbours.8[2] must be an integer >= 1 and <= 7, got 9"),
    ("table2", '[network.neighbours]\n"8" = [1, 1]\n', "names a monitoring node twice"),
    ("table2", "[metrics]\ncutoff = 0\n", "metrics.cutoff must be a finite number > 0"),
    ("table2", "[metrics]\norder = 0.5\n", "metrics.order must be a finite number >= 1"),
    ("table2", "[fusion]\ngrowth = 0.99\n", "fusion.growth must be a finite number >= 1"),
    ("table2", "[network]\nneighbours = {}\n", "network.neighbours must be a table naming at "
     "least one processing node, got {}"),
    ("table2", 'backend = "gurobi"\n', "backend must be one of ['newton'"),
    ("table2", "[scenario]\nresample_threshold = 1.5\n", "resample_threshold must be a "
     "probability"),
    ("table2", 'backend = "closed-form"\n', "'closed-form' fuses two estimates only"),
    ("table2", '[[scenario.targets]]\nx0 = [0, 1, "a", 0]\nbirth = 0.0\ndeath = 1.0\n',
     "scenario.targets[0].x0[2] must be a finite number"),
    ("nnode", "[sweeps]\nN = [2]\nrho = [0.0, 1.5]\n", "sweeps.rho[1] must be a finite "
     "number >= 0 and <= 1, got 1.5"),
    ("nnode", "[sweeps]\nrho = [0.0]\n", "[sweeps] must be a table with a sweep over N"),
    ("nnode", '[sweeps]\nN = [2]\n[sweeps.bad]\nfield = "nope"\nvalues = [1]\n',
     "sweeps.bad.field must be one"),
    ("nnode", "[sweeps]\nN = [2]\nfoo = [1, 2]\n", "sweeps.foo sweeps no field of [static]"),
    # fuzz F1: a TypeError traceback for a sweep that is not a list, or a fixed not a table
    ("nnode", '[sweeps]\nN = "abc"\n', "sweeps.N must be a non-empty list, got 'abc'"),
    ("nnode", "[sweeps]\nN = [2]\nrho = 0.5\n", "sweeps.rho must be a non-empty list"),
    ("nnode", '[sweeps]\nN = [2]\n[sweeps.s]\nfield = "growth_assumed"\nvalues = [1.1]\n'
              "fixed = 3\n", "sweeps.s.fixed must be a table of [static] fields, got 3"),
    # fuzz F10: a repeated value collapsed into one result; a fixed value of the swept
    # field was dropped while the figure said the sweep held it
    ("nnode", "[sweeps]\nN = [2, 2]\n", "sweeps.N lists a value more than once: [2, 2]"),
    ("nnode", '[sweeps]\nN = [2]\n[sweeps.x]\nfield = "rho"\nvalues = [0.25, 0.75]\n'
              "fixed = { rho = 0.1 }\n", "sweeps.x.fixed sets 'rho', the field the sweep"),
    ("nnode", "[sweeps]\nN = [2]\nchi_inv_assumed = [1.5]\n", "(chi_inv_assumed is now "
     "growth_assumed"),
    ("nnode", '[sweeps]\nN = [2]\n[sweeps.stale]\nfield = "growth_assumed"\nvalues = [1.5]\n'
     "fixed = { reported_share = 2.0 }\n",
     "sweeps.stale.fixed.reported_share must be a finite number >= 0 and <= 1"),
    ("nnode", "[static]\ngrowth_assumed = 0.5\n", "static.growth_assumed must be a finite "
     "number >= 1"),
    ("nnode", "[static]\nchi_inv_true = 1.5\n", "(chi_inv_true is now growth_true"),
    # [static] has no field growth: its growth fields are named instead
    ("nnode", "[static]\nchi_inv = 1.5\n", "(chi_inv is now growth_assumed or growth_true"),
    ("nnode", "[static]\nrho = nan\n", "static.rho must be a finite number >= 0 and <= 1"),
    # covariances past float64's range ended runs in numpy's LinAlgError (fuzz, 2026-11-26)
    ("nnode", "[static]\ngrowth_true = 1e308\n", "static: the covariances reach 10^-0.5 to "
     "10^6160 (base_log10, grown by growth_true up to max_misses times), outside"),
    ("nnode", "[static]\nbase_log10 = [-320.0, -310.0]\n", "static: the covariances reach "
     "10^-320"),
    ("nnode", "[sweeps]\nN = [2]\ngrowth_true = [1.5, 1e10]\n", "sweeps.growth_true[1] = "
     "10000000000.0: the covariances reach"),
    ("nnode", "runs = -1\n", f"{RUNS} -1"),
    ("nnode", 'backend = "gurobi"\n', "backend must be one of ['newton'"),
    ("nnode", "[dynamic]\nburn_in = 500\n", "dynamic.burn_in must be below dynamic.steps"),
    ("nnode", '[scaling]\nbackends = ["gurobi"]\n', "scaling.backends[0] must be one of"),
    ("nnode", '[scaling]\nbackends = ["closed-form"]\n', "'closed-form' fuses two estimates"),
    ("network", "[fusion]\ngrowth = 0.5\n", "fusion.growth must be a finite number >= 1"),
    ("network", "[benchmark]\ngrowth = nan\n", "benchmark.growth must be a finite number >= 1"),
    ("network", "[rules]\n", "[rules] must name at least one fusion rule, got {}"),
    ("network", 'backend = "gurobi"\n', "backend must be one of ['newton'"),
    ("network", "seed = -2\n", "seed must be an integer >= 0, got -2"),
    ("backends", 'criteria = ["trace", "det"]\n', "criteria[1] must be one of"),
    ("backends", "instances = 0\n", "instances must be an integer >= 1"),
    ("backends", 'backends = ["gurobi"]\n', "backends[0] must be one of"),
    ("backends", "batch_check = 0\n", "batch_check must be an integer >= 1"),
    ("backends", 'backends = ["closed-form"]\nN = [3, 7]\n', "fuses N = 2 only"),
    # fuzz F4: each passed the check, made the output folder, then hit numpy's MemoryError
    ("backends", "n = [1000000]\n", "n = 1000000, N = 2 with instances = 32: about"),
    ("backends", "N = [100000000]\n", "n = 2, N = 100000000 with instances = 32: about"),
    ("backends", "batch_size = 1000000000000\n", "with batch_size = 1000000000000: about"),
    ("backends", "large = [[100000, 2]]\n", "n = 100000, N = 2 with large_instances = 2: about"),
    ("backends", "batch_shapes = [[2, 100000000]]\n", "batch_shapes [2, 100000000] with"),
    # fuzz I3: instances had no bound; a cell's problems are kept together (and a row per
    # solver and problem to the end): n = 48, N = 64, 5,000 instances died in MemoryError
    ("backends", "n = [48]\nN = [64]\ninstances = 5000\n",
     "n = 48, N = 64 with instances = 5000: about"),
    ("backends", "n = [2]\nN = [2]\ninstances = 3000000\n",
     "instances = 3000000 and large_instances = 2 ("),
    # sizes beyond memory, refused at the check, not when a run allocates them
    ("table1", "[check]\nsteps = 100000000000\n",
     "check.steps must be an integer >= 0 and <= 960, got 100000000000"),
    ("table1", "[scenario]\nn_steps = 10000000000000\n", "[scenario] n_steps = 1000"),
    ("table1", "[scenario]\nn_particles = 10000000000000\n",
     "table1: [scenario] n_particles = 10000000000000: about"),
    ("table2", "[scenario]\nn_particles = 10000000000000\n", "[scenario] n_particles = 1"),
    ("table2", "[scenario]\nclutter_rate = 1e12\n", "n_steps, targets and clutter_rate"),
    ("network", "[tracker]\nn_particles = 10000000000000\n", "[tracker] n_particles = 1"),
    ("network", "[benchmark]\ntargets = [10, 1000000000]\n",
     "benchmark.sources_at_targets and targets: about"),
    ("nnode", "[static]\nn = 100000\n", "static.n, static.N and static.draws: about"),
    ("nnode", "[static]\ndraws = 10000000000\n", "static.n, static.N and static.draws"),
    ("nnode", "[static]\nN = 100000000\n", "static.n, static.N and static.draws"),
    ("nnode", "[sweeps]\nN = [2, 1000000000]\n", "sweeps.N[1] = 1000000000: about"),
    ("nnode", "[dynamic]\nN = [2, 100000]\n",
     "dynamic.N[1] = 100000 with dynamic.steps = 200: about"),
    ("nnode", "[scaling]\nn = [2, 200]\n", "scaling.n[1] with clarabel: about"),
    ("nnode", "[scaling]\nN = [8]\n", "scaling.N must hold two or more distinct sizes (the "
     "log-log slope is fitted to them), got [8]"),
    ("nnode", "[scaling]\nn = [4, 4]\n", "scaling.n must hold two or more distinct sizes"),
    # fuzz F11: each passed the check and failed a run at its filters' second or third
    # step, whose covariance float64 could not hold positive definite
    ("table1", "[scenario]\nprior_cov = 1e20\n", "table1: [scenario] prior_cov / r = 2e+21: "
     "after a first update the filters' covariance has about that condition"),
    ("table2", "[scenario]\nprior_cov = 1e15\n", "[scenario] prior_cov / meas_sd^2 = 4e+17"),
    # fuzz H3 / H4: below 1/eps but above what the fusion accepts, a run failed there
    ("table1", "[scenario]\nr = 1e-14\nprior_cov = 1.0\n", "prior_cov / r = 1e+14: after a "
     "first update the filters' covariance has about that condition (positions near r, "
     "velocities near prior_cov), beyond the 7e+13 a fusion accepts"),
    ("table2", "[scenario]\nmeas_sd = 1e-7\nprior_cov = 1.0\n", "prior_cov / meas_sd^2 = 1e+14"),
    # fuzz F5: each passed the check and failed run 0 (OverflowError, scipy's "array must
    # not contain infs", "Python int too large to convert to C int")
    ("stonesoup", "[metrics]\norder = 1e300\n", "metrics.cutoff ^ metrics.order must lie"),
    ("stonesoup", "[metrics]\ncutoff = 1e300\n", "metrics.cutoff ^ metrics.order must lie"),
    ("stonesoup", "[scenario]\nnoise_sd = [[1e300, 1.0], [3.0, 1.0], [2.0, 2.0]]\n",
     "noise_sd[0] must be [sd_x, sd_y], each in (0, 1e100]"),
    ("stonesoup", "[scenario]\ndt = 1e300\n", "steps x dt must be at most 1e10 s"),
    ("stonesoup", "[scenario]\nclutter_rate = [1e12, 1.0, 1.0]\n",
     "scenario.clutter_rate and steps: about"),
    # fuzz H14, H17, H13: targets where float64's rounding of positions exceeds the noise
    # (a fusion met covariances not positive definite; a figure ended in StopIteration)
    ("table1", "[scenario]\nx0 = [0.0, 1e30, 0.0, 0.0]\n",
     "[scenario] x0: the target reaches 1e+30 m from the origin, 4.47e+30 times sqrt(r)"),
    ("table1", "[scenario]\nx0 = [0.0, 0.0, 1e12, 0.0]\n", "x0: the target reaches 2.4e+13 m"),
    ("table2", "[scenario]\ntargets = [{x0 = [1e300, 1e300, 1e300, 1e300], birth = 0.0, "
     "death = 1.0}]\n", "[scenario] targets[0]: the target reaches 2.41e+300 m"),
    ("network", "[scenario]\nstart_radius = 1e12\n", "start_radius: the target reaches 3e+12"),
    ("stonesoup", "[scenario]\ntargets = [[1e200, 0.0, 0.0, 0.0]]\n",
     "targets[0]: the target reaches 1e+200 m from the origin, 1e+200 times the smallest "
     "noise_sd = 1"),
    ("stonesoup", "[scenario]\ntargets = [[nan, 0.0, 0.0, 0.0]]\n",
     "scenario.targets[0][0] must be a finite number, got nan"),
    # fuzz H5, H8, H9 and q = 1e30, dt = 1e30: the dynamic case's model failed at every
    # seed mid-run (H5 as a bare "LinAlgError: Matrix is not positive definite")
    ("nnode", "[dynamic]\ndt = 1e-300\n", "dynamic.dt = 1e-300, dynamic.q = 0.1, dynamic.r = "
     "0.05: the step's process noise covariance Q is not positive definite in float64 (its "
     "smallest entry, q dt^3 / 3, is 0)"),
    ("nnode", "[dynamic]\ndt = 1e30\n", "dynamic.r = 0.05: dt = 1e+30 is too long a step"),
    ("nnode", "[dynamic]\nr = 1e-30\n", "dynamic.r = 1e-30, dynamic.steps = 200: the "
     "covariance of a node detecting at every step or of one never detecting is not one a "
     "fusion accepts: covs of node 0 is numerically singular"),
    ("nnode", "[dynamic]\nq = 1e30\n", "dynamic.q = 1e+30, dynamic.r = 0.05, dynamic.steps"),
    ("nnode", "[dynamic]\ndt = 1e-8\nburn_in = 0\n", "dynamic.burn_in = 0: even two nodes "
     "that detect at every step keep linearly dependent errors"),
    # fuzz H11: the trackers' covariances beyond the fusion's condition limit at every seed
    ("stonesoup", "[scenario]\nq = 1e30\n", "scenario.q = 1e+30, dt = 1, noise_sd[0] = [1.0, "
     "3.0]: a track's covariance over min_points updates and max_misses predictions is not "
     "one a fusion accepts: covs of node 0 is numerically singular"),
    # fuzz H7: a tracker prior whose first update the fusion refuses failed every run there
    ("network", "[tracker]\nprior_vel_var = 1e300\n", "tracker.prior_pos_var = 4, "
     "tracker.prior_vel_var = 1e+300 with scenario.meas_sd = 0.05: a new track's covariance "
     "after its first update is not one a fusion accepts: covs of node 0 is numerically "
     "singular"),
    ("network", "[tracker]\nprior_pos_var = 1e-300\n", "tracker.prior_pos_var = 1e-300"),
    # fuzz H2: a span of eigenvalues beyond the fusion's condition limit failed every run
    ("nnode", "[static]\nbase_log10 = [-7.0, 7.0]\n", "static: base_log10 spans 14 decades, "
     "so a node's covariance has a condition up to 10^14, beyond the 7e+13 a fusion accepts"),
]


@pytest.fixture(autouse=True)
def nothing_runs(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a study ran")
    monkeypatch.setattr(runner, "run_all", refuse)
    for name in STUDIES:
        if not hasattr(_module(name), "run_one"):
            monkeypatch.setattr(_module(name), "run", refuse)


def _refused(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("study,text,message", CASES)
def test_a_bad_configuration_is_refused_before_anything_is_created(tmp_path, capsys, study,
                                                                   text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    out = tmp_path / "out"
    err = _refused(capsys, ["run", study, "--config", str(path), "--out", str(out)])
    assert message in err
    assert not out.exists()


@pytest.mark.parametrize("flags,message", [
    (["--workers", "0"], "--workers must be an integer from 1 to 256, got 0"),
    (["--workers", "-2"], "--workers must be an integer from 1 to 256, got -2"),
    (["--workers", "1000000"], "--workers must be an integer from 1 to 256, got 1000000"),
    (["--workers", "99999999999999999999999"], "from 1 to 256, got 99999999999999999999999"),
    (["--runs", "0"], f"{RUNS} 0"),
    (["--runs", "1"], f"{RUNS} 1"),
    (["--runs", "100000000000"], f"{RUNS} 1000000"),
    (["--seed", "-1"], "seed must be an integer >= 0, got -1"),
])
def test_bad_flags_are_refused_before_anything_is_created(tmp_path, capsys, flags, message):
    out = tmp_path / "out"
    assert message in _refused(capsys, ["run", "paper", "--out", str(out), *flags])
    assert not out.exists()


def test_a_config_file_that_is_not_utf8_is_refused_in_one_line(tmp_path, capsys):
    path = tmp_path / "binary.toml"
    path.write_bytes(b"\xff\xfe")
    out = tmp_path / "out"
    err = _refused(capsys, ["run", "table1", "--config", str(path), "--out", str(out)])
    assert f"table1: --config {path}: 'utf-8' codec can't decode byte 0xff" in err
    assert not out.exists()


def test_integers_past_int64_in_a_config_file_are_floats_or_refused_by_field(tmp_path,
                                                                            capsys):
    """Fuzz N7: prior_pos_var = 2^70 (TOML has no integer bound) reached numpy as an object
    and `run network` ended in a traceback. Past int64 an integer is read as the float it
    is; a field that must be an integer then refuses it by name, and 10^400 is refused."""
    path = tmp_path / "big.toml"
    path.write_text(f"[tracker]\nprior_pos_var = {2**70}\n")
    config = configs.load("network", quick=True, path=path)
    assert config["tracker"]["prior_pos_var"] == float(2**70)
    _module("network").check(config)
    path.write_text(f"runs = {2**70}\n")
    err = _refused(capsys, ["run", "table1", "--config", str(path), "--out", str(tmp_path)])
    assert "runs must be an integer" in err and "got 1.1805916207174113e+21" in err
    path.write_text(f"[metrics]\ncutoff = {10**400}\n")
    err = _refused(capsys, ["run", "stonesoup", "--config", str(path), "--out", str(tmp_path)])
    assert "metrics.cutoff = 10000000... (401 digits) is beyond float64's range" in err


def test_a_seed_past_int64_in_a_config_file_is_the_integer_as_from_the_command_line(
        tmp_path):
    """Fuzz of 2026-11-29 (F3): seed = 10^29 in a --config file became the float 1e+29 and
    was refused ("seed must be an integer"), while --seed 10^29 ran: a run could not be
    reproduced from a file. SeedSequence takes a seed of any size (numpy's advice for a
    fresh one is SeedSequence().entropy, 128 bits), so the file's seed stays the integer."""
    seed = 2**127 + 12345
    path = tmp_path / "seed.toml"
    path.write_text(f"seed = {seed}\n[quick]\nseed = {seed + 1}\n")
    for quick in (False, True):
        config = configs.load("table1", quick=quick, path=path)
        assert config["seed"] == seed + quick and type(config["seed"]) is int
        _module("table1").check(config)
    assert runner.seed_of(seed, 3).entropy == seed  # the runner's streams take it as it is


def test_a_config_check_runs_no_more_steps_than_its_study(tmp_path):
    """Fuzz N9: nnode's check ran the dynamic model over dynamic.steps = 10^7 before the
    memory limit could refuse them (minutes, gigabytes), and stonesoup's predicted a track
    over max_misses = 10^7 scans of a 60-step run. The limit now comes first, and the track
    is followed over at most the run's steps (identical for any count past them)."""
    path = tmp_path / "steps.toml"
    path.write_text("[dynamic]\nsteps = 10000000\n")
    with pytest.raises(configs.ConfigError, match=r"dynamic.steps = 10000000: about .* GiB"):
        _module("nnode").check(configs.load("nnode", quick=True, path=path))
    for field in ("max_misses", "min_points"):
        path.write_text(f"[scenario]\n{field} = 10000000\n")
        _module("stonesoup").check(configs.load("stonesoup", quick=True, path=path))


@pytest.mark.parametrize("command", ["run", "report"])
def test_an_empty_out_is_refused_not_taken_for_the_current_folder(tmp_path, capsys,
                                                                  monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    err = _refused(capsys, [command, "table1", "--out", ""])
    assert "--out must name a folder, got ''" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["run", "report"])
def test_an_out_that_is_a_file_is_refused_by_name(tmp_path, capsys, command):
    """Fuzz (second campaign): `run --out FILE` said only "[Errno 20] Not a directory",
    `report` that the study had not been run there."""
    path = tmp_path / "a_file"
    path.write_text("keep me")
    err = _refused(capsys, [command, "table1", "--out", str(path)])
    assert f"--out must name a folder, but {path} is a file" in err
    assert path.read_text() == "keep me"


def test_runs_flag_does_not_apply_to_a_benchmark(tmp_path, capsys):
    assert "--runs does not apply" in _refused(capsys, ["run", "backends", "--runs", "3",
                                                        "--out", str(tmp_path)])


def test_a_group_checks_every_store_before_running_any_study(tmp_path, capsys):
    """`run paper` with a table2 store of another seed: refused before table1 starts."""
    main_seed = ["run", "table2", "--out", str(tmp_path), "--seed", "1"]
    table2 = tmp_path / "table2"
    with pytest.MonkeyPatch.context() as m:  # a store with two runs of seed 1
        m.setattr(runner, "run_all", lambda run_one, config, store, **kw:
                  [store.put(i, {}, None, 0.0) for i in range(2)])
        m.setattr(_module("table2"), "report", lambda *args: None)
        assert main(main_seed) == 0
    capsys.readouterr()
    assert "another configuration" in _refused(capsys, ["run", "paper", "--out",
                                                        str(tmp_path), "--seed", "2"])
    assert not (tmp_path / "table1").exists() and (table2 / "runs.sqlite").exists()


@pytest.mark.parametrize("name", sorted(STUDIES))
def test_the_default_and_quick_configurations_pass_their_check(name):
    for quick in (False, True):
        _module(name).check(configs.load(name, quick=quick))


@pytest.mark.parametrize("name", sorted(STUDIES))
def test_a_copy_of_a_shipped_configuration_is_a_valid_config_file(name, tmp_path):
    """A user copies studies/configs/NAME.toml to edit it: the copy, [quick] table and all,
    loads to exactly the shipped configuration, with --quick and without (its [quick] was
    refused as an unknown field)."""
    path = tmp_path / "copy.toml"
    path.write_text(resources.files("studies").joinpath("configs", f"{name}.toml").read_text())
    for quick in (False, True):
        assert configs.load(name, quick, path) == configs.load(name, quick)


def test_a_config_files_own_quick_table_applies_with_quick_only(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("runs = 40\n[quick]\nruns = 3\n[quick.scenario]\nn_steps = 20\n")
    assert configs.load("table1", path=path)["runs"] == 40
    quick = configs.load("table1", quick=True, path=path)
    assert quick["runs"] == 3 and quick["scenario"]["n_steps"] == 20
    assert quick["scenario"]["dt"] == configs.load("table1")["scenario"]["dt"]
    for text, message in (("quick = 3\n", "quick must be a table ([quick]), got 3"),
                          ("[quick]\nrunz = 3\n", "[quick] has unknown field(s) ['runz']"),
                          ("[quick.scenario]\nn_stepz = 3\n",  # fuzz Q3: passed without
                           "[quick.scenario] has unknown field(s) ['n_stepz']")):  # --quick
        path.write_text(text)
        for quick in (False, True):
            with pytest.raises(configs.ConfigError, match=re.escape(message)):
                configs.load("table1", quick=quick, path=path)
    path.write_text('[quick.network.neighbours]\n"8" = [1, 2]\n')  # named entries: any name
    assert configs.load("table2", quick=True, path=path)["network"]["neighbours"] == \
        {"8": [1, 2]}


def test_a_table_of_named_entries_is_replaced_whole_and_others_merge(tmp_path):
    """What a --config names is what runs: its processing nodes, rules or sweeps replace the
    default's (merged, the default's would run too); a table of fields merges."""
    path = tmp_path / "c.toml"
    path.write_text('[network.neighbours]\n"8" = [1, 2]\n[network]\nthreshold = 0.2\n')
    net = configs.load("table2", path=path)["network"]
    assert net == {"neighbours": {"8": [1, 2]}, "association": "nearest", "threshold": 0.2}
    path.write_text('[rules]\nmine = { method = "bci", criterion = "logdet" }\n'
                    '[figure]\nrule = "mine"\n')
    config = configs.load("network", path=path)
    assert list(config["rules"]) == ["mine"] and config["network"]["level1"]["A"]
    _module("network").check(config)
    path.write_text("[sweeps]\nN = [2, 4]\n[static]\nN = 4\n")
    config = configs.load("nnode", path=path)
    assert config["sweeps"] == {"N": [2, 4]} and config["static"]["rho"] == 0.5


def test_the_growth_factor_has_one_name_in_every_configuration():
    """growth, the paper's chi^-1 >= 1, as fusion_opt takes it; no chi_inv anywhere."""
    for name in STUDIES:
        text = (Path(configs.__file__).parent / "configs" / f"{name}.toml").read_text()
        assert "chi_inv" not in text, name
    assert configs.load("table1")["fusion"]["growth"] == 1.025
    assert configs.load("table2")["fusion"]["growth"] == 1.01
    assert configs.load("network")["fusion"]["growth"] == 1.05
    assert configs.load("nnode")["static"]["growth_assumed"] == 1.5


def test_the_growth_reaches_the_fusion():
    """growth = 1 makes modified CI the CI rule exactly; 1.025 does not."""
    from studies import table1

    config = configs.load("table1")
    config["scenario"] |= {"n_steps": 30, "n_particles": 3}
    config["check"]["steps"] = 0
    seed = runner.seed_of(1, 0)
    for growth, same in ((1.0, True), (1.025, False)):
        config["fusion"]["growth"] = growth
        result, _ = table1.run_one(config, 1, seed)
        assert (result["modified CI"] == result["CI"]) is same


@pytest.mark.parametrize("name,field,value", [("table1", "scenario.q", 0.2),
                                              ("table1", "fusion.growth", 1.5),
                                              ("table2", "network.threshold", 0.5),
                                              ("table2", "metrics.cutoff", 1.0)])
def test_the_paper_values_are_shown_beside_the_paper_setting_only(name, field, value):
    """A user's own scenario is not set beside the paper's numbers (it was, row by row, as
    if comparable); the run count, seed, backend and quick settings do not change that."""
    module = _module(name)
    for quick in (False, True):
        config = configs.load(name, quick)
        config |= {"runs": 3, "seed": 1, "backend": "clarabel"}
        assert module._paper(config) == module.PAPER and module.PAPER
    table, key = field.split(".")
    config[table] = config[table] | {key: value}
    assert module._paper(config) == {}


@pytest.mark.parametrize("name", ["table1", "table2"])
def test_a_scenario_field_written_at_its_default_is_still_the_papers_setting(name):
    """Fields the shipped file leaves to the scenario's defaults, written out at those
    defaults, run the paper's setting bit for bit: its values stay beside it (fuzz Q4)."""
    module = _module(name)
    config = configs.load(name)
    built = module.scenario(config)
    config["scenario"] = config["scenario"] | {
        "region": [list(r) for r in built.region], "truth_process_noise": False}
    assert module.scenario(config) == built and module._paper(config) == module.PAPER
