"""Study configurations: TOML defaults per study, a [quick] table of overrides, a user
file merged on top, and a stable hash that keys the results database."""

from __future__ import annotations

import copy
import hashlib
import json
import tomllib
from importlib import resources
from pathlib import Path


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load(name: str, quick: bool = False, path: str | Path | None = None) -> dict:
    """The configuration of study `name`: defaults, then [quick], then the file at path."""
    text = resources.files("studies").joinpath("configs", f"{name}.toml").read_text()
    config = tomllib.loads(text)
    quick_over = config.pop("quick", {})
    if quick:
        config = _merge(config, quick_over)
    if path is not None:
        with open(path, "rb") as fh:
            config = _merge(config, tomllib.load(fh))
    return config


def config_hash(config: dict) -> str:
    """SHA-256 of the canonical JSON of config (the run count is left out, so a study can
    be extended with more runs without losing the ones it has)."""
    keyed = {k: v for k, v in config.items() if k != "runs"}
    return hashlib.sha256(json.dumps(keyed, sort_keys=True).encode()).hexdigest()
