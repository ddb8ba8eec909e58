"""Fan-out of independent jobs: ``mapper(fn, jobs, static)`` runs ``fn(job, **static)`` for every job and
yields the results in any order. The library's heavy stages (the terrain scan, the pose targets) take a
mapper: ``pool_mapper(k)`` here runs the jobs on k local processes (the CLI's ``--workers``), and
``flows.fanout.dask_mapper`` runs them as Prefect tasks on a Dask cluster. Each stage commits its results
in job order, so the bytes it writes do not depend on the mapper.
"""

from __future__ import annotations

import contextlib
import os
import socket
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any

Mapper = Callable[[Callable[..., Any], list, dict[str, Any]], Iterable[Any]]


def worker_identity() -> str:
    """``<dask worker address>/pid-<pid>`` on a Dask worker, ``<host>/pid-<pid>`` elsewhere (a process that has not
    loaded Dask's ``distributed`` is no Dask worker, and is not made to import it: a third of a second)."""
    where = socket.gethostname()
    distributed = sys.modules.get("distributed")
    if distributed is not None:
        with contextlib.suppress(ValueError):  # ValueError: not inside a Dask worker
            where = distributed.get_worker().address
    return f"{where}/pid-{os.getpid()}"


def usable_cores() -> list[int]:
    """The cores this process may run on (its affinity; every core where the platform has none), in order."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def threads_per_worker(workers: int) -> int:
    """The threads each of ``workers`` local workers may use, so that together they use this machine's cores once."""
    return max(1, len(usable_cores()) // workers)


def serial_mapper(fn: Callable[..., Any], jobs: list, static: dict[str, Any]) -> Iterator[Any]:
    for job in jobs:
        yield fn(job, **static)


def pool_mapper(workers: int, start_method: str = "fork") -> Mapper:
    """Jobs on ``workers`` local processes (in this process for one worker or one job). ``start_method``
    "spawn" starts each worker from a fresh interpreter (for work that must not inherit this process's state,
    such as a GL context)."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")

    def run(fn: Callable[..., Any], jobs: list, static: dict[str, Any]) -> Iterator[Any]:
        if workers == 1 or len(jobs) <= 1:
            yield from serial_mapper(fn, jobs, static)
            return

        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=get_context(start_method)) as pool:
            for fut in as_completed([pool.submit(fn, job, **static) for job in jobs]):
                yield fut.result()

    return run
