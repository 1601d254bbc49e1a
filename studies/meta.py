"""What a study ran on: git commit, package versions, machine.

`run` writes meta.json (the configuration, the command, and the times of every invocation
of a resumed study; a benchmark's also the SHA-256 of its measurement files and a
checksum, which `report` verifies); `report` writes report.json beside it and never
touches meta.json.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

from .store import StoreError

PACKAGES = ("numpy", "scipy", "cvxpy", "clarabel", "scs", "matplotlib", "fusion-opt")


def git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).parent, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def versions() -> dict:
    found = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = None
    return found


def machine() -> dict:
    return {"platform": platform.platform(), "processor": platform.processor(),
            "machine": platform.machine(), "cpu_count": os.cpu_count()}


def write(path: Path, **fields) -> Path:
    """The JSON file at path with the given fields plus commit, versions and machine."""
    meta = {**fields, "git_commit": git_commit(), "versions": versions(), "machine": machine()}
    Path(path).write_text(json.dumps(meta, indent=2, sort_keys=True, default=str))
    return Path(path)


def read(path: Path) -> dict:
    """The fields of a meta.json written by `write`; StoreError if it is missing or
    unreadable (a study without a store keeps its configuration there)."""
    try:
        meta = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise StoreError(f"{path} does not exist: the study has not been run there (run "
                         "it first, or give the --out it was run with)") from None
    except (OSError, ValueError, RecursionError) as exc:  # JSON nested past the stack too
        raise StoreError(f"{path} is not readable ({exc}); run the study again") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("config"), dict):
        raise StoreError(f"{path} holds no configuration; run the study again")
    if meta.get("checksum") != seal(meta["config"], meta.get("quick"), meta.get("files")):
        raise StoreError(f"{path}: its config, quick and files do not match its checksum "
                         "(it was changed or damaged); run the study again")
    return meta


def seal(config: dict, quick, files) -> str:
    """SHA-256 of what `report` reads of a benchmark's meta.json: its configuration, quick
    flag and {name: SHA-256} of its measurement files (keys sorted, as `write` writes)."""
    text = json.dumps([config, quick, files], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()
