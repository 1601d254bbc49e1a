"""Stopping a running study. Killed (SIGKILL), it loses no stored run; on Ctrl-C (SIGINT
to its process group, as a terminal sends it) or SIGTERM it stops within 2 s and says how
many runs are stored. Either way the stored runs are intact, the resumed study holds the results
of an uninterrupted one (so its tables are the same), and meta.json counts the time of
every invocation."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from studies import config as configs
from studies import table1
from studies.__main__ import main
from studies.store import Store

ROOT = Path(__file__).parents[1]
RUNS = 6
# about 0.2 s per run, so that a signal lands inside a run
CONFIG = 'backend = "newton"\n[scenario]\nn_steps = 120\nn_particles = 5\n'


def _stored(db: Path) -> int:
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
            return con.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    except sqlite3.Error:
        return 0


def _resume(config: Path, out: Path) -> dict:
    """Run the study to the end in this process; returns the stored results."""
    assert main(["run", "table1", "--config", str(config), "--out", str(out), "--quiet",
                 "--workers", "1", "--runs", str(RUNS)]) == 0
    store = Store(out / "table1" / "runs.sqlite")  # verifies every stored run
    try:
        return store.results(RUNS)
    finally:
        store.close()


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("config") / "c.toml"
    path.write_text(CONFIG)
    return path


@pytest.fixture(scope="module")
def uninterrupted(config) -> dict:
    """The result of every run computed directly, as JSON stores it: what the store of a
    study interrupted and resumed must hold."""
    cfg = configs.load("table1", path=config) | {"runs": RUNS}
    seeds = np.random.SeedSequence(cfg["seed"]).spawn(RUNS)  # the README's contract
    return {i: json.loads(json.dumps(table1.run_one(cfg, i, seeds[i])[0]))
            for i in range(RUNS)}


def _start_and_signal(config, out, workers, sig) -> tuple[subprocess.Popen, str, float]:
    """Start the study in a subprocess, send sig to its process group once 2 runs are
    stored; returns the process, its stderr and the seconds it took to stop."""
    cmd = [sys.executable, "-m", "studies", "run", "table1", "--config", str(config),
           "--out", str(out), "--workers", workers, "--quiet", "--runs", str(RUNS)]
    proc = subprocess.Popen(cmd, cwd=ROOT, start_new_session=True, stderr=subprocess.PIPE,
                            text=True)
    db = out / "table1" / "runs.sqlite"
    deadline = time.monotonic() + 60
    while _stored(db) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.01)
    t0 = time.monotonic()
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=30)
    return proc, err, time.monotonic() - t0


def _part_way(config, tmp_path, workers, sig, tries=3):
    """`_start_and_signal` into a fresh folder until the signal lands part-way (fewer than
    RUNS runs stored); returns that folder, the process, its stderr and its stop time. On
    2 loaded cores the poll that sees 2 runs stored can be held off until the study has
    stored them all (once in a full run, 2026-11-26): such an attempt shows nothing of an
    interruption and is made again; a study that ignored the signal fails every try."""
    for k in range(tries):
        out = tmp_path / f"try{k}"
        proc, err, stop = _start_and_signal(config, out, workers, sig)
        if _stored(out / "table1" / "runs.sqlite") < RUNS:
            break
    return out, proc, err, stop


def _resumes(config, out, uninterrupted) -> None:
    assert _resume(config, out) == uninterrupted
    info = json.loads((out / "table1" / "meta.json").read_text())
    assert info["invocations"] == 2
    assert info["wall_time_s"] > info["this_invocation_wall_time_s"]
    assert info["run_compute_time_s"] > 0


@pytest.mark.slow  # 4.5 s: the default run resumes after Ctrl-C (below) within its budget
def test_killed_study_resumes_to_the_uninterrupted_table(config, uninterrupted, tmp_path):
    out = _part_way(config, tmp_path, "1", signal.SIGKILL)[0]
    assert 2 <= _stored(out / "table1" / "runs.sqlite") < RUNS, "must land part-way"
    assert _resume(config, out) == uninterrupted


# SIGTERM follows SIGINT's path once the handler is set, and a pool's signal handling is
# also tested (idle workers) in the default run: those cases (7-9 s each) run with the
# slow tests, so that the default run keeps within its budget
@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM,
                                                             marks=pytest.mark.slow)])
@pytest.mark.parametrize("workers", ["1", pytest.param("2", marks=pytest.mark.slow)])
def test_ctrl_c_or_sigterm_stops_within_2_s_and_the_study_resumes(config, uninterrupted,
                                                                  tmp_path, workers, sig):
    """SIGTERM as Ctrl-C: the stored runs are said, and the invocation is counted."""
    out, proc, err, stop = _part_way(config, tmp_path, workers, sig)
    assert proc.returncode == 130, err
    assert stop < 2.0, f"stopped after {stop:.2f} s"
    stored = _stored(out / "table1" / "runs.sqlite")
    assert 2 <= stored < RUNS, "Ctrl-C must land part-way"
    assert err.strip().splitlines()[-1].startswith(
        f"interrupted: {stored} of {RUNS} runs of table1 are stored")
    assert "Traceback" not in err
    _resumes(config, out, uninterrupted)


def test_a_signal_to_the_group_of_a_study_with_idle_workers_does_not_hang_its_pool():
    """Regression: pool workers shared the study's process group, so a SIGTERM to the group
    (kill -TERM -PGID) killed an idle worker inside the task queue's lock, and the pool's
    terminate then waited for that lock for ever (the 2-worker SIGTERM test hung once in
    about 10 runs; this setting, workers idle when the signal lands, hung every time)."""
    script = (
        "import os, signal, time\n"
        "from studies import runner\n"
        "pool = runner._Pool(2)\n"
        "pool._pool.map(abs, range(4))  # then both workers wait for a task\n"
        "time.sleep(0.5)\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "os.killpg(os.getpgrp(), signal.SIGTERM)\n"
        "time.sleep(0.3)\n"
        "pool.close()\n")
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, start_new_session=True)
    try:
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
