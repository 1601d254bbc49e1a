"""Command line of the studies: list, run NAME, report NAME.

    python -m studies list
    python -m studies run paper --quick          # Table 1 and Table 2, quick settings
    python -m studies run table1 --runs 200 --workers 2
    python -m studies report table1              # rebuild tables and figures from the store
"""

from __future__ import annotations

import os

# Studies parallelise over runs in processes; multi-threaded BLAS inside each process only
# contends for the same cores (measured: a 32 x 32 eigh took 6 ms instead of 0.07 ms with
# two threads). Set before numpy is first imported; a user's own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from . import config as configs  # noqa: E402
from . import meta, runner  # noqa: E402
from .store import Store, StoreError  # noqa: E402

STUDIES = {
    "table1": "studies.table1",
    "table2": "studies.table2",
    "backends": "studies.backends",
    "nnode": "studies.nnode",
}
GROUPS = {"paper": ("table1", "table2")}


def _module(name: str):
    return importlib.import_module(STUDIES[name])


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m studies", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the studies and what each does")
    names = sorted(STUDIES) + sorted(GROUPS)
    for cmd, text in (("run", "run a study (resuming stored runs), then write its report"),
                      ("report", "rebuild a study's tables and figures from stored runs")):
        s = sub.add_parser(cmd, help=text)
        s.add_argument("name", choices=names, help="study, or 'paper' for table1 and table2")
        s.add_argument("--runs", type=int, help="Monte Carlo runs (default: the config's)")
        s.add_argument("--seed", type=int, help="root seed; run i uses SeedSequence(seed)"
                       ".spawn(runs)[i] (default: the config's)")
        s.add_argument("--out", type=Path, default=Path("results"),
                       help="output folder; each study writes to OUT/NAME (default: results)")
        s.add_argument("--config", type=Path, help="TOML file merged over the defaults")
        s.add_argument("--quick", action="store_true",
                       help="the config's [quick] settings: few runs, for a first look")
        if cmd == "run":
            s.add_argument("--workers", type=int, default=None,
                           help="local processes (1 = serial; default: all cores)")
            s.add_argument("--scheduler", metavar="ADDRESS",
                           help="run on a Dask cluster at ADDRESS (needs the dask extra)")
            s.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _config(name: str, args) -> dict:
    config = configs.load(name, quick=args.quick, path=args.config)
    config["name"] = name
    if args.runs is not None:
        config["runs"] = args.runs
    if args.seed is not None:
        config["seed"] = args.seed
    return configs.check_runs(config) if "runs" in config else config


def _run_one_study(name: str, args, run: bool) -> None:
    module, config = _module(name), _config(name, args)
    out = args.out / name
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if not hasattr(module, "run_one"):  # a single-shot study (a benchmark)
        if run:
            module.run(config, out, quick=args.quick, progress=not args.quiet)
        else:
            module.report(config, out, quick=args.quick)
    else:
        store = Store(out / "runs.sqlite", configs.config_hash(config), config)
        try:
            if run:
                runner.run_all(module.run_one, config, store, workers=_workers(args),
                               scheduler=args.scheduler, progress=not args.quiet)
                if hasattr(module, "benchmark"):  # timings, measured once after the runs
                    module.benchmark(config, out, progress=not args.quiet)
            module.report(config, store.results(config["runs"]), out)
        finally:
            store.close()
    meta.write(out, study=name, config=config, seed=config.get("seed"),
               runs=config.get("runs"), wall_time_s=time.perf_counter() - t0,
               command=" ".join(sys.argv))
    print(f"{name}: wrote {out}", file=sys.stderr)


def _workers(args) -> int:
    return args.workers if args.workers is not None else (os.cpu_count() or 1)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "list":
        for name in sorted(STUDIES):
            doc = (_module(name).__doc__ or "").strip().splitlines()
            print(f"{name:10s} {doc[0] if doc else ''}")
        for group, members in GROUPS.items():
            print(f"{group:10s} runs {' and '.join(members)}")
        return 0
    try:
        for name in GROUPS.get(args.name, (args.name,)):
            _run_one_study(name, args, run=args.command == "run")
    except (StoreError, configs.ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: finished runs are stored; run the same command to resume",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
