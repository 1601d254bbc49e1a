"""The results store: every row verified by its checksum, a damaged or foreign file refused
with one line (never read, never treated as new), the configuration kept for `report`."""

import json
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from studies.__main__ import main
from studies.store import Store, StoreError

CONFIG = {"runs": 3, "seed": 1, "backend": "newton", "scenario": {"n_steps": 5}}


def _filled(tmp_path, runs=3):
    path = tmp_path / "runs.sqlite"
    store = Store(path, CONFIG)
    for i in range(runs):
        store.put(i, {"row": {"mse": 1.25 + i}}, {"xy": np.arange(4.0)} if i == 0 else None,
                  0.5)
    store.close()
    return path


def _refused(path, match) -> str:
    with pytest.raises(StoreError, match=match) as info:
        Store(path)
    message = str(info.value)
    assert len(message.splitlines()) == 1
    return message


def test_a_store_keeps_results_figure_data_config_and_times(tmp_path):
    store = Store(_filled(tmp_path), CONFIG)
    assert store.config == CONFIG
    assert store.results(3) == {i: {"row": {"mse": 1.25 + i}} for i in range(3)}
    assert store.results(2) == {0: {"row": {"mse": 1.25}}, 1: {"row": {"mse": 2.25}}}
    assert store.figure(0) == {"xy": [0.0, 1.0, 2.0, 3.0]} and store.figure(1) is None
    assert store.run_seconds() == 1.5
    store.add_invocation(2.0)
    store.add_invocation(3.0)
    assert store.totals() == {"wall_time_s": 5.0, "invocations": 2, "run_compute_time_s": 1.5}
    store.close()


def test_a_second_run_on_a_store_in_use_is_refused_at_once(tmp_path):
    """Two runs on one --out: the second is refused (checked or opened to run), and
    neither its configuration nor a run of it reaches the store."""
    path = tmp_path / "table1" / "runs.sqlite"
    first = Store(path, CONFIG)
    for write in (False, True):
        with pytest.raises(StoreError, match=f"^another run is using {tmp_path / 'table1'}; "
                           "wait for it or choose another --out$"):
            Store(path, CONFIG | {"seed": 2}, write=write)
    first.put(0, {"row": {"mse": 1.0}}, None, 0.5)
    first.close()
    store = Store(path, CONFIG)  # free again
    assert store.config == CONFIG and store.done() == {0}
    store.close()


def _tamper(path, sql):
    with sqlite3.connect(path) as con:
        con.execute(sql)


def test_a_digit_changed_in_a_stored_result_is_refused(tmp_path):
    path = _filled(tmp_path)
    _tamper(path, "UPDATE runs SET result = replace(result, '2.25', '2.26') WHERE idx = 1")
    _refused(path, "run 1 does not match its checksum")


def test_a_corrupted_json_byte_is_refused_not_parsed(tmp_path):
    path = _filled(tmp_path)
    _tamper(path, "UPDATE runs SET result = replace(result, '}', ']') WHERE idx = 2")
    _refused(path, "run 2 does not match its checksum")


def test_changed_figure_data_or_time_is_refused(tmp_path):
    path = _filled(tmp_path)
    _tamper(path, "UPDATE runs SET seconds = 0.25 WHERE idx = 0")
    _refused(path, "run 0 does not match its checksum")


def test_a_changed_configuration_is_refused(tmp_path):
    path = _filled(tmp_path)
    _tamper(path, "UPDATE meta SET value = replace(value, '\"seed\": 1', '\"seed\": 2') "
                  "WHERE key = 'config'")
    _refused(path, "'config' record does not match its checksum")


def test_a_store_truncated_to_zero_bytes_is_refused_not_new(tmp_path):
    path = _filled(tmp_path)
    path.write_bytes(b"")
    _refused(path, "is empty or not a study store")
    with pytest.raises(StoreError, match="is empty or not a study store"):
        Store(path, CONFIG)  # nor is it taken as a new store to run into
    assert path.read_bytes() == b""


@pytest.mark.parametrize("cut", [0.5, 0.9])
def test_a_truncated_or_overwritten_file_is_refused(tmp_path, cut):
    path = _filled(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut)])
    _refused(path, "not a usable study store|does not match its checksum|bytes missing from "
                   "its SQLite pages")
    path.write_bytes(b"this is not sqlite" * 100)
    _refused(path, "not a usable study store")


def test_bytes_appended_to_the_file_are_refused(tmp_path):
    """SQLite reads a file by its pages and ignores what follows them (fuzz I2: a store
    with garbage appended was read as intact)."""
    path = _filled(tmp_path)
    with path.open("ab") as f:
        f.write(b"garbage")
    _refused(path, "has 7 bytes beyond its SQLite pages")


def test_a_deleted_or_copied_in_run_is_refused(tmp_path):
    """Each row verifies alone, so a deleted one made the store look unfinished (fuzz I11);
    the ledger counts and hashes the runs, so it is seen, as is a row copied in from
    another store of the same configuration."""
    path = _filled(tmp_path)
    _tamper(path, "DELETE FROM runs WHERE idx = 1")
    _refused(path, r"holds 2 run\(s\) where its ledger records 3, or other ones")
    path = _filled(tmp_path / "b", runs=2)
    other = _filled(tmp_path / "c", runs=3)
    with sqlite3.connect(path) as con:
        con.execute("ATTACH ? AS other", (str(other),))
        con.execute("INSERT INTO runs SELECT * FROM other.runs WHERE idx = 2")
    _refused(path, r"holds 3 run\(s\) where its ledger records 2")


def test_a_journal_left_by_a_killed_commit_is_rolled_back_not_refused(tmp_path):
    """A process killed while it committed a run leaves a hot journal; SQLite rolls it back
    only on a read-write connection, and the store was refused ("attempt to write a
    readonly database", fuzz I1) by report and by a run that would resume it."""
    path = _filled(tmp_path)
    code = ("import os, sqlite3, sys\n"
            "db = sqlite3.connect(sys.argv[1], isolation_level=None)\n"
            "db.execute('PRAGMA cache_size=1'); db.execute('BEGIN')\n"
            "db.execute(\"INSERT INTO runs VALUES (99, ?, NULL, 1.0, 'x')\", ('x' * 300000,))\n"
            "os._exit(0)\n")
    subprocess.run([sys.executable, "-c", code, str(path)], check=True)
    assert path.with_name(path.name + "-journal").exists()
    store = Store(path)
    assert store.done() == {0, 1, 2} and store.results(3)[2] == {"row": {"mse": 3.25}}
    store.close()
    store = Store(path, CONFIG)  # and a run resumes it
    assert store.done() == {0, 1, 2}
    store.close()


def test_a_store_of_an_older_version_is_refused(tmp_path):
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as con:
        con.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
        con.execute("CREATE TABLE runs (idx INTEGER PRIMARY KEY, result TEXT NOT NULL)")
    _refused(path, "was not written by this version")


def test_only_a_missing_file_is_a_new_store_and_reading_creates_nothing(tmp_path):
    path = tmp_path / "sub" / "runs.sqlite"
    with pytest.raises(StoreError, match="has not been run there"):
        Store(path)
    Store(path, CONFIG, write=False).close()
    assert not path.parent.exists()
    store = Store(path, CONFIG)
    assert store.done() == set() and path.exists()
    store.close()


def test_another_configuration_is_refused_unless_the_store_is_empty(tmp_path):
    other = CONFIG | {"seed": 2}
    empty = tmp_path / "empty.sqlite"
    Store(empty, CONFIG).close()
    Store(empty, other).close()  # no runs: the new configuration takes the store
    assert Store(empty).config == other
    with pytest.raises(StoreError, match="holds 3 run.s. of another configuration"):
        Store(_filled(tmp_path), other)
    more = Store(_filled(tmp_path / "x"), CONFIG | {"runs": 5})  # more runs: same study
    assert more.config["runs"] == 5
    more.close()


def test_the_cli_refuses_a_damaged_store_in_one_line(tmp_path, capsys):
    folder = tmp_path / "table1"
    folder.mkdir()
    path = _filled(folder)
    _tamper(path, "UPDATE runs SET result = replace(result, '1.25', '7.25') WHERE idx = 0")
    assert main(["report", "table1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "run 0 does not match its checksum" in err


# ------------------------------------------------------------------ measurement files

BACKENDS = ("n = [2]\nN = [2, 3]\ninstances = 2\nrepeats = 1\nbatch_size = 50\nlarge = []\n"
            "batch_shapes = [[3, 2]]\nbatch_repeats = 1\n")
NETWORK = ("runs = 2\n[scenario]\nn_steps = 8\nn_targets = 2\nbirths = [0.0]\n[tracker]\n"
           "n_particles = 3\n[benchmark]\nsources = [2, 3]\ntargets_at_sources = 3\n"
           "targets = [2, 4]\nsources_at_targets = 2\nwarmup = 1\nsteps = 2\n")
DAMAGE = {  # how a measurement file is damaged after `run` wrote it
    "emptied": lambda p: p.write_text(""),
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:len(p.read_bytes()) // 2]),
    "garbage": lambda p: p.write_bytes(b"\xff\xfe garbage"),
    "NaN cell": lambda p: p.write_text(re.sub(r"\d+\.\d+", "NaN", p.read_text(), count=1)),
    "deleted": lambda p: p.unlink(),
}


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> Path:
    """OUT of a tiny backends benchmark and a tiny network study, as `run` left them."""
    out = tmp_path_factory.mktemp("measured")
    for study, text in (("backends", BACKENDS), ("network", NETWORK)):
        (out / f"{study}.toml").write_text(text)
        assert main(["run", study, "--config", str(out / f"{study}.toml"), "--out",
                     str(out), "--quiet", "--workers", "1"]) == 0
        assert main(["report", study, "--out", str(out)]) == 0  # intact: reported
    return out


def _report_refused(out, study, capsys) -> str:
    assert main(["report", study, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("damage", DAMAGE)
@pytest.mark.parametrize("study,name", [
    ("backends", "backends.csv"), ("backends", "backends_instances.csv"),
    ("backends", "machine.json"), ("network", "throughput.json")])
def test_a_damaged_or_missing_measurement_file_is_refused_by_report(measured, tmp_path, capsys,
                                                                    study, name, damage):
    out = tmp_path / "out"
    shutil.copytree(measured, out)
    DAMAGE[damage](out / study / name)
    err = _report_refused(out, study, capsys)
    assert f"{study}/{name}" in err and ("missing" in err or "checksum" in err)


def test_a_hand_edited_benchmark_meta_json_is_refused_by_report(measured, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(measured, out)
    path = out / "backends" / "meta.json"
    info = json.loads(path.read_text())
    info["config"]["instances"] = 3
    path.write_text(json.dumps(info, indent=2, sort_keys=True))
    assert "meta.json: its config, quick and files do not match its checksum" in \
        _report_refused(out, "backends", capsys)


def test_a_meta_json_nested_past_the_stack_is_refused_by_report(measured, tmp_path, capsys):
    """Fuzz of 2026-11-29: JSON nested 100,000 deep made json.loads raise RecursionError,
    a traceback where every other unreadable meta.json is refused in one line."""
    out = tmp_path / "out"
    shutil.copytree(measured, out)
    (out / "backends" / "meta.json").write_text("[" * 100_000 + "]" * 100_000)
    assert "meta.json is not readable (maximum recursion depth exceeded" in \
        _report_refused(out, "backends", capsys)


def test_a_measurement_file_its_run_did_not_record_is_refused(measured, tmp_path, capsys):
    """A throughput.json beside a store that recorded none (left by another run) is not
    shown as this run's."""
    out = tmp_path / "out"
    shutil.copytree(measured, out)
    with sqlite3.connect(out / "network" / "runs.sqlite") as con:
        con.execute("DELETE FROM meta WHERE key = 'files'")
    assert "throughput.json was not written by the run recorded in" in \
        _report_refused(out, "network", capsys)


@pytest.mark.parametrize("make", ["fifo", "lock folder", "folder file"])
def test_a_store_that_is_no_file_is_refused_at_once(tmp_path, capsys, make):
    """Fuzz N10: a FIFO in place of runs.sqlite blocked `report` and `run` in open(), deaf
    to Ctrl-C and SIGTERM; N11: a folder in place of the lock, or a file in place of the
    study's folder, gave only "[Errno 21] Is a directory" or "[Errno 17] File exists"."""
    import os

    folder = tmp_path / "table1"
    if make == "folder file":
        folder.write_text("x")
        said = f"{folder} is a file, not the study's folder"
    else:
        folder.mkdir()
        if make == "fifo":
            os.mkfifo(folder / "runs.sqlite")
            said = "runs.sqlite is not a regular file (a pipe"
        else:
            (folder / "runs.sqlite.lock").mkdir()
            said = "runs.sqlite.lock is a folder, where the study's store keeps its lock"
    for command in (["report", "table1"], ["run", "table1", "--runs", "2", "--quiet"]):
        assert main([*command, "--out", str(tmp_path)]) != 0
        assert said in capsys.readouterr().err


@pytest.mark.parametrize("make", ["dangling study folder", "out below a file", "dangling out"])
def test_an_out_that_cannot_be_a_folder_is_refused_by_name(tmp_path, capsys, make):
    """Fuzz O5: a study's folder that is a link to nothing, or an --out below a regular
    file, gave only "[Errno 17] File exists" or "[Errno 20] Not a directory"."""
    out = tmp_path / "out"
    if make == "dangling study folder":
        out.mkdir()
        for name in ("table1", "backends"):
            (out / name).symlink_to(tmp_path / "nowhere")
        said = "is a link to nothing, not the study's folder"
    elif make == "out below a file":
        (tmp_path / "f").write_text("x")
        out = tmp_path / "f" / "sub"
        said = f"--out must name a folder, but {tmp_path / 'f'} is a file"
    else:
        out.symlink_to(tmp_path / "nowhere")
        said = f"--out must name a folder, but {out} is a link to nothing"
    for command in (["run", "table1", "--runs", "2", "--quiet"], ["run", "backends", "--quick",
                                                                  "--quiet"]):
        assert main([*command, "--out", str(out)]) != 0
        assert said in capsys.readouterr().err


def test_a_damaged_byte_in_the_schema_text_is_refused_in_one_line(tmp_path, capsys):
    """Fuzz U7: a byte of the stored CREATE TABLE text set to 0xFF made Python's sqlite3
    raise UnicodeDecodeError on the first statement, a traceback from `report` and `run`."""
    path = _filled(tmp_path)
    data = bytearray(path.read_bytes())
    data[data.index(b"CREATE TABLE meta") + 7] = 0xFF
    path.write_bytes(bytes(data))
    _refused(path, "is not a usable study store .*codec can't decode")
    with pytest.raises(StoreError, match="is not a usable study store"):
        Store(path, CONFIG)
