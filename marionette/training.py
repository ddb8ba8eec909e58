"""The skeleton the trainers share (their config knobs and flags are ``marionette.knobs``): the warm-up + cosine
schedule, resume, the step loop, checkpoints, DDP helpers, the summary, and the launch under torchrun.

A trainer declares its config as a frozen dataclass whose fields are ``knob``s (a default, a help text,
the values it accepts), builds its data, model and optimizer, and hands ``run_steps`` a function that
computes the loss terms of global step s. That function draws everything random from (seed, s, rank)
(``noise_generator``; torch's global RNG, which dropout draws from, is seeded per step by the loop), so
a run resumed from a checkpoint draws what the uninterrupted run would have: with the weights,
optimizer and scheduler restored by ``resume``, the losses and final weights are bit-identical (same
config, world size and device).

    run = resume(out, model, opt, sched, {"train_config": config, ...})   # or a fresh Run at step 0
    run_steps(run, end, loss_at, model, opt, sched, ...)                # records, checkpoints, progress bar
    last = final_checkpoint(run, checkpoint)                            # unless nothing was trained
    finish(out, summary)                                                # summary.json (rank 0), barrier

Under DDP (``launch`` with nproc > 1, or more than one node, relaunches the command under torchrun) every
rank runs the same loop on its own batches; gradients are averaged by ``DistributedDataParallel``
(``ddp``; or onto each rank's shard of the weights by FSDP, ``fsdp``), the logged terms by
``mean_over_ranks``; rank 0 (the global rank: node 0's first process) alone logs, shows the progress
bar and writes checkpoints and the summary. On several machines (``--nnodes``, ``distributed.Nodes``)
the training directory is one they share, and ``resume`` checks that every rank found the same
checkpoint there. A finished run asked again with the same config (``finished_summary``) returns the summary it
wrote without relaunching anything.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from marionette.checkpoint import is_dtensor, latest_checkpoint, load_checkpoint, read_meta
from marionette.distributed import ONE_NODE, Nodes, process_group_from_env, rank_world, train_under_torchrun
from marionette.io import read_json, write_json
from marionette.knobs import add_training_arguments, config_from_args, nodes_from_args
from marionette.options import Parser

SUMMARY = "summary.json"  # the last run's summary (losses left out), written by rank 0 into the training directory
CADENCE_FIELDS = ("eval_every", "checkpoint_every")  # config fields a resumed run may change


# -- schedule, noise, DDP ----------------------------------------------------------------------------


def lr_factor(step: int, warmup: int, steps: int, min_ratio: float) -> float:
    """Multiplier of the peak learning rate at optimizer step ``step`` (0-based): linear warm-up over
    ``warmup`` steps, then cosine decay to ``min_ratio`` at ``steps``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min((step - warmup) / max(steps - warmup, 1), 1.0)
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def warmup_cosine(
    optimizer: torch.optim.Optimizer, warmup: int, steps: int, min_ratio: float
) -> torch.optim.lr_scheduler.LambdaLR:
    """The ``lr_factor`` schedule as a ``LambdaLR`` (its state, plain numbers, goes into checkpoints)."""
    # a lambda, not a functools.partial: LambdaLR saves the __dict__ of callable objects in its state
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, warmup, steps, min_ratio))


def noise_seed(seed: int, step: int, rank: int, stream: int = 0) -> int:
    """The noise seed of one (seed, step, rank) and ``stream`` (0: the trainer's own noise, 1: torch's global
    RNG during the step): distinct for every tuple, a function of the step so that a resumed run draws
    what an uninterrupted one would."""
    words = [int(seed), int(step), int(rank)] + ([int(stream)] if stream else [])
    return int(np.random.SeedSequence(words).generate_state(1, np.uint64)[0] >> 1)


def noise_generator(seed: int, step: int, rank: int) -> torch.Generator:
    """A CPU generator seeded by ``noise_seed(seed, step, rank)``."""
    return torch.Generator().manual_seed(noise_seed(seed, step, rank))


def ddp(module: nn.Module, device: torch.device) -> nn.Module:
    """``module`` wrapped in ``DistributedDataParallel`` inside a process group of more than one rank, else itself."""
    if rank_world()[1] == 1:
        return module
    return nn.parallel.DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)


def fsdp(module: nn.Module, units: Sequence[nn.Module], device: torch.device) -> nn.Module:
    """``module`` sharded in place by FSDP2 (``fully_shard``) over the ranks of a process group of more than one:
    each of ``units`` (its submodules, the transformer's blocks) a unit whose weights are gathered for its
    forward and backward and freed after, then ``module`` the root unit holding the rest. Its parameters become
    DTensor shards (build the optimizer on them after this; checkpoints gather them whole, ``full_state``) and
    every forward is collective. In one process: ``module`` unchanged."""
    world = rank_world()[1]
    if world == 1:
        return module
    from torch.distributed.device_mesh import init_device_mesh
    from torch.distributed.fsdp import fully_shard

    mesh = init_device_mesh(device.type, (world,))
    for unit in units:
        fully_shard(unit, mesh=mesh)
    return fully_shard(module, mesh=mesh)


def mean_over_ranks(values: Tensor) -> Tensor:
    """``values`` averaged over the ranks of the process group (in place; unchanged outside one)."""
    world = rank_world()[1]
    if world > 1:
        dist.all_reduce(values)
        values /= world
    return values


def rank_zero_log(log: Callable[[str], Any]) -> Callable[[str], None]:
    """``log`` on rank 0 (written around a progress bar, which it would otherwise break), nothing elsewhere."""
    if rank_world()[0] != 0:
        return lambda *_: None
    from tqdm import tqdm

    def say(message: str) -> None:
        with tqdm.external_write_mode():
            log(message)

    return say


# -- resume, the loop, checkpoints, summary ----------------------------------------------------------


@dataclass
class Run:
    """Where a training run stands: the steps done, their records and the evaluations (all saved in each
    checkpoint), and the checkpoint it resumed from."""

    step: int = 0
    history: list[dict] = field(default_factory=list)
    evals: list[dict] = field(default_factory=list)
    resumed_from: Path | None = None
    started: int = 0  # the step this call began at


def same_checkpoint_everywhere(out_dir: Path | str, ckpt: Path | None) -> None:
    """Check that every rank of the process group found ``ckpt`` (the latest checkpoint in ``out_dir``, or
    None): ranks on machines that do not share ``out_dir`` would resume from different steps."""
    world = rank_world()[1]
    if world == 1:
        return
    found: list[str | None] = [None] * world
    dist.all_gather_object(found, None if ckpt is None else ckpt.name)
    if len(set(found)) > 1:
        seen = ", ".join(f"rank {r}: {name or 'none'}" for r, name in enumerate(found))
        raise ValueError(
            f"{out_dir}: the ranks found different latest checkpoints ({seen}); it must be one directory every node shares"
        )


def resume(
    out_dir: Path | str,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    configs: dict[str, Any],
    may_change: Sequence[str] = CADENCE_FIELDS,
) -> Run:
    """The run in ``out_dir``: a fresh one, or the latest checkpoint's after checking that each config
    (meta key → config dataclass with ``from_json``) is the one it saved, fields in ``may_change`` aside,
    and restoring the model, optimizer, scheduler and torch RNG. A mismatch names the fields that differ."""
    ckpt = latest_checkpoint(Path(out_dir))
    same_checkpoint_everywhere(out_dir, ckpt)
    if ckpt is None:
        return Run()
    meta = read_meta(ckpt)
    differ = []
    for key, mine in configs.items():
        try:
            saved = type(mine).from_json(meta[key])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{ckpt}: its {key} does not read: {exc}") from exc
        names = [f.name for f in fields(mine) if f.name not in may_change and getattr(saved, f.name) != getattr(mine, f.name)]
        differ += names if key == "train_config" else [f"{key}.{n}" for n in names]
    if differ:
        why = " (steps shapes the learning-rate schedule: a run cannot be extended)" if "steps" in differ else ""
        raise ValueError(f"{ckpt}: was trained with another config (differs in {differ}){why}; use a fresh out_dir")
    load_checkpoint(ckpt, model, optimizer, scheduler)
    step = int(meta["step"])
    return Run(step, list(meta["losses"]), list(meta.get("evals", [])), ckpt, step)


def run_steps(
    run: Run,
    end: int,
    loss_at: Callable[[int], dict[str, Tensor]],
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    *,
    seed: int,
    objective: str,
    grad_clip: float,
    checkpoint: Callable[[int], Path | None],
    checkpoint_every: int = 0,
    evaluate: Callable[[int], Any] | None = None,
    eval_every: int = 0,
    on_record: Callable[[dict], Any] | None = None,
    log: Callable[[str], Any] = print,
    progress: bool = False,
    desc: str = "train",
) -> None:
    """Optimise from ``run.step`` to ``end``: per step, the terms ``loss_at(step)`` (``objective`` among
    them, the one minimised), backward, gradient clipping, optimizer and scheduler steps, then the record
    ``{"step", *terms, "grad_norm", "lr"}`` (terms averaged over ranks) appended to ``run.history``, logged
    every ``end // 50`` steps (or shown on the progress bar, rank 0, with ``progress``) and given to ``on_record``; ``evaluate`` and
    ``checkpoint`` every ``eval_every`` / ``checkpoint_every`` steps before ``end`` (0: never here).

    What draws from torch's global RNG during a step (dropout) draws from ``noise_seed(seed, step, rank, 1)``,
    the caller's RNG state left as it was: a fresh run is reproducible and a resumed one exact."""
    from tqdm import tqdm

    rank = rank_world()[0]
    bar = tqdm(
        total=end,
        initial=run.step,
        desc=desc,
        unit="step",
        dynamic_ncols=True,
        disable=not progress or rank != 0 or run.step >= end,
    )
    devices = [torch.cuda.current_device()] if torch.cuda.is_available() else []
    model.train()
    while run.step < end:
        with torch.random.fork_rng(devices):
            torch.manual_seed(noise_seed(seed, run.step, rank, 1))
            terms = loss_at(run.step)
            optimizer.zero_grad(set_to_none=True)
            terms[objective].backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
        if is_dtensor(grad_norm):  # FSDP's shards: the whole gradient's norm, a DTensor replicated on every rank
            grad_norm = grad_norm.full_tensor()
        lr = optimizer.param_groups[0]["lr"]
        optimizer.step()
        scheduler.step()
        run.step += 1
        values = mean_over_ranks(torch.stack([v.detach().float() for v in terms.values()] + [grad_norm.detach().float()]))
        record = {"step": run.step, **dict(zip([*terms, "grad_norm"], values.tolist(), strict=True)), "lr": lr}
        run.history.append(record)
        if on_record is not None:
            on_record(record)
        if bar.disable and (run.step % max(1, end // 50) == 0 or run.step == end):  # ~50 lines a run
            log(" ".join(f"{k} {v:.5g}" if isinstance(v, float) else f"{k} {v}" for k, v in record.items()))
        else:
            bar.set_postfix_str(f"{objective} {record[objective]:.4g} lr {lr:.3g}", refresh=False)
            bar.update(1)
        if evaluate is not None and eval_every and run.step % eval_every == 0 and run.step < end:
            evaluate(run.step)
        if checkpoint_every and run.step % checkpoint_every == 0 and run.step < end:
            checkpoint(run.step)
    bar.close()


def final_checkpoint(run: Run, checkpoint: Callable[[int], Path | None]) -> Path | None:
    """The run's last checkpoint: written now if this call trained, else the one it resumed from (a
    finished run asked again does no work)."""
    return checkpoint(run.step) if run.step > run.started else run.resumed_from


def finished_summary(out_dir: Path | str, config: Any) -> dict | None:
    """The summary of the run in ``out_dir`` if it has finished with exactly ``config`` (its latest checkpoint is at
    ``config.steps``, saved with this config, and the summary names it), else None. Such a run asked again trains
    nothing and writes this summary again."""
    out = Path(out_dir)
    ckpt = latest_checkpoint(out)
    if ckpt is None or not (out / SUMMARY).is_file():
        return None
    meta = read_meta(ckpt)
    if meta.get("step") != config.steps or meta.get("train_config") != config.to_json():
        return None
    summary = read_json(out / SUMMARY)
    return summary if isinstance(summary, dict) and summary.get("checkpoint") == str(ckpt) else None


def finish(out_dir: Path | str, summary: dict) -> dict:
    """Write ``summary`` (its ``losses`` left out) to ``<out_dir>/summary.json`` on rank 0, wait for every
    rank, and return it."""
    rank, world = rank_world()
    if rank == 0:
        write_json(Path(out_dir) / SUMMARY, {k: v for k, v in summary.items() if k != "losses"})
    if world > 1:
        dist.barrier()  # nobody returns (and tears the group down) before rank 0 has written
    return summary


# -- launching ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Trainer:
    """A trainer module's entry points, made once from its ``train``, its config class and its first docstring line:
    ``add_arguments`` (its command's arguments), ``run`` (in this process, or ``nproc`` processes under torchrun)
    and ``main`` (its ``python -m``, which torchrun runs once per rank)."""

    module: str
    train: Callable[..., dict]
    config: type
    description: str

    def add_arguments(self, ap: Parser) -> None:
        add_training_arguments(ap, self.config)

    def run(
        self,
        corpus: Path | str,
        out_dir: Path | str,
        config: Any,
        *,
        nproc: int = 1,
        nodes: Nodes = ONE_NODE,
        progress: bool = False,
        log: Callable[[str], Any] = print,
    ) -> dict:
        """``train(corpus, out_dir, config, log, progress=)`` in this process (in torchrun's process group when
        launched by it), or, with ``nproc`` > 1 or several ``nodes`` outside one, ``python -m module`` in ``nproc``
        processes on this node under torchrun, returning the summary rank 0 wrote (losses left out; the ranks print
        their own log; on a node other than 0, the summary rank 0 wrote in the shared OUT)."""
        if (nproc > 1 or nodes.nnodes > 1) and "WORLD_SIZE" not in os.environ:
            done = finished_summary(out_dir, config)
            if done is not None:  # what the processes would write again: none is started
                return done
            return train_under_torchrun(
                self.module, corpus, out_dir, config.to_json(), nproc, SUMMARY, nodes=nodes, progress=progress
            )
        with process_group_from_env():
            return self.train(corpus, out_dir, config, log, progress=progress)

    def main(self, argv: list[str] | None = None) -> dict:
        return main(argv, f"python -m {self.module}", self.description, self.config, self.run)


def main(argv: list[str] | None, prog: str, description: str, cls: type, run: Callable[..., dict]) -> dict:
    """A trainer module's ``python -m`` entry (also what torchrun runs): parse ``add_arguments(cls)``, then
    ``run(corpus, out, config, nproc=, nodes=, progress=)``; prints the summary unless it is one rank of many."""
    ap = Parser(prog=prog, description=description)
    add_training_arguments(ap, cls)
    a = ap.parse_args(argv)
    summary = run(a.corpus, a.out, config_from_args(cls, a), nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    if "WORLD_SIZE" not in os.environ:
        print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return summary
