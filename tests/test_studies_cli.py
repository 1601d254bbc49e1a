"""The studies command line on a tiny Table 1: outputs, determinism across executors,
resuming after a kill, refusing a database of another configuration."""

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from studies.__main__ import main

TINY = """
runs = 4
[scenario]
n_steps = 60
n_particles = 10
"""


@pytest.fixture
def tiny(tmp_path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return path


def _run(tiny, out, *extra) -> str:
    rc = main(["run", "table1", "--config", str(tiny), "--out", str(out), "--quiet", *extra])
    assert rc == 0
    return (out / "table1" / "table1.csv").read_text()


def test_cli_writes_tables_figures_and_meta(tiny, tmp_path):
    _run(tiny, tmp_path / "a", "--workers", "1")
    folder = tmp_path / "a" / "table1"
    for name in ("table1.md", "table1.csv", "meta.json", "table1_measurements.png",
                 "table1_paths.png", "table1_covnorm.png"):
        assert (folder / name).stat().st_size > 0, name
    assert "modified CI" in (folder / "table1.md").read_text()
    assert main(["report", "table1", "--config", str(tiny), "--out", str(tmp_path / "a")]) == 0


def test_same_seed_same_table_whatever_the_executor(tiny, tmp_path):
    serial = _run(tiny, tmp_path / "s", "--workers", "1")
    assert _run(tiny, tmp_path / "p", "--workers", "2") == serial
    other = _run(tiny, tmp_path / "o", "--workers", "1", "--seed", "7")
    assert other != serial


def test_dask_local_cluster_gives_identical_results(tiny, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    serial = _run(tiny, tmp_path / "s", "--workers", "1")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        assert _run(tiny, tmp_path / "d", "--scheduler", cluster.scheduler_address) == serial


def _stored(db: Path) -> int:
    try:
        with sqlite3.connect(db) as con:
            return con.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    except sqlite3.Error:
        return 0


def test_killed_study_resumes_to_the_uninterrupted_table(tiny, tmp_path):
    out = tmp_path / "k"
    cmd = [sys.executable, "-m", "studies", "run", "table1", "--config", str(tiny), "--out",
           str(out), "--workers", "1", "--quiet", "--runs", "8"]
    proc = subprocess.Popen(cmd, cwd=Path(__file__).parents[1], start_new_session=True)
    db = out / "table1" / "runs.sqlite"
    deadline = time.time() + 120
    while _stored(db) < 2 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    stored = _stored(db)
    assert 2 <= stored < 8, "the kill must land part-way"
    resumed = _run(tiny, out, "--workers", "1", "--runs", "8")
    assert _stored(db) == 8
    assert resumed == _run(tiny, tmp_path / "u", "--workers", "1", "--runs", "8")


def test_database_of_another_configuration_is_refused(tiny, tmp_path, capsys):
    _run(tiny, tmp_path / "r", "--workers", "1")
    rc = main(["run", "table1", "--config", str(tiny), "--out", str(tmp_path / "r"),
               "--quiet", "--seed", "99"])
    assert rc == 2
    assert "another configuration" in capsys.readouterr().err


def test_damaged_database_is_reported(tiny, tmp_path, capsys):
    folder = tmp_path / "x" / "table1"
    folder.mkdir(parents=True)
    (folder / "runs.sqlite").write_bytes(b"this is not sqlite" * 100)
    rc = main(["run", "table1", "--config", str(tiny), "--out", str(tmp_path / "x"), "--quiet"])
    assert rc == 2
    assert "not a readable study database" in capsys.readouterr().err


@pytest.mark.parametrize("text,message", [
    ("[scenario]\nn_stepz = 5\n", "unknown field(s) ['n_stepz']"),
    ("runz = 5\n", "unknown field(s) ['runz']"),
    ("[scenario]\ndt = -1.0\n", "dt"),
    ("runs = 0\n", "runs must be an integer >= 1"),
    ("runs = [\n", "--config"),
])
def test_bad_configuration_is_reported(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    rc = main(["run", "table1", "--config", str(path), "--out", str(tmp_path), "--quiet",
               "--workers", "1"])
    assert rc == 2
    assert message in capsys.readouterr().err
