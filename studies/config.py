"""Study configurations: TOML defaults per study, a [quick] table of overrides, a user
file merged on top, and a stable hash that keys the results database."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import tomllib
from importlib import resources
from pathlib import Path


class ConfigError(ValueError):
    """A study configuration names an unknown field or holds a bad value."""


def build(cls, table: dict, section: str):
    """cls(**table) for a frozen config dataclass, TOML arrays made tuples; an unknown field
    or a value the dataclass rejects raises ConfigError naming the section."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"[{section}] has unknown field(s) {unknown}; known: {sorted(known)}")
    try:
        return cls(**_tuples(table))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[{section}]: {exc}") from None


def _tuples(x):
    if isinstance(x, dict):
        return {k: _tuples(v) for k, v in x.items()}
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    return x


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
        config = _merge(config, _user_file(path, config))
    return config


def _user_file(path, defaults: dict) -> dict:
    try:
        with open(path, "rb") as fh:
            user = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"--config {path}: {exc}") from None
    unknown = sorted(set(user) - set(defaults))
    if unknown:
        raise ConfigError(f"--config {path}: unknown field(s) {unknown}; "
                          f"known: {sorted(defaults)}")
    return user


def check_runs(config: dict) -> dict:
    """runs a positive integer, seed a non-negative integer."""
    for key, low in (("runs", 1), ("seed", 0)):
        value = config.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ConfigError(f"{key} must be an integer >= {low}, got {value!r}")
    return config


def config_hash(config: dict) -> str:
    """SHA-256 of the canonical JSON of config (the run count is left out, so a study can
    be extended with more runs without losing the ones it has)."""
    keyed = {k: v for k, v in config.items() if k != "runs"}
    return hashlib.sha256(json.dumps(keyed, sort_keys=True).encode()).hexdigest()
