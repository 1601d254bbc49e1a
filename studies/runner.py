"""Run a Monte Carlo study: one pure function call per run, each with its own seed.

Run i gets SeedSequence(seed).spawn(runs)[i], whose stream depends only on (seed, i), so a
run's result is the same whichever executor ran it, in whatever order: serially
(workers=1), in a local process pool, or on a Dask cluster (scheduler address). A study's
`run_one(config, index, seed)` returns (result, figure): its scores as JSON data, and the
data its report's figures draw for run FIGURE_RUN (None for every other run). Each
finished run is committed to the store as it arrives, so an interrupted study resumes
where it stopped, with no run lost or repeated.

Ctrl-C (SIGINT) stops at once, and so does SIGTERM (the CLI raises KeyboardInterrupt on
either): the serial runner is interrupted inside its run; pool workers ignore SIGINT, run
in process groups of their own (`_worker`), and are terminated without waiting for their
runs. Runs that have finished by then, and arrived, are stored before KeyboardInterrupt
goes on to the caller.

A local pool first has its workers compile the library's compiled kernels, stage by stage,
a part each (`fusion_opt.core.compile_part`, KERNEL_STAGES), which on a machine with a
cold cache shortens the first runs by a third; when a worker starts to compile one, the
pool says once that the kernels are being compiled (`fusion_opt.linalg.NOTICE`; the
workers pass it on instead of saying it).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import queue
import signal
import sys
import time
from collections.abc import Callable, Iterator

import numpy as np
from tqdm import tqdm

from fusion_opt.validation import safe_repr

from .store import Store

FIGURE_RUN = 0  # the run whose figure data the report draws


class RunError(RuntimeError):
    """A run raised an exception; names the run and the exception."""


def seed_of(seed: int, index: int) -> np.random.SeedSequence:
    """Run `index`'s SeedSequence(seed).spawn(runs)[index], made alone (the same entropy
    and spawn key, so the same streams: tested), so that no list of every run's seed is
    built."""
    return np.random.SeedSequence(seed, spawn_key=(index,))


def timed_run(run_one: Callable, config: dict, index: int, seed) -> tuple:
    """(index, result, figure, seconds) of one run (module level, so executors pickle it)."""
    t0 = time.perf_counter()
    try:
        result, figure = run_one(config, index, seed)
    except Exception as exc:  # noqa: BLE001 (reported with the run that raised it)
        raise RunError(f"run {index} failed: {type(exc).__name__}: {exc}") from None
    return index, result, figure, time.perf_counter() - t0


def run_all(run_one: Callable, config: dict, store: Store, *, workers: int = 1,
            scheduler: str | None = None, progress: bool = True, label: str = "study",
            kernels=None) -> int:
    """Run every run of config["runs"] not yet in store, in a pool of at most `workers`
    processes and one per run to do; returns how many ran now. kernels: the parts of
    `fusion_opt.core.KERNEL_PARTS` the runs call (None: all), which a pool's workers
    compile before the runs."""
    runs, done = config["runs"], store.done()
    jobs = [(i, seed_of(config["seed"], i)) for i in range(runs) if i not in done]
    bar = tqdm(total=runs, initial=runs - len(jobs), unit="run", disable=not progress,
               file=sys.stderr, desc=label)
    executor = _executor(min(workers, len(jobs)), scheduler, kernels) if jobs else _Serial()
    try:
        for finished in executor.results(run_one, config, jobs):
            with _sigint_deferred():  # a run that has arrived is stored whole
                store.put(*finished)
            bar.update()
    except (KeyboardInterrupt, RunError):  # keep what has finished, then stop
        with _sigint_ignored():
            for finished in executor.finished():
                store.put(*finished)
            executor.close()
        raise
    finally:
        executor.close()
        bar.close()
    return len(jobs)


STOP = (signal.SIGINT, signal.SIGTERM)  # the CLI raises KeyboardInterrupt on either


@contextlib.contextmanager
def _sigint_deferred():
    """Hold a SIGINT or SIGTERM that arrives inside the block and raise KeyboardInterrupt
    when the block ends."""
    caught = []
    previous = {sig: signal.signal(sig, lambda *_: caught.append(True)) for sig in STOP}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if caught:
        raise KeyboardInterrupt


@contextlib.contextmanager
def _sigint_ignored():
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in STOP}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _executor(workers: int, scheduler: str | None, kernels):
    if scheduler:
        return _Dask(scheduler)
    return _Serial() if workers <= 1 else _Pool(workers, kernels)


class _Serial:
    """Runs in this process, one after the other; Ctrl-C interrupts the run in progress."""

    def results(self, run_one, config, jobs) -> Iterator[tuple]:
        for i, ss in jobs:
            yield timed_run(run_one, config, i, ss)

    def finished(self) -> list[tuple]:
        return []

    def close(self) -> None:
        pass


def _worker(compiling) -> None:
    """A pool worker: SIGINT ignored, SIGTERM (how the pool ends it) ends it, in a process
    group of its own; its first kernel compile is put on the queue `compiling` for the
    pool to tell, once for all workers (a timer, 1 s of waiting for the workers' kernels,
    told it on a busy machine whose cache was warm). Its own group keeps a signal sent to
    the study's group (kill -TERM -PGID, a service manager's stop) from the worker: one
    killed by it while taking its next task left the lock of the pool's task queue held,
    and the pool's terminate then waited for that lock for ever (the SIGTERM test with 2
    workers hung, once in about 10 runs). The main process ends the workers, as on
    Ctrl-C."""
    from fusion_opt.linalg import NOTICE

    os.setpgrp()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    NOTICE.send_to(lambda _text: compiling.put(True))


class _Pool:
    """A local process pool. Workers ignore SIGINT (a terminal's Ctrl-C reaches the whole
    process group): the main process decides, and terminates them."""

    def __init__(self, workers: int, kernels=None):
        self._compiling = multiprocessing.SimpleQueue()  # a worker started to compile
        self._pool = multiprocessing.Pool(workers, initializer=_worker,
                                          initargs=(self._compiling,))
        self._arrived: queue.SimpleQueue = queue.SimpleQueue()
        self._kernels = kernels

    def results(self, run_one, config, jobs) -> Iterator[tuple]:
        self._compile_kernels()
        for i, ss in jobs:
            self._pool.apply_async(timed_run, (run_one, config, i, ss),
                                   callback=self._arrived.put,
                                   error_callback=self._arrived.put)
        for _ in jobs:
            item = self._next()
            if isinstance(item, BaseException):
                raise item
            yield item

    def _compile_kernels(self) -> None:
        """The workers compile the library's kernels before the runs, stage by stage, the
        parts of a stage at once (`fusion_opt.core.KERNEL_STAGES`): on a cold cache and 2
        cores, 25 s and then 10.5 s for the paper study, instead of each worker compiling
        all of it on its first runs (about 70 s). On a warm cache, a load of 0.1 s. Only
        the parts the study's runs call (`run_all`'s kernels)."""
        from fusion_opt.core import KERNEL_STAGES, compile_part

        compiled: queue.SimpleQueue = queue.SimpleQueue()  # apart from the runs' results
        for stage in KERNEL_STAGES:
            parts = [p for p in stage if self._kernels is None or p in self._kernels]
            for part in parts:
                self._pool.apply_async(compile_part, (part,), callback=compiled.put,
                                       error_callback=compiled.put)
            for _ in parts:
                item = self._next(compiled)
                if isinstance(item, BaseException):
                    raise item

    def _next(self, arrived=None):
        """The next item of `arrived` (default: the runs'); while waiting, the compile
        notice once a worker has started to compile."""
        arrived = self._arrived if arrived is None else arrived
        while True:  # a short timeout keeps the wait responsive to Ctrl-C
            with contextlib.suppress(queue.Empty):
                return arrived.get(timeout=0.1)
            if not self._compiling.empty():
                from fusion_opt.linalg import NOTICE

                self._compiling.get()
                NOTICE.tell(lambda text: tqdm.write(text, file=sys.stderr))  # above the bar

    def finished(self) -> list[tuple]:
        items = []
        while not self._arrived.empty():
            item = self._arrived.get()
            if not isinstance(item, BaseException):
                items.append(item)
        return items

    def close(self) -> None:
        self._pool.terminate()
        self._pool.join()


class _Dask:
    """A dask.distributed cluster at `scheduler`."""

    def __init__(self, scheduler: str):
        try:
            from dask.distributed import Client
        except ImportError:
            msg = "--scheduler needs dask.distributed: pip install 'fusion-opt[dask]'"
            raise SystemExit(msg) from None
        try:
            self._client = Client(scheduler)
        except (ValueError, OSError) as exc:  # a malformed or unreachable address
            raise RunError(f"--scheduler {safe_repr(scheduler)}: {exc}") from None
        self._futures: list = []
        self._yielded: set[int] = set()

    def results(self, run_one, config, jobs) -> Iterator[tuple]:
        from dask.distributed import as_completed

        self._futures = [self._client.submit(timed_run, run_one, config, i, ss, pure=False)
                         for i, ss in jobs]
        for fut in as_completed(self._futures):
            item = fut.result()
            self._yielded.add(item[0])
            yield item

    def finished(self) -> list[tuple]:
        done = [f.result() for f in self._futures if f.status == "finished"]
        return [item for item in done if item[0] not in self._yielded]

    def close(self) -> None:
        if self._client.status != "closed":
            self._client.cancel(self._futures)
            self._client.close()
