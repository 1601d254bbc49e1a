"""The studies command line on a tiny Table 1: outputs, `report` from the store alone,
determinism across executors, refusing a store of another configuration, and `list`.
Killing and interrupting a running study: test_studies_interrupt.py."""

import json
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from studies import runner, store, table1
from studies.__main__ import GROUPS, STUDIES, main

ROOT = Path(__file__).parents[1]
# 40 steps, 5 particles, the exact "newton" backend and no Clarabel check steps (its own tests
# are in test_study_table1.py): a run takes about 0.05 s.
TINY = """
runs = 3
backend = "newton"
[scenario]
n_steps = 40
n_particles = 5
[check]
steps = 0
"""


@pytest.fixture
def tiny(tmp_path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return path


def _run(tiny, out, *extra, study="table1") -> str:
    rc = main(["run", study, "--config", str(tiny), "--out", str(out), "--quiet", *extra])
    assert rc == 0
    return (out / study / f"{study}.csv").read_text()


def _stored(db: Path) -> int:
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
            return con.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    except sqlite3.Error:
        return 0


def test_run_writes_tables_csv_figures_and_meta(tiny, tmp_path):
    _run(tiny, tmp_path, "--workers", "1")
    folder = tmp_path / "table1"
    for name in ("table1.md", "table1.csv", "table1_paired.csv", "meta.json",
                 "table1_measurements.png", "table1_paths.png", "table1_covnorm.png"):
        assert (folder / name).stat().st_size > 0, name
    assert "modified CI" in (folder / "table1.md").read_text()
    assert "mse_full" in (folder / "table1_paired.csv").read_text()
    info = json.loads((folder / "meta.json").read_text())
    assert info["runs"] == 3 and info["invocations"] == 1
    assert 0 < info["run_compute_time_s"] <= info["wall_time_s"]


def test_report_rebuilds_from_the_store_alone_without_simulating(tiny, tmp_path,
                                                                 monkeypatch):
    """The run's config (here 3 runs of 40 steps, not the default 100 of 960) comes from
    the store; the figures come from run 0's stored figure data, not a new simulation;
    meta.json is left as the run wrote it, and report.json says what report did."""
    _run(tiny, tmp_path, "--workers", "1")
    folder = tmp_path / "table1"
    meta_before = (folder / "meta.json").read_text()
    table_before = (folder / "table1.md").read_text()
    for name in ("table1.md", "table1.csv", "table1_paths.png"):
        (folder / name).unlink()

    def no_simulation(*args, **kwargs):
        raise AssertionError("report simulated a run")
    monkeypatch.setattr(table1, "estimates", no_simulation)
    assert main(["report", "table1", "--out", str(tmp_path)]) == 0
    assert (folder / "table1.md").read_text() == table_before
    assert (folder / "table1_paths.png").stat().st_size > 0
    assert (folder / "meta.json").read_text() == meta_before
    provenance = json.loads((folder / "report.json").read_text())
    assert provenance["runs_reported"] == 3 and provenance["command"].endswith(
        f"report table1 --out {tmp_path}")


@pytest.mark.slow  # 8 s; each table's run and report are in the default run apart
def test_report_of_the_quick_paper_needs_no_flags(tmp_path, capsys):
    """The README's flow: `run paper --quick`, then `report table1`, `report table2` and
    `report paper` (here with tiny scenarios)."""
    config = tmp_path / "tiny.toml"
    config.write_text('backend = "newton"\n[scenario]\nn_steps = 30\nn_particles = 3\n')
    assert main(["run", "paper", "--quick", "--runs", "2", "--config", str(config),
                 "--out", str(tmp_path), "--quiet", "--workers", "1"]) == 0
    for name in ("table2", "paper"):  # the README's example, and both tables
        assert main(["report", name, "--out", str(tmp_path)]) == 0, capsys.readouterr().err
    assert "(2 runs" in (tmp_path / "table2" / "table2.md").read_text()


@pytest.mark.parametrize("name", ["table1", "table2", "nnode", "network", "paper",
                                  "backends"])
def test_report_of_a_study_never_run_says_so_and_creates_nothing(tmp_path, capsys, name):
    out = tmp_path / "nothing"
    assert main(["report", name, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "has not been run there" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_report_of_one_stored_run_is_refused_not_given_zero_width_intervals(tiny, tmp_path,
                                                                            capsys):
    _run(tiny, tmp_path, "--workers", "1")
    with sqlite3.connect(tmp_path / "table1" / "runs.sqlite") as con:
        con.execute("DELETE FROM runs WHERE idx > 0")  # as if stopped after run 0,
        kept = con.execute("SELECT idx, checksum FROM runs").fetchall()  # its ledger too
        ledger = json.dumps(store._ledger(kept))
        con.execute("UPDATE meta SET value = ?, checksum = ? WHERE key = 'ledger'",
                    (ledger, store._checksum("meta", "ledger", ledger)))
    capsys.readouterr()
    assert main(["report", "table1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "holds 1 finished run(s) and a 95% interval needs two or more runs" in err


# Three and two whole runs of the study (7-9 and 5 s): with the slow tests, so that the
# default run keeps within its budget (the interrupted pool runs of
# test_studies_interrupt.py, resumed to the serial results, stay in it)
@pytest.mark.slow
def test_same_seed_same_table_whatever_the_executor(tiny, tmp_path):
    serial = _run(tiny, tmp_path / "s", "--workers", "1")
    assert _run(tiny, tmp_path / "p", "--workers", "2") == serial
    assert _run(tiny, tmp_path / "o", "--workers", "1", "--seed", "7") != serial


@pytest.mark.parametrize("seed", [0, 20180401, 2**70])
def test_a_run_seed_made_alone_is_the_spawned_one(seed):
    """runner.seed_of(seed, i) gives the streams of SeedSequence(seed).spawn(runs)[i],
    and so do the children a run spawns from it."""
    spawned = np.random.SeedSequence(seed).spawn(9)
    for i in (0, 4, 8):
        alone = runner.seed_of(seed, i)
        assert alone.generate_state(8).tolist() == spawned[i].generate_state(8).tolist()
        assert ([c.generate_state(4).tolist() for c in alone.spawn(3)]
                == [c.generate_state(4).tolist() for c in spawned[i].spawn(3)])


def test_a_pool_never_has_more_workers_than_runs_to_do(tiny, tmp_path, monkeypatch):
    started = []
    monkeypatch.setattr(runner, "_Pool", lambda workers, kernels: started.append(
        (workers, kernels)) or runner._Serial())
    _run(tiny, tmp_path, "--workers", "256")
    assert started == [(3, table1.KERNELS)]  # and its workers compile what table 1 calls


@pytest.mark.slow
def test_dask_local_cluster_gives_identical_results(tiny, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    serial = _run(tiny, tmp_path / "s", "--workers", "1")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        assert _run(tiny, tmp_path / "d", "--scheduler", cluster.scheduler_address) == serial


def test_a_scheduler_address_that_is_not_one_is_refused_in_one_line(tiny, tmp_path, capsys):
    pytest.importorskip("dask.distributed")
    assert main(["run", "table1", "--config", str(tiny), "--out", str(tmp_path), "--quiet",
                 "--scheduler", "not an address"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "--scheduler 'not an address': missing port number" in err


def test_list_into_a_reader_that_stops_early_ends_quietly():
    """`python -m studies list | head -1`: the pipe closes before list writes."""
    proc = subprocess.Popen([sys.executable, "-m", "studies", "list"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == 0 and err == ""


def test_store_of_another_configuration_is_refused_before_running(tiny, tmp_path, capsys):
    _run(tiny, tmp_path, "--workers", "1")
    before = (tmp_path / "table1" / "runs.sqlite").read_bytes()
    rc = main(["run", "table1", "--config", str(tiny), "--out", str(tmp_path), "--quiet",
               "--seed", "99"])
    assert rc == 2
    assert "another configuration" in capsys.readouterr().err
    assert (tmp_path / "table1" / "runs.sqlite").read_bytes() == before


def test_store_without_runs_does_not_block_a_corrected_configuration(tiny, tmp_path,
                                                                     monkeypatch, capsys):
    """A first attempt that fails in its first run leaves a store with no runs; the
    corrected configuration then runs into it."""
    def broken(*args, **kwargs):
        raise RuntimeError("boom")
    with monkeypatch.context() as m:
        m.setattr(table1, "estimates", broken)
        assert main(["run", "table1", "--config", str(tiny), "--out", str(tmp_path),
                     "--quiet", "--workers", "1", "--seed", "5"]) == 2
    assert "run 0 failed: RuntimeError: boom" in capsys.readouterr().err
    assert _stored(tmp_path / "table1" / "runs.sqlite") == 0
    _run(tiny, tmp_path, "--workers", "1")
    assert _stored(tmp_path / "table1" / "runs.sqlite") == 3


def test_list_shows_each_whole_description(capsys):
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    table2 = next(line for line in lines if line.startswith("table2"))
    assert table2.endswith("3 processing nodes fusing with CI and modified CI.")
    assert len(lines) == len(STUDIES) + len(GROUPS)


def test_report_of_a_benchmark_rebuilds_from_its_meta_json(tmp_path):
    config = tmp_path / "b.toml"
    config.write_text("n = [2]\nN = [2, 3]\ninstances = 2\nrepeats = 1\nbatch_size = 50\n"
                      "large = []\nbatch_shapes = [[3, 2]]\nbatch_repeats = 1\n")
    assert main(["run", "backends", "--config", str(config), "--out", str(tmp_path),
                 "--quiet"]) == 0
    folder = tmp_path / "backends"
    table, meta_before = ((folder / n).read_text() for n in ("backends.md", "meta.json"))
    (folder / "backends.md").unlink()
    assert main(["report", "backends", "--out", str(tmp_path)]) == 0
    assert (folder / "backends.md").read_text() == table
    assert (folder / "meta.json").read_text() == meta_before


def test_an_out_folder_that_cannot_be_made_is_refused_in_one_line(tiny, tmp_path, capsys):
    (tmp_path / "file").write_text("")  # a folder below a file cannot be made (an --out
    out = tmp_path / "file" / "sub"        # that is a file is refused by name, apart)
    assert main(["run", "table1", "--config", str(tiny), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1  # the file in the way, named (fuzz O5)
    assert f"--out must name a folder, but {tmp_path / 'file'} is a file" in err


def test_a_study_whose_extra_is_missing_is_listed_and_refused_in_one_line(tmp_path, capsys,
                                                                          monkeypatch):
    """The README's main job installs no extra: list still works and names the install
    command; run and report of the Stone Soup study say what to install, create nothing."""
    monkeypatch.setitem(sys.modules, "stonesoup", None)  # import stonesoup now fails
    monkeypatch.delitem(sys.modules, "studies.stonesoup", raising=False)
    assert main(["list"]) == 0
    listed = capsys.readouterr().out
    assert "pip install -e '.[stonesoup]'" in listed and "table1 " in listed
    for argv in (["run", "stonesoup", "--quick"], ["report", "stonesoup"]):
        assert main([*argv, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert "stonesoup: this study needs 'stonesoup'" in err
        assert not (tmp_path / "out").exists()


def _compiling_part(part):
    """A worker's compile_part on a cold cache: numba's compile event tells the notice
    (`NOTICE.on_start`), and the compile takes a while."""
    from fusion_opt.linalg import NOTICE

    NOTICE.tell()
    time.sleep(0.3)
    return 0.3


def _loading_part(part):
    """A worker's compile_part on a warm cache of a busy machine: a slow load, no compile
    (a timer of 1 s told the notice here)."""
    time.sleep(1.5)
    return 1.5


def _one_run(config, index, seed):
    return {}, None


@pytest.mark.parametrize("part,told", [(_compiling_part, 1), (_loading_part, 0)])
def test_a_pool_tells_once_that_its_workers_compile_and_they_say_nothing(
        part, told, monkeypatch, caplog, capfd):
    """Two workers, each compiling: one notice, from the pool, on stderr above the bar; the
    workers neither log nor print it. A slow load is no compile: no notice."""
    import fusion_opt.core
    from fusion_opt import linalg

    monkeypatch.setattr(fusion_opt.core, "compile_part", part)
    monkeypatch.setattr(linalg.NOTICE, "told", False)
    pool = runner._Pool(2, kernels=("solve", "assemble"))
    try:
        with caplog.at_level("WARNING", logger="fusion_opt"):
            list(pool.results(_one_run, {}, [(0, None), (1, None)]))
    finally:
        pool.close()
    # on stderr, a line of its own above the progress bar, not through logging
    assert capfd.readouterr().err.count(linalg.COMPILE_NOTICE + "\n") == told
    assert caplog.records == []
