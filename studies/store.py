"""SQLite store of a study's finished runs: one row per run, committed as it finishes.

The store holds the configuration the study runs with (so `report` needs no flags) and,
per run, its result, the figure data of the run the figures show, and its compute time;
and the SHA-256 of each measurement file a run wrote beside it (a benchmark's timings).
Every row carries a SHA-256 checksum of its content, and a ledger record the count and the
XOR of the digests of the stored runs (updated in the transaction that adds a run), so a
deleted or copied-in row is seen; opening a store verifies every row, the ledger and that
the file holds nothing beyond its SQLite pages, and refuses one that does not verify, with
one line. A journal left by a process killed while it committed is rolled back on
opening (SQLite's recovery: the runs committed before it are kept). Only a missing file
is a new store: an empty, truncated or foreign file is refused, never read as new. A
store of another configuration is refused too, unless it holds no runs (then the new
configuration replaces the old one, so a failed first attempt never blocks the corrected
one).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import sqlite3
import stat
from pathlib import Path
from urllib.parse import quote

import numpy as np

from fusion_opt.validation import safe_repr

from .config import config_hash

SCHEMA = "fusion-opt studies store 3"
_TABLES = (
    "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL, checksum TEXT NOT NULL)",
    "CREATE TABLE runs (idx INTEGER PRIMARY KEY, result TEXT NOT NULL, figure TEXT, "
    "seconds REAL NOT NULL, checksum TEXT NOT NULL)",
)


class StoreError(RuntimeError):
    """The store is missing, damaged, or belongs to another configuration."""


def file_digests(folder: Path, names) -> dict[str, str]:
    """{name: SHA-256 of folder/name} of the measurement files a run wrote there (the
    timings of a benchmark), which the run records so that `report` can verify them."""
    return {name: hashlib.sha256((Path(folder) / name).read_bytes()).hexdigest()
            for name in names}


def verify_files(folder: Path, digests: dict) -> None:
    """StoreError (one line) unless every file of digests {name: SHA-256} is in folder
    with its recorded SHA-256: deleted, emptied, truncated or edited since `run` wrote it."""
    for name, digest in digests.items():
        path = Path(folder) / name
        if not path.is_file():
            raise StoreError(f"{path} is missing, though the run wrote it; run the study "
                             "again to measure it")
        if file_digests(folder, [name])[name] != digest:
            raise StoreError(f"{path} does not match the checksum its run recorded (it was "
                             "changed or damaged); run the study again to measure it")


def _checksum(*fields) -> str:
    return hashlib.sha256(json.dumps(fields).encode()).hexdigest()


def _ledger(rows, start: dict | None = None) -> dict:
    """The ledger of start (none: of no runs) with rows [(idx, checksum)] added: their
    count and the XOR of their SHA-256 digests (hex), which no order changes."""
    count, xor = (0, 0) if start is None else (start["runs"], int(start["xor"], 16))
    for idx, checksum in rows:
        xor ^= int(hashlib.sha256(f"{idx}:{checksum}".encode()).hexdigest(), 16)
    return {"runs": count + len(rows), "xor": f"{xor:x}"}


def _json(value) -> str:
    """JSON text of value; numpy arrays and scalars are written as lists and numbers."""
    return json.dumps(value, default=_plain)


def _plain(obj):
    if isinstance(obj, np.ndarray | np.generic):
        return obj.tolist()
    raise TypeError(f"a study result must be JSON data, got a {type(obj).__name__}")


class Store:
    """The verified store at `path`.

    Store(path) reads an existing store (StoreError if there is none). Store(path, config)
    opens it to run `config`: a missing file becomes a new store; an existing one must
    hold this configuration (up to the run count, which it takes from config) or no runs.
    With write=False nothing is created or changed: it only checks that running config
    would be accepted. Opened to run a config, it holds a lock (an flock on path + ".lock")
    until closed, and refuses a store another process holds so.
    """

    def __init__(self, path: Path, config: dict | None = None, *, write: bool = True):
        self.path = Path(path)
        self._db = self._lock = None
        _plain_files(self.path)
        if config is not None:  # to run: no other run may be using the store
            self._lock = _lock(self.path, create=write)
            if not write:
                self._unlock()
        if not self.path.exists():
            if config is None:
                raise StoreError(f"{self.path} does not exist: the study has not been run "
                                 "there (run it first, or give the --out it was run with)")
            if write:
                self._create(config)
            return
        try:
            self._guard(self._open, write and config is not None)
            self._guard(self._verify)
            if config is not None:
                self._guard(self._claim, config, write)
        except StoreError:
            self.close()
            raise

    # -- opening -------------------------------------------------------------------------

    def _guard(self, fn, *args):
        """fn(*args), with every SQLite error turned into one line naming the file; also
        the UnicodeDecodeError of Python's sqlite3 when a damaged byte lies in the schema's
        own SQL text, which it decodes on the first statement (fuzz U7)."""
        try:
            return fn(*args)
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
            raise StoreError(f"{self.path} is not a usable study store (SQLite: {exc}); move "
                             "it away or choose another --out") from None

    def _open(self, writable: bool) -> None:
        """Open the existing file (never creates one); read-write also where a journal lies
        beside it, which SQLite rolls back only so (else: "attempt to write a readonly
        database", fuzz I1), if the file is writable."""
        journal = self.path.with_name(self.path.name + "-journal")
        recover = journal.exists() and os.access(self.path, os.W_OK)
        mode = "rw" if writable or recover else "ro"
        self._db = sqlite3.connect(f"file:{quote(str(self.path.resolve()))}?mode={mode}",
                                   uri=True)

    def _create(self, config: dict) -> None:
        """Build the new store beside path and move it there whole: an interrupted
        creation leaves no half-made store to be refused later."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        new = self.path.with_name(self.path.name + ".new")
        new.unlink(missing_ok=True)
        self._db = sqlite3.connect(new)
        with self._db:
            for sql in _TABLES:
                self._db.execute(sql)
            self._set("schema", SCHEMA)
            self._set("config", config)
            self._set("wall_time_s", 0.0)
            self._set("invocations", 0)
            self._set("ledger", _ledger([]))
        self._db.close()
        os.replace(new, self.path)
        self._open(writable=True)
        self.config = config

    def _refuse(self, what: str):
        raise StoreError(f"{self.path}: {what}; move it away or choose another --out")

    def _verify(self) -> None:
        """The file must be a store of this schema, hold nothing beyond its pages, every row
        must match its checksum and the runs the ledger; read in one transaction, so that
        a run committed meanwhile is seen whole or not at all."""
        self._db.execute("BEGIN")
        try:
            self._verify_rows()
        finally:
            self._db.execute("COMMIT")

    def _verify_rows(self) -> None:
        pages = [self._db.execute(f"PRAGMA {p}").fetchone()[0] for p in ("page_size",
                                                                         "page_count")]
        extra = self.path.stat().st_size - pages[0] * pages[1]
        if extra != 0:
            self._refuse(f"has {abs(extra)} bytes {'beyond' if extra > 0 else 'missing from'} "
                         "its SQLite pages (the file was changed or damaged)")
        tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master")}
        if not {"meta", "runs"} <= tables:
            self._refuse("is empty or not a study store (no meta and runs tables)")
        schema = self._db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
        if schema is None or schema[0] != json.dumps(SCHEMA):
            self._refuse(f"was not written by this version of the studies (schema "
                         f"{schema and schema[0]}, expected {safe_repr(SCHEMA)})")
        meta = {}
        for key, value, checksum in self._db.execute("SELECT key, value, checksum FROM meta"):
            if _checksum("meta", key, value) != checksum:
                self._refuse(f"its {safe_repr(key)} record does not match its checksum (the store "
                             f"was changed or damaged)")
            meta[key] = value
        for key in ("config", "wall_time_s", "invocations", "ledger"):
            if key not in meta:
                self._refuse(f"lacks its {safe_repr(key)} record")
        rows = []
        for idx, result, figure, seconds, checksum in self._db.execute(
                "SELECT idx, result, figure, seconds, checksum FROM runs"):
            if _checksum("run", idx, result, figure, seconds) != checksum:
                self._refuse(f"run {idx} does not match its checksum (the store was changed "
                             "or damaged)")
            rows.append((idx, checksum))
        recorded = json.loads(meta["ledger"])
        if _ledger(rows) != recorded:
            self._refuse(f"holds {len(rows)} run(s) where its ledger records "
                         f"{recorded['runs']}, or other ones (a run was deleted or added "
                         "outside the studies)")
        self.config = json.loads(meta["config"])

    def _claim(self, config: dict, write: bool) -> None:
        """Accept config if it is the stored one up to the run count, or the store is
        empty; with write, record it (the stored run count becomes config's)."""
        theirs, ours = config_hash(self.config), config_hash(config)
        if theirs != ours and self.done():
            self._refuse(f"holds {len(self.done())} run(s) of another configuration (hash "
                         f"{theirs[:12]}, this one is {ours[:12]})")
        if write and config != self.config:
            with self._db:
                self._set("config", config)
            self.config = config

    # -- rows ----------------------------------------------------------------------------

    def _set(self, key: str, value) -> None:
        text = _json(value)
        self._db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?, ?)",
                         (key, text, _checksum("meta", key, text)))

    def _get(self, key: str):
        row = self._guard(lambda: self._db.execute(
            "SELECT value FROM meta WHERE key = ?", (key,)).fetchone())
        return json.loads(row[0])

    def done(self) -> set[int]:
        """Indices of the stored runs."""
        if self._db is None:
            return set()
        return self._guard(lambda: {r[0] for r in self._db.execute("SELECT idx FROM runs")})

    def put(self, index: int, result: dict, figure, seconds: float) -> None:
        """Commit one finished run: its result, its figure data (or None), its time (s)."""
        result_text = _json(result)
        figure_text = None if figure is None else _json(figure)
        row = (index, result_text, figure_text, float(seconds))

        checksum = _checksum("run", *row)

        def insert():
            with self._db:
                self._db.execute("INSERT INTO runs VALUES (?, ?, ?, ?, ?)", (*row, checksum))
                ledger = self._get("ledger")
                self._set("ledger", _ledger([(index, checksum)], ledger))
        self._guard(insert)

    def results(self, runs: int) -> dict[int, dict]:
        """{index: result} of the stored runs with index < runs, in index order."""
        rows = self._guard(lambda: self._db.execute(
            "SELECT idx, result FROM runs WHERE idx < ? ORDER BY idx", (runs,)).fetchall())
        return {idx: json.loads(text) for idx, text in rows}

    def figure(self, index: int):
        """The figure data stored with run `index`, or None."""
        row = self._guard(lambda: self._db.execute(
            "SELECT figure FROM runs WHERE idx = ?", (index,)).fetchone())
        return None if row is None or row[0] is None else json.loads(row[0])

    def run_seconds(self) -> float:
        """Compute time summed over every stored run (s), whichever invocation ran it."""
        return self._guard(lambda: self._db.execute(
            "SELECT COALESCE(SUM(seconds), 0) FROM runs").fetchone()[0])

    def add_invocation(self, wall_seconds: float) -> None:
        """Count one `run` invocation and add its wall time."""
        wall, count = self._get("wall_time_s"), self._get("invocations")

        def update():
            with self._db:
                self._set("wall_time_s", wall + wall_seconds)
                self._set("invocations", count + 1)
        self._guard(update)

    def record_files(self, digests: dict) -> None:
        """Record {name: SHA-256} of the measurement files run wrote beside the store."""
        def update():
            with self._db:
                self._set("files", digests)
        self._guard(update)

    def files(self) -> dict:
        """{name: SHA-256} of the recorded measurement files ({} if none was recorded)."""
        row = self._guard(lambda: self._db.execute(
            "SELECT value FROM meta WHERE key = 'files'").fetchone())
        return {} if row is None else json.loads(row[0])

    def totals(self) -> dict:
        """Wall time and count of every `run` invocation, and the runs' compute time."""
        return {"wall_time_s": self._get("wall_time_s"),
                "invocations": self._get("invocations"),
                "run_compute_time_s": self.run_seconds()}

    def _unlock(self) -> None:
        if self._lock is not None:
            os.close(self._lock)  # releases the flock
            self._lock = None

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None
        self._unlock()


def _plain_files(path: Path) -> None:
    """StoreError unless the store's folder is a folder (where it exists) and the store and
    its lock are regular files (where they exist): a FIFO in place of the store blocked
    `report` and `run` in open(), deaf to Ctrl-C (fuzz N10), and a file in place of the
    folder or a folder in place of the lock gave only "[Errno 17] File exists" or
    "[Errno 21] Is a directory" (N11)."""
    check_folder(path.parent)
    for p in (path, path.with_name(path.name + ".lock")):
        if p.exists() and not stat.S_ISREG(p.stat().st_mode):
            kind = "a folder" if p.is_dir() else "not a regular file (a pipe, socket or " \
                "device)"
            raise StoreError(f"{p} is {kind}, where the study's store keeps "
                             f"{'its lock' if p != path else 'its runs'}: move it away or "
                             "choose another --out")


def check_folder(folder: Path) -> None:
    """StoreError naming why folder cannot be a study's folder (`folder_problem`)."""
    problem = folder_problem(folder)
    if problem:
        raise StoreError(f"{problem}, not the study's folder: move it away or choose another "
                         "--out")


def folder_problem(folder: Path) -> str | None:
    """Why folder cannot be a folder of a study's outputs: it, or the nearest of its
    parents that exists, is a file; or one of them is a link to nothing (mkdir said only
    "[Errno 17] File exists" or "[Errno 20] Not a directory": fuzz N11, O5). None if it
    can."""
    for p in (folder, *folder.parents):
        if p.is_symlink() and not p.exists():
            return f"{p} is a link to nothing"
        if p.exists():
            return None if p.is_dir() else f"{p} is a file"
    return None


def _lock(path: Path, create: bool) -> int | None:
    """A descriptor holding an exclusive flock on the lock file beside the store at path
    (created with its folder if create; None if there is none and create is False);
    StoreError at once if another process holds it: two runs adding to one store would
    rewrite each other's configuration."""
    lock = path.with_name(path.name + ".lock")
    if create:
        path.parent.mkdir(parents=True, exist_ok=True)
    elif not lock.exists():
        return None
    fd = os.open(lock, os.O_RDWR | os.O_CREAT if create else os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise StoreError(f"another run is using {path.parent}; wait for it or choose another "
                         "--out") from None
    return fd
