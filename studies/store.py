"""SQLite store of a study's finished runs: one row per run, committed as it finishes.

The database is keyed by the hash of the configuration (and seed) that produced it: opening
it with another configuration is refused, never mixed. A damaged file is reported as such.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path


class StoreError(RuntimeError):
    """The results database belongs to another configuration or is damaged."""


class Store:
    """Runs of one configuration in `path`: put(index, result) commits at once."""

    def __init__(self, path: Path, config_hash: str, config: dict):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(self.path)
            self._db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT)")
            self._db.execute(
                "CREATE TABLE IF NOT EXISTS runs (idx INTEGER PRIMARY KEY, result TEXT NOT NULL)")
            self._claim(config_hash, config)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path} is not a readable study database ({exc}); "
                             "move it away or choose another --out") from None

    def _claim(self, config_hash: str, config: dict) -> None:
        row = self._db.execute("SELECT value FROM meta WHERE key = 'config_hash'").fetchone()
        if row is None:
            with self._db:
                self._db.execute("INSERT INTO meta VALUES ('config_hash', ?)", (config_hash,))
                self._db.execute("INSERT INTO meta VALUES ('config', ?)",
                                 (json.dumps(config, sort_keys=True),))
        elif row[0] != config_hash:
            raise StoreError(
                f"{self.path} holds runs of another configuration (hash {row[0][:12]}, this "
                f"one is {config_hash[:12]}); use another --out or delete the file")

    def done(self) -> set[int]:
        return {r[0] for r in self._db.execute("SELECT idx FROM runs")}

    def put(self, index: int, result: dict) -> None:
        with self._db:
            self._db.execute("INSERT INTO runs VALUES (?, ?)", (index, json.dumps(result)))

    def results(self, runs: int) -> list[dict]:
        """Results of runs 0..runs-1 in order (all must be stored)."""
        rows = dict(self._db.execute("SELECT idx, result FROM runs WHERE idx < ?", (runs,)))
        missing = [i for i in range(runs) if i not in rows]
        if missing:
            raise StoreError(f"{self.path} lacks runs {missing[:5]}...; run the study first")
        return [json.loads(rows[i]) for i in range(runs)]

    def close(self) -> None:
        self._db.close()
