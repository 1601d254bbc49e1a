"""What a study ran on: git commit, package versions, machine; written as meta.json."""

from __future__ import annotations

import json
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

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


def write(out_dir: Path, **fields) -> Path:
    """meta.json in out_dir with the given fields plus commit, versions and machine."""
    meta = {**fields, "git_commit": git_commit(), "versions": versions(), "machine": machine()}
    path = Path(out_dir) / "meta.json"
    path.write_text(json.dumps(meta, indent=2, sort_keys=True, default=str))
    return path
