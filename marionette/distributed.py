"""Multi-process training on one machine or several: torchrun launches, process groups from its environment,
rank queries.

On one machine torchrun's rendezvous is ``--standalone`` (loopback, a free port). On several (``Nodes`` with
``nnodes`` > 1) it is static: node 0 hosts it at ``master_addr:master_port`` and every node runs the same
command with its own ``node_rank``; the ranks of node r are ``r * nproc .. (r + 1) * nproc - 1``. The
training directory must be one directory every node sees (a shared filesystem): rank 0 alone writes the
checkpoints and the summary, and every rank resumes from what it finds there.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from marionette.io import read_json, write_json

# torch is imported by the functions that use it: a training command's options (``Nodes`` and its checks) are read
# by its ``--help`` and by the launcher, neither of which needs torch.


def rank_world() -> tuple[int, int]:
    """(rank, world size) of this process: (0, 1) outside a process group."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


@contextmanager
def process_group_from_env() -> Iterator[None]:
    """Under torchrun (WORLD_SIZE > 1 in the environment), join the process group for the block and leave it
    after; otherwise do nothing. Where torch sees a GPU, each rank takes its LOCAL_RANK device and collectives on
    CUDA tensors go through NCCL, those on CPU tensors through gloo (a trainer may run on the CPU of a GPU machine);
    elsewhere gloo alone. A block that ends normally ends at a barrier; one that raises leaves at once."""
    import torch
    import torch.distributed as dist

    started = False
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        if torch.cuda.is_available():
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group("cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo")
        started = True
    try:
        yield
        if started:  # every rank leaves together: none tears its group down while another still uses it
            dist.barrier()
    finally:
        if started:
            dist.destroy_process_group()


@dataclass(frozen=True)
class Nodes:
    """The machines of one training run, as torchrun's static rendezvous names them: ``nnodes`` of them,
    this one ``node_rank``; node 0 hosts the rendezvous at ``master_addr:master_port`` (required with more
    than one node, refused with one, whose rendezvous is a loopback one on a free port)."""

    nnodes: int = 1
    node_rank: int = 0
    master_addr: str | None = None
    master_port: int | None = None

    def __post_init__(self) -> None:
        if (why := nodes_problem(self.nnodes, self.node_rank, self.master_addr, self.master_port)) is not None:
            raise ValueError(why)

    def torchrun_arguments(self, nproc: int) -> list[str]:
        """torchrun's rendezvous and process arguments for ``nproc`` processes on this node."""
        if self.nnodes == 1:
            return ["--standalone", f"--nproc-per-node={nproc}"]
        return [
            f"--nnodes={self.nnodes}",
            f"--node-rank={self.node_rank}",
            f"--master-addr={self.master_addr}",
            f"--master-port={self.master_port}",
            f"--nproc-per-node={nproc}",
        ]


def host_problem(host: str) -> str | None:
    """What is wrong with ``host`` as the address of node 0 (a host name or an IP address), or None."""
    if not host.strip():
        return "expected a host name or an IP address, not an empty string"
    if any(c.isspace() for c in host) or "/" in host:
        return f"expected a host name or an IP address (no scheme, path or spaces), not {host!r}"
    if host.count(":") == 1:
        return f"expected a host without a port (give the port with --master-port), not {host!r}"
    return None


def port_problem(port: int) -> str | None:
    """What is wrong with ``port`` as a TCP port, or None."""
    return None if 1 <= port <= 65535 else f"a TCP port runs from 1 to 65535, not {port}"


def nodes_problem(nnodes: int, node_rank: int, master_addr: str | None, master_port: int | None) -> str | None:
    """What is wrong with these node options taken together (each named by its flag), or None."""
    if nnodes < 1:
        return f"--nnodes must be at least 1, not {nnodes}"
    if not 0 <= node_rank < nnodes:
        return f"--node-rank must be at least 0 and below --nnodes ({nnodes}), not {node_rank}"
    if nnodes == 1:
        given = [flag for flag, v in (("--master-addr", master_addr), ("--master-port", master_port)) if v is not None]
        if given:
            return f"{' and '.join(given)} only with --nnodes > 1 (one machine's rendezvous is a loopback one on a free port)"
        return None
    missing = [flag for flag, v in (("--master-addr", master_addr), ("--master-port", master_port)) if v is None]
    if missing:
        return f"--nnodes {nnodes} needs {' and '.join(missing)} (where node 0 hosts the rendezvous)"
    return host_problem(master_addr) or port_problem(master_port)


ONE_NODE = Nodes()  # one machine: a loopback rendezvous


def train_under_torchrun(
    module: str,
    corpus: Path | str,
    out_dir: Path | str,
    config_json: dict,
    nproc: int,
    summary: str = "summary.json",
    *,
    nodes: Nodes = ONE_NODE,
    progress: bool = False,
) -> dict:
    """Run ``python -m module CORPUS --out OUT --config OUT/train-config.json [--progress]`` in ``nproc``
    processes under torchrun (``nodes.torchrun_arguments``: a loopback rendezvous on one machine, node 0's
    on several) and return the summary JSON rank 0 wrote in OUT; on a node other than 0 that is the file
    rank 0 wrote on the shared filesystem before the ranks' last barrier, so it is there once torchrun
    returns. The ranks' output goes where ours goes; a failure raises naming OUT and the exit code."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "train-config.json", config_json)  # every node writes the same bytes (atomically)
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        *nodes.torchrun_arguments(nproc),
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
    where = f"node {nodes.node_rank} of {nodes.nnodes}, " if nodes.nnodes > 1 else ""
    if done.returncode != 0:
        raise RuntimeError(
            f"{out}: torchrun with {where}{nproc} processes failed with exit code {done.returncode} (its output is above)"
        )
    if not (out / summary).exists():
        raise RuntimeError(
            f"{out}: torchrun ({where}{nproc} processes) finished but rank 0 wrote no {summary} here; is {out} a directory every node shares?"
        )
    return read_json(out / summary)
