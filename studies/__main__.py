"""Command line of the studies: list, run NAME, report NAME.

    python -m studies list
    python -m studies run paper --quick          # Table 1 and Table 2, quick settings
    python -m studies run table1 --runs 200 --workers 2
    python -m studies report table1              # rebuild tables and figures from the store

`run` checks every configuration (and every existing store) before anything runs or is
created, then runs each study, resuming its stored runs, and writes its report and
meta.json. `report` rebuilds the tables and figures from what the store holds, with the
configuration stored there; it writes report.json and leaves meta.json alone.

A study module has `check(config)` and either `run_one(config, index, seed)` ->
(result, figure) and `report(config, results, out, figure)` (a Monte Carlo study, runs in
OUT/NAME/runs.sqlite), or `run(config, out, quick=, progress=)` and
`report(config, out, quick=)` (a single-shot benchmark; its meta.json holds its config).
"""

from __future__ import annotations

import os
import signal
import sys


def _stop_while_starting(*_) -> None:
    print("interrupted while starting: nothing was run", file=sys.stderr)
    sys.exit(130)


if __name__ == "__main__":  # Ctrl-C during the imports below: one line, no traceback
    signal.signal(signal.SIGINT, _stop_while_starting)

# Studies parallelise over runs in processes; multi-threaded BLAS inside each process only
# contends for the same cores (measured: a 32 x 32 eigh took 6 ms instead of 0.07 ms with
# two threads). Set before numpy is first imported; a user's own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import ast  # noqa: E402
import importlib  # noqa: E402
import importlib.util  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from fusion_opt import FusionInputError  # noqa: E402  (a study's own input, refused)
from fusion_opt.validation import safe_repr  # noqa: E402

from . import config as configs  # noqa: E402
from . import meta, runner  # noqa: E402
from .store import (  # noqa: E402
    Store,
    StoreError,
    check_folder,
    file_digests,
    folder_problem,
    verify_files,
)

STUDIES = {
    "table1": "studies.table1",
    "table2": "studies.table2",
    "backends": "studies.backends",
    "nnode": "studies.nnode",
    "network": "studies.network",
    "stonesoup": "studies.stonesoup",
}
GROUPS = {"paper": ("table1", "table2")}
# study -> (the package it needs beyond the base install, the extra that installs it)
NEEDS = {"stonesoup": ("stonesoup", "stonesoup")}
STORE, META, REPORT = "runs.sqlite", "meta.json", "report.json"
MAX_WORKERS = 256  # local processes; a pool never has more than the runs left to do


def _module(name: str):
    """The study's module; a ConfigError (one line) when a package it needs is missing."""
    if name in NEEDS and importlib.util.find_spec(NEEDS[name][0]) is None:
        raise configs.ConfigError(f"{name}: {_missing(name)}")
    return importlib.import_module(STUDIES[name])


def _missing(name: str) -> str:
    package, extra = NEEDS[name]
    return (f"this study needs {safe_repr(package)}, which is not installed: "
            f"pip install -e '.[{extra}]'")


def _monte_carlo(module) -> bool:
    return hasattr(module, "run_one")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m studies", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the studies and what each does")
    names = sorted(STUDIES) + sorted(GROUPS)
    run = sub.add_parser("run", help="run a study (resuming stored runs), then write its "
                         "report")
    report = sub.add_parser("report", help="rebuild a study's tables and figures from its "
                            "store, with the configuration it was run with")
    for s in (run, report):
        s.add_argument("name", choices=names, help="study, or 'paper' for table1 and table2")
        s.add_argument("--out", default="results",
                       help="output folder; each study writes to OUT/NAME (default: results)")
    run.add_argument("--runs", type=int, help="Monte Carlo runs (default: the config's)")
    run.add_argument("--seed", type=int, help="root seed; run i uses SeedSequence(seed)"
                     ".spawn(runs)[i] (default: the config's)")
    run.add_argument("--config", type=Path, help="TOML file merged over the defaults")
    run.add_argument("--quick", action="store_true",
                     help="the config's [quick] settings: few runs, for a first look")
    run.add_argument("--workers", type=int, default=None,
                     help=f"local processes, 1 to {MAX_WORKERS} and at most one per run "
                     "left to do (1 = serial; default: all cores)")
    run.add_argument("--scheduler", metavar="ADDRESS",
                     help="run on a Dask cluster at ADDRESS (needs the dask extra)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _summary_line(name: str) -> str:
    """The first paragraph of the study module's docstring, on one line, read from its
    source (listing imports no study, so a study whose extra is missing is listed too)."""
    source = Path(importlib.util.find_spec(STUDIES[name]).origin).read_text()
    paragraph = (ast.get_docstring(ast.parse(source)) or "").strip().split("\n\n")[0]
    line = " ".join(paragraph.split())
    if name in NEEDS and importlib.util.find_spec(NEEDS[name][0]) is None:
        line += f" [{_missing(name)}]"
    return line


# -------------------------------------------------------------------------------- run

def _config(name: str, args) -> dict:
    """The checked configuration of study `name`; ConfigError names the study and field."""
    module = _module(name)
    try:
        config = configs.load(name, quick=args.quick, path=args.config)
        if args.runs is not None:
            if "runs" not in config:
                raise configs.ConfigError("--runs does not apply: this study is one "
                                          "benchmark, not Monte Carlo runs")
            config["runs"] = args.runs
        if args.seed is not None:
            config["seed"] = args.seed
        module.check(config)
    except configs.ConfigError as exc:
        raise configs.ConfigError(f"{name}: {exc}") from None
    return config


def _run(args) -> None:
    if args.workers is not None and not 1 <= args.workers <= MAX_WORKERS:
        raise configs.ConfigError(f"--workers must be an integer from 1 to {MAX_WORKERS}, "
                                  f"got {args.workers}")
    names = GROUPS.get(args.name, (args.name,))
    config = {name: _config(name, args) for name in names}
    for name in names:  # a store that would refuse its config, before anything runs
        if _monte_carlo(_module(name)):
            Store(args.out / name / STORE, config[name], write=False).close()
    for name in names:
        _run_study(name, config[name], args)


def _run_study(name: str, config: dict, args) -> None:
    module, out = _module(name), args.out / name
    check_folder(out)  # "[Errno 17] File exists" said less (fuzz N11, O5)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if not _monte_carlo(module):
        module.run(config, out, quick=args.quick, progress=not args.quiet)
        files = file_digests(out, module.MEASUREMENTS)
        meta.write(out / META, study=name, config=config, quick=args.quick, files=files,
                   checksum=meta.seal(config, args.quick, files), seed=config.get("seed"),
                   wall_time_s=time.perf_counter() - t0, command=args.command_line)
        print(f"{name}: wrote {out}", file=sys.stderr)
        return
    store = Store(out / STORE, config)
    try:
        try:
            runner.run_all(module.run_one, config, store, workers=_workers(args),
                           scheduler=args.scheduler, progress=not args.quiet, label=name,
                           kernels=getattr(module, "KERNELS", None))
            if hasattr(module, "benchmark"):  # timings, measured once after the runs
                module.benchmark(config, out, progress=not args.quiet)
                store.record_files(file_digests(out, module.MEASUREMENTS))
            _report_runs(module, store, out)
        finally:  # an interrupted invocation counts too
            wall = time.perf_counter() - t0
            store.add_invocation(wall)
        meta.write(out / META, study=name, config=config, quick=args.quick,
                   seed=config["seed"], runs=config["runs"], command=args.command_line,
                   this_invocation_wall_time_s=wall, **store.totals())
    except runner.RunError as exc:
        raise runner.RunError(f"{name}: {exc} ({len(store.done())} of {config['runs']} "
                              f"runs are stored in {store.path})") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"{len(store.done())} of {config['runs']} runs of {name} "
                                f"are stored in {store.path}; run the same command to "
                                "resume") from None
    finally:
        store.close()
    print(f"{name}: wrote {out}", file=sys.stderr)


def _workers(args) -> int:
    return args.workers if args.workers is not None else (os.cpu_count() or 1)


# ----------------------------------------------------------------------------- report

def _report(args) -> None:
    """Rebuild every named study's report from its store (all stores opened first, so a
    study never run is found before anything is written)."""
    sources = {}
    try:
        for name in GROUPS.get(args.name, (args.name,)):
            sources[name] = _source(name, args.out / name)
        for name, source in sources.items():
            _report_one(name, source, args)
    finally:
        for source in sources.values():
            if isinstance(source, Store):
                source.close()


def _report_one(name: str, source, args) -> None:
    t0, module, out = time.perf_counter(), _module(name), args.out / name
    if isinstance(source, Store):
        fields = {"store": str(source.path), "runs_reported": _report_runs(module, source, out)}
    else:
        module.report(source["config"], out, quick=source.get("quick", False))
        fields = {"from": str(out / META)}
    meta.write(out / REPORT, study=name, command=args.command_line,
               wall_time_s=time.perf_counter() - t0, **fields)
    print(f"{name}: rebuilt the report in {out}", file=sys.stderr)


def _source(name: str, out: Path):
    """What study `name` stored in out: its Store, or its meta.json's fields (a study
    without runs), with a configuration this version can still use."""
    module = _module(name)
    if _monte_carlo(module):
        source = Store(out / STORE)
        config = source.config
    else:
        source = meta.read(out / META)
        config = source["config"]
        _measurements(module, out, source.get("files") or {}, out / META)
    try:
        module.check(config)
    except configs.ConfigError as exc:
        raise configs.ConfigError(f"{name}: the configuration stored in {out} no longer "
                                  f"passes: {exc}") from None
    return source


def _report_runs(module, store: Store, out: Path) -> int:
    """Write the report of a Monte Carlo study from the runs in store; returns how many."""
    config = store.config
    _measurements(module, out, store.files(), store.path)
    results = store.results(config["runs"])
    if len(results) < 2:
        raise StoreError(f"{store.path} holds {len(results)} finished run(s) and "
                         f"{configs.INTERVAL_RUNS}; run the study to finish it")
    if len(results) < config["runs"]:
        print(f"note: {store.path} holds {len(results)} of {config['runs']} runs; the "
              "report shows those (run the study to finish it)", file=sys.stderr)
    module.report(config, list(results.values()), out, store.figure(runner.FIGURE_RUN))
    return len(results)


def _measurements(module, out: Path, recorded: dict, record: Path) -> None:
    """Refuse the study's measurement files (module.MEASUREMENTS, read by its report)
    unless each is as its run recorded it in `record`: one it did not record is not its
    own, one it recorded must be there unchanged (SHA-256)."""
    for name in getattr(module, "MEASUREMENTS", ()):
        if name not in recorded and (out / name).exists():
            raise StoreError(f"{out / name} was not written by the run recorded in {record}; "
                             "move it away or run the study again")
    verify_files(out, recorded)


def _out(text: str) -> Path:
    """The --out folder; an empty one is refused (it would silently be the current one),
    and so is one that cannot be a folder (`store.folder_problem`)."""
    if not text:
        raise configs.ConfigError("--out must name a folder, got ''")
    out = Path(text)
    problem = folder_problem(out)  # a file, below one, or a link to nothing (O5)
    if problem:
        raise configs.ConfigError(f"--out must name a folder, but {problem}")
    return out


def _list() -> int:
    """Print the studies and groups; a reader that stops early (`| head`) ends it quietly."""
    try:
        for name in sorted(STUDIES):
            print(f"{name:10s} {_summary_line(name)}")
        for group, members in GROUPS.items():
            print(f"{group:10s} runs {' and '.join(members)}")
        sys.stdout.flush()
    except BrokenPipeError:  # nothing more can be written (the Python docs' recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def main(argv=None) -> int:
    if signal.getsignal(signal.SIGINT) is _stop_while_starting:  # started: Ctrl-C as usual
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # SIGTERM (a kill, a job scheduler) stops like Ctrl-C: finished runs stored, counted
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    args.command_line = " ".join(["python -m studies", *argv])
    if args.command == "list":
        return _list()
    try:
        args.out = _out(args.out)
        (_run if args.command == "run" else _report)(args)
    except (StoreError, configs.ConfigError, runner.RunError, OSError,
            FusionInputError) as exc:  # OSError: an --out that cannot be written
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"interrupted{f': {exc}' if str(exc) else ''}", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
