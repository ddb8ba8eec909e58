"""Dask fan-out for the flows: a library stage's jobs as Prefect tasks, in a subflow whose task runner is a
Dask cluster (a task runner is fixed when a flow is defined, so the cluster is chosen per call through
``with_options``). ``dask_mapper`` is a ``marionette.fanout.Mapper``: the stage that takes it commits the
results in job order, as it does for a local pool."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from prefect import flow, task, unmapped
from prefect.cache_policies import NO_CACHE
from prefect_dask import DaskTaskRunner

from marionette.fanout import Mapper


def local_worker_env(n_workers: int) -> dict[str, str]:
    """The environment of a local cluster's workers: Mesa's llvmpipe (the pose pass's renderer) gets this
    machine's cores split between them, unless ``LP_NUM_THREADS`` is set already (a cluster's workers started
    by hand take the environment they are started with)."""
    if "LP_NUM_THREADS" in os.environ:
        return {}
    return {"LP_NUM_THREADS": str(max(1, (os.cpu_count() or 1) // max(1, n_workers)))}


def dask_runner(dask_address: str | None, n_workers: int) -> DaskTaskRunner:
    """An existing Dask scheduler by address, else a local cluster of single-threaded processes."""
    if dask_address:
        return DaskTaskRunner(address=dask_address)
    return DaskTaskRunner(
        cluster_kwargs={
            "n_workers": n_workers,
            "threads_per_worker": 1,
            "processes": True,
            "dashboard_address": ":0",
            "env": local_worker_env(n_workers),
        }
    )


@contextmanager
def dask_cluster(dask_address: str | None, n_workers: int) -> Iterator[str]:
    """The scheduler address a flow's fan-outs share: ``dask_address``, else that of a local cluster of
    ``n_workers`` single-threaded processes started for the block (one start-up for every stage of a run)."""
    if dask_address:
        yield dask_address
        return
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=":0", env=local_worker_env(n_workers)
    ) as cluster:
        yield cluster.scheduler_address


@task(cache_policy=NO_CACHE, task_run_name="{name}")
def run_job(fn, job, static: dict[str, Any], name: str):
    """One job: ``fn(job, **static)`` (``name`` is the task run's name)."""
    return fn(job, **static)


@flow(name="fan-out")
def fan_out(fn, jobs: list, static: dict[str, Any], names: list[str]) -> list:
    """``run_job`` mapped over ``jobs`` on this flow's task runner; the results in job order."""
    futures = run_job.map(unmapped(fn), jobs, unmapped(static), names)
    return [f.result() for f in futures]


def dask_mapper(name: str, dask_address: str | None, n_workers: int) -> Mapper:
    """Jobs as tasks of the subflow ``name`` on Dask: the scheduler at ``dask_address``, else a local cluster of
    ``n_workers`` processes started for the call. A task's name is its job's ``name`` attribute."""

    def run(fn, jobs: list, static: dict[str, Any]) -> list:
        if not jobs:
            return []
        names = [str(getattr(j, "name", j)) for j in jobs]
        sub = fan_out.with_options(name=name, task_runner=dask_runner(dask_address, n_workers))
        return sub(fn, jobs, static, names)

    return run
