"""Spread big batches of simulated runs over the machine's cores.

A persistent process pool evaluates slices of a batch; each worker limits BLAS to one thread so that
the processes do not fight for the cores. The workers are forked when this process runs a single
thread (fast, and scripts need no ``if __name__ == "__main__"`` guard), else started by a fork server
(a threaded parent must not fork). ``BAC_SIM_WORKERS`` sets the number of workers (1 = always in this process).

A daemonic process (a worker of a ``multiprocessing`` pool, or of a ``dask.distributed`` cluster) may not start
processes of its own, and a process that already is one of many workers (``in_this_process``) should not: there
every batch is simulated in the process itself.
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any, TypeVar

T = TypeVar("T")


class _PoolHolder:
    """The one persistent pool of this process."""

    pool: Executor | None = None
    size = 0


_LOCAL = threading.local()


@contextmanager
def in_this_process() -> Iterator[None]:
    """Within this block (this thread), batches are simulated in this process: no worker pool."""
    depth = getattr(_LOCAL, "serial", 0)
    _LOCAL.serial = depth + 1
    try:
        yield
    finally:
        _LOCAL.serial = depth


def worker_count() -> int:
    """Processes a big batch is split over: ``BAC_SIM_WORKERS``, else one per core; 1 in a daemonic process
    (it may not have children) and inside :func:`in_this_process`."""
    if getattr(_LOCAL, "serial", 0) or multiprocessing.current_process().daemon:
        return 1
    env = os.environ.get("BAC_SIM_WORKERS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            pass
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _init_worker() -> None:
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - threadpoolctl is installed with scikit-learn
        pass


def _pool(size: int) -> Executor:
    if _PoolHolder.pool is None or size != _PoolHolder.size:
        shutdown()
        ctx: Any
        if threading.active_count() == 1:
            ctx = multiprocessing.get_context("fork")
        else:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(["numpy", "scipy.linalg", "bac_sim.problems"])
        _PoolHolder.pool = ProcessPoolExecutor(max_workers=size, mp_context=ctx, initializer=_init_worker)
        _PoolHolder.size = size
    return _PoolHolder.pool


def shutdown() -> None:
    """Stop the worker processes (they are restarted on the next parallel call)."""
    if _PoolHolder.pool is not None:
        _PoolHolder.pool.shutdown(wait=True, cancel_futures=True)
    _PoolHolder.pool = None
    _PoolHolder.size = 0


atexit.register(shutdown)


def run_split(fn: Callable[..., T], jobs: Sequence[tuple[Any, ...]], parallel: bool) -> list[T]:
    """``[fn(*job) for job in jobs]``, in worker processes when ``parallel`` and there are several jobs."""
    if not parallel or len(jobs) < 2:
        return [fn(*job) for job in jobs]
    pool = _pool(min(len(jobs), worker_count()))
    futures = [pool.submit(fn, *job) for job in jobs]
    return [f.result() for f in futures]
