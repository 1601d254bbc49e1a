"""Study configurations: TOML defaults per study, a [quick] table of overrides, a user
file merged on top, and a stable hash that keys the results database.

A user file (and [quick]) is merged table by table: a field it gives replaces the
default's, and a table it gives is merged field by field, except the tables of named
entries a study lists in its NAMED (processing nodes, rules, sweeps): the file's table
replaces the default's whole, so what the file names is exactly what runs.

Each study module has a `check(config)` that refuses, before anything runs, every field
it cannot use; the helpers below give those refusals one form, a ConfigError naming the
field as the user writes it ("fusion.growth must be a number >= 1 ..., got 0.5").
The covariance growth over a missed detection is `growth` everywhere (the paper's
chi^-1 >= 1, the name fusion_opt takes); the older names are refused with a hint.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import importlib
import json
import tomllib
from collections.abc import Collection, Mapping
from importlib import resources
from pathlib import Path

import numpy as np

import fusion_opt as fo
from fusion_opt.limits import fits as limits_fits
from fusion_opt.validation import finite_real, safe_repr, short_repr


class ConfigError(ValueError):
    """A study configuration names an unknown field or holds a bad value."""


# ----------------------------------------------------------------------------- loading

def load(name: str, quick: bool = False, path: str | Path | None = None) -> dict:
    """The configuration of study `name`: defaults, then their [quick] (when quick), then
    the file at path, then its own [quick] (when quick): a copy of a shipped configuration
    is a valid file (its [quick] was refused as an unknown field). The tables of named
    entries that module studies.NAME lists in NAMED (dotted paths, "network.neighbours")
    are replaced whole by an override instead of merged into."""
    text = resources.files("studies").joinpath("configs", f"{name}.toml").read_text()
    config = tomllib.loads(text)
    named = frozenset(getattr(importlib.import_module(f"studies.{name}"), "NAMED", ()))
    quick_over = config.pop("quick", {})
    if quick:
        config = _merge(config, quick_over, named)
    if path is not None:
        user = _user_file(path, config, named)
        user_quick = user.pop("quick", {})
        config = _merge(config, user, named)
        if quick:
            config = _merge(config, user_quick, named)
    return config


def paper_setting(name: str, config: dict, scenario, fields) -> bool:
    """Whether config is the setting of the paper's runs of study `name`, beside which a
    table shows the paper's values (a user's own scenario showed them too, as if
    comparable): its scenario, as scenario(config) builds it (so a field written out at
    its default value is the default), and the shipped defaults at every one of fields
    (dotted paths, "fusion.growth")."""
    default = load(name)

    def at(c, path):
        for key in path.split("."):
            c = c[key]
        return c

    return scenario(config) == scenario(default) and \
        all(at(config, f) == at(default, f) for f in fields)


def _merge(base: dict, over: dict, named: frozenset = frozenset(), where: str = "") -> dict:
    out = copy.deepcopy(base)
    for key, value in over.items():
        at = f"{where}.{key}" if where else key
        if isinstance(value, dict) and isinstance(out.get(key), dict) and at not in named:
            out[key] = _merge(out[key], value, named, at)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _user_file(path, defaults: dict, named: frozenset = frozenset()) -> dict:
    try:
        with open(path, "rb") as fh:
            user = tomllib.load(fh)
    except (OSError, ValueError, RecursionError) as exc:  # TOMLDecodeError, UnicodeDecodeError
        if "4300" in str(exc):  # Python's own limit on the digits of an int (fuzz T4)
            exc = "an integer of more than 4,300 digits, which no field takes"
        elif isinstance(exc, RecursionError):  # arrays or tables nested thousands deep
            exc = "nested deeper than Python's parser can follow"
        raise ConfigError(f"--config {path}: {exc}") from None
    quick = user.get("quick", {})
    if not isinstance(quick, dict):
        raise ConfigError(f"--config {path}: quick must be a table ([quick]), got "
                          f"{short_repr(quick)}")
    unknown = sorted(set(user) - {"quick"} - set(defaults))
    if unknown:
        raise ConfigError(f"--config {path}: unknown field(s) {unknown}; known: "
                          f"{sorted(defaults)}{renamed_hint(unknown, defaults)}")
    _known_in(quick, defaults, named, "quick", path)  # checked with or without --quick
    return _wide_ints_as_floats(user, "")


def _known_in(over: dict, defaults: dict, named: frozenset, where: str, path) -> None:
    """Refuses a field of the table `over` (at `where`) or of its tables that `defaults`
    does not have, but inside the tables of named entries (NAMED), which name anything:
    a [quick] table is used with --quick only, and a typo in it would otherwise pass
    until then, named as a field of the table it merges into."""
    unknown = sorted(set(over) - set(defaults))
    if unknown:
        raise ConfigError(f"--config {path}: [{where}] has unknown field(s) {unknown}; "
                          f"known: {sorted(defaults)}{renamed_hint(unknown, defaults)}")
    for key, value in over.items():
        at = f"{where}.{key}"
        if isinstance(value, dict) and isinstance(defaults[key], dict) and \
                at.removeprefix("quick.") not in named:
            _known_in(value, defaults[key], named, at, path)


SEED_FIELDS = ("seed", "quick.seed")


def _wide_ints_as_floats(value, where: str):
    """value with every integer beyond int64 (TOML has no bound) as a float: numpy took
    2^70 as an object and a study's run ended in a TypeError traceback (fuzz N7). A field
    that must be an integer then refuses the float by name; one past float64's range is
    refused here. Not the seed (SEED_FIELDS), which SeedSequence takes at any size, as
    --seed does (a 128-bit SeedSequence().entropy is numpy's advice for a fresh seed)."""
    if where in SEED_FIELDS:
        return value
    if isinstance(value, dict):
        return {k: _wide_ints_as_floats(v, f"{where}.{k}" if where else k)
                for k, v in value.items()}
    if isinstance(value, list):
        return [_wide_ints_as_floats(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, int) and not isinstance(value, bool) and \
            not -(2**63) <= value < 2**63:
        try:
            return float(value)
        except OverflowError:
            raise ConfigError(f"{where} = {short_repr(value)} is beyond float64's "
                              "range") from None
    return value


RENAMED = {  # an older or library-side name -> the field a configuration uses
    "chi_inv": "growth", "chi": "growth (= 1 / chi)", "chi_inv_true": "growth_true",
    "chi_inv_assumed": "growth_assumed", "chi_stale": "growth_stale",
}


def renamed_hint(unknown, known=None) -> str:
    """' (chi_inv is now growth, ...)' for the unknown names that were renamed, else ''; a
    table that has no field of the new name (nnode's [static]: growth_true and
    growth_assumed) is given its growth fields instead."""
    def new_name(k):
        growths = sorted(f for f in (known or ()) if f.startswith("growth"))
        if known is None or RENAMED[k].split()[0] in known or not growths:
            return RENAMED[k]
        return " or ".join(growths)
    hints = [f"{k} is now {new_name(k)}" for k in unknown if k in RENAMED]
    return f" ({'; '.join(hints)}: the covariance growth over a missed detection, the " \
           "paper's chi^-1 >= 1)" if hints else ""


def config_hash(config: dict) -> str:
    """SHA-256 of the canonical JSON of config (the run count is left out, so a study can
    be extended with more runs without losing the ones it has)."""
    keyed = {k: v for k, v in config.items() if k != "runs"}
    return hashlib.sha256(json.dumps(keyed, sort_keys=True).encode()).hexdigest()


# ---------------------------------------------------------------------------- checking

def fields(table, where: str, required: Collection[str],
           optional: Collection[str] = ()) -> dict:
    """table (the section `where` of a configuration; "" for the whole), which must be a
    table holding every required field and no field outside required and optional."""
    label = f"[{where}]" if where else "the configuration"
    if not isinstance(table, Mapping):
        raise ConfigError(f"{label} must be a table, got {safe_repr(table)}")
    unknown = sorted(set(table) - set(required) - set(optional))
    if unknown:
        raise ConfigError(f"{label} has unknown field(s) {unknown}; known: "
                          f"{sorted({*required, *optional})}"
                          f"{renamed_hint(unknown, {*required, *optional})}")
    missing = sorted(set(required) - set(table))
    if missing:
        raise ConfigError(f"{label} lacks field(s) {missing}")
    return table


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _refuse(where: str, kind: str, value, why: str = "", **bounds) -> None:
    """ConfigError: where must be a <kind> <bounds> (why), got value."""
    ops = {"low": ">=", "high": "<=", "above": ">"}
    rule = " and ".join(f"{ops[k]} {v}" for k, v in bounds.items() if v is not None)
    raise ConfigError(f"{where} must be {kind}{' ' + rule if rule else ''}"
                      f"{f' ({why})' if why else ''}, got {safe_repr(value)}")


def number(where: str, value, low: float | None = None, high: float | None = None, *,
           above: float | None = None, why: str = "") -> float:
    """A finite number in [low, high] and > above (each bound optional)."""
    ok = _is_number(value) and finite_real(value) is not None  # TOML ints of any size
    if not (ok and (low is None or value >= low) and (high is None or value <= high)
            and (above is None or value > above)):
        _refuse(where, "a finite number", value, why, low=low, high=high, above=above)
    return float(value)


def integer(where: str, value, low: int | None = None, high: int | None = None, *,
            why: str = "") -> int:
    """An integer (not a bool, not a float) in [low, high]."""
    ok = isinstance(value, int) and not isinstance(value, bool)
    if not (ok and (low is None or value >= low) and (high is None or value <= high)):
        _refuse(where, "an integer", value, why, low=low, high=high)
    return value


def probability(where: str, value) -> float:
    """A number in [0, 1]."""
    return number(where, value, low=0, high=1)


def growth(where: str, value) -> float:
    """A covariance growth over a missed detection: the paper's chi^-1, a number >= 1
    (fusion_opt's `growth`; chi = 1 / growth)."""
    return number(where, value, low=1, why="the paper's chi^-1, the covariance growth over "
                  "a missed detection")


def table(value, where: str, rules: dict) -> dict:
    """A table with exactly the fields of rules {field: check(where, value)}, each checked."""
    fields(value, where, rules)
    for key, rule in rules.items():
        rule(f"{where}.{key}", value[key])
    return value


def sources(value, where: str, member, item: str = "source") -> dict:
    """A table {processing node: [its sources]} naming at least one node, each source
    checked by member(where, source) and none listed twice (`item` names them)."""
    if not isinstance(value, dict) or not value:
        raise ConfigError(f"{where} must be a table naming at least one processing node, got "
                          f"{safe_repr(value)}")
    for name, members in value.items():
        for i, k in enumerate(items(f"{where}.{name}", members)):
            member(f"{where}.{name}[{i}]", k)
        if len(set(members)) != len(members):
            raise ConfigError(f"{where}.{name} names a {item} twice: {safe_repr(members)}")
    return value


def choice(where: str, value, options: Collection[str]) -> str:
    if not isinstance(value, str) or value not in options:
        raise ConfigError(f"{where} must be one of {list(options)}, got {safe_repr(value)}")
    return value


def items(where: str, value, length: int | None = None) -> list:
    """A non-empty list (of the given length)."""
    if not isinstance(value, list | tuple) or not value or (
            length is not None and len(value) != length):
        what = f"a list of {length} values" if length else "a non-empty list"
        raise ConfigError(f"{where} must be {what}, got {safe_repr(value)}")
    return list(value)


MAX_RUNS = 10_000  # the bootstrap of a table cell draws 2000 x runs indices
INTERVAL_RUNS = "a 95% interval needs two or more runs"


def run_fields(config: dict) -> None:
    """runs an integer in [2, MAX_RUNS] (every Monte Carlo study reports 95% intervals
    over its runs), seed a non-negative integer of any size."""
    integer("runs", config.get("runs"), low=2, high=MAX_RUNS, why=INTERVAL_RUNS)
    integer("seed", config.get("seed"), low=0)


def build(cls, table: dict, section: str):
    """cls(**table) for a frozen config dataclass, TOML arrays made tuples. An unknown
    field, a value of another type than the field's default, or a value the dataclass
    rejects raises ConfigError naming the section and field."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"{section} must be a table, got {safe_repr(table)}")
    defaults = {f.name: getattr(cls(), f.name) for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(defaults))
    if unknown:
        raise ConfigError(f"[{section}] has unknown field(s) {unknown}; known: "
                          f"{sorted(defaults)}{renamed_hint(unknown, defaults)}")
    for key, value in table.items():
        _like(f"{section}.{key}", value, defaults[key])
    try:
        return cls(**_tuples(table))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[{section}] {exc}") from None


def _like(where: str, value, default) -> None:
    """Refuse value unless it has the type and nesting of the field's default value."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {safe_repr(value)}")
    elif isinstance(default, int):
        integer(where, value)
    elif isinstance(default, float):
        number(where, value)
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {safe_repr(value)}")
    elif dataclasses.is_dataclass(default):
        _like_dataclass(where, value, default)
    elif isinstance(default, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where} must be a list, got {safe_repr(value)}")
        if default:  # the first entry is the template of every entry
            for i, v in enumerate(value):
                _like(f"{where}[{i}]", v, default[0])


def _like_dataclass(where: str, value, default) -> None:
    names = [f.name for f in dataclasses.fields(default)]
    if isinstance(value, Mapping):
        unknown = sorted(set(value) - set(names))
        if unknown:
            raise ConfigError(f"{where} has unknown field(s) {unknown}; known: {names}")
        pairs = value.items()
    elif isinstance(value, list | tuple):
        pairs = zip(names, value, strict=False)
    else:
        raise ConfigError(f"{where} must be a table with fields {names}, got {safe_repr(value)}")
    for key, v in pairs:
        _like(f"{where}.{key}", v, getattr(default, key))


def _tuples(x):
    if isinstance(x, dict):
        return {k: _tuples(v) for k, v in x.items()}
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    return x


def fits(where: str, n_bytes: float, limit: str = "array_memory") -> None:
    """Refuse sizes (named by where) whose arrays take about n_bytes, over the limit of
    fusion_opt.limits of that name (`fusion_opt.limits.fits`, as a ConfigError): checked
    before a run allocates them."""
    try:
        limits_fits(where, n_bytes, limit)
    except fo.FusionInputError as exc:
        raise ConfigError(str(exc)) from None


def fusion_fits(where: str, n: int, N: int, backend: str) -> None:
    """Refuse a fusion of N estimates of dimension n by backend that fusion_opt would
    refuse for its memory (its own estimate, fusion_opt.core.over_memory), before any run
    starts."""
    over = fo.core.over_memory(fo.core.request("bci", "trace", backend, {}), n, N)
    if over is not None:
        fits(where, over[1], over[2])


def fusable(where: str, covs) -> None:
    """Refuse covariances (k, n, n), k >= 2, that a fusion would refuse (not positive
    definite, or beyond its condition limit: fusion_opt's own validation, by a naive fusion
    of them), as a ConfigError: where names the fields that made them, then the reason."""
    covs = np.asarray(covs, dtype=float)
    try:
        fo.fuse(np.zeros(covs.shape[:-1]), covs, method="naive")
    except fo.FusionInputError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def construct(section: str, make, *args, **kwargs):
    """make(*args, **kwargs) (a tracker, as a run builds it: its own checks of sizes and
    settings), a refusal (ValueError) becoming a ConfigError naming the section."""
    try:
        return make(*args, **kwargs)
    except ValueError as exc:
        raise ConfigError(f"[{section}] {exc}") from None


def backend(where: str, value, nodes: int) -> str:
    """A weight solver of fusion_opt.BACKENDS able to fuse up to `nodes` estimates."""
    choice(where, value, fo.BACKENDS)
    if value == "closed-form" and nodes > 2:
        raise ConfigError(f"{where} 'closed-form' fuses two estimates only, but this "
                          f"configuration fuses up to {nodes}; choose another of "
                          f"{list(fo.BACKENDS)}")
    return value
