"""Run a Monte Carlo study: one pure function call per run, each with its own seed.

Run i gets SeedSequence(seed).spawn(runs)[i], whose stream depends only on (seed, i), so a
run's result is the same whichever executor ran it, in whatever order: serially
(workers=1), in a local process pool, or on a Dask cluster (scheduler address). Each result
is committed to the SQLite store as it arrives; an interrupted study resumes where it
stopped, with no run lost or repeated.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np
from tqdm import tqdm

from .store import Store


def seeds(seed: int, runs: int) -> list[np.random.SeedSequence]:
    return np.random.SeedSequence(seed).spawn(runs)


def run_all(run_one: Callable, config: dict, store: Store, *, workers: int = 1,
            scheduler: str | None = None, progress: bool = True) -> int:
    """Run every run of config["runs"] not yet in store; returns how many ran now."""
    runs, todo = config["runs"], []
    done = store.done()
    todo = [i for i in range(runs) if i not in done]
    all_seeds = seeds(config["seed"], runs)
    bar = tqdm(total=runs, initial=runs - len(todo), unit="run", disable=not progress,
               file=sys.stderr, desc=config.get("name", "study"))
    try:
        for index, result in _execute(run_one, config, [(i, all_seeds[i]) for i in todo],
                                      workers, scheduler):
            store.put(index, result)
            bar.update()
    finally:
        bar.close()
    return len(todo)


def _execute(run_one, config, jobs, workers, scheduler) -> Iterator[tuple[int, dict]]:
    if not jobs:
        return
    if scheduler:
        yield from _dask(run_one, config, jobs, scheduler)
    elif workers <= 1:
        for i, ss in jobs:
            yield i, run_one(config, i, ss)
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {pool.submit(run_one, config, i, ss): i for i, ss in jobs}
            try:
                for fut in as_completed(futures):
                    yield futures[fut], fut.result()
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise


def _dask(run_one, config, jobs, scheduler) -> Iterator[tuple[int, dict]]:
    try:
        from dask.distributed import Client
        from dask.distributed import as_completed as dask_completed
    except ImportError:
        msg = "--scheduler needs dask.distributed: pip install 'fusion-opt[dask]'"
        raise SystemExit(msg) from None
    with Client(scheduler) as client:
        futures = {client.submit(run_one, config, i, ss, pure=False): i for i, ss in jobs}
        for fut in dask_completed(futures):
            yield futures[fut], fut.result()
