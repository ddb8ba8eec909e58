"""Multi-process training on one machine: torchrun launches, process groups from its environment, rank queries."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch
import torch.distributed as dist

from marionette.io import write_json


def rank_world() -> tuple[int, int]:
    """(rank, world size) of this process: (0, 1) outside a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


@contextmanager
def process_group_from_env() -> Iterator[None]:
    """Under torchrun (WORLD_SIZE > 1 in the environment), join the process group for the block (NCCL on a
    GPU, each rank on its LOCAL_RANK device; gloo on CPU) and leave it after; otherwise do nothing."""
    started = False
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        if torch.cuda.is_available():
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        started = True
    try:
        yield
    finally:
        if started:
            dist.destroy_process_group()


def train_under_torchrun(
    module: str,
    corpus: Path | str,
    out_dir: Path | str,
    config_json: dict,
    nproc: int,
    summary: str = "summary.json",
    *,
    progress: bool = False,
) -> dict:
    """Run ``python -m module CORPUS --out OUT --config OUT/train-config.json [--progress]`` in ``nproc``
    processes under ``torchrun --standalone`` (a loopback rendezvous) and return the summary JSON rank 0
    wrote in OUT. The ranks' output goes where ours goes; a failure raises naming OUT and the exit code."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "train-config.json", config_json)
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc_per_node={nproc}",
        "-m",
        module,
        str(corpus),
        "--out",
        str(out),
        "--config",
        str(out / "train-config.json"),
        "--progress" if progress else "--no-progress",
    ]
    done = subprocess.run(cmd, env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    if done.returncode != 0:
        raise RuntimeError(
            f"{out}: torchrun with {nproc} processes failed with exit code {done.returncode} (its output is above)"
        )
    return json.loads((out / summary).read_text())
