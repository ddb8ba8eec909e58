"""Training the observation model on a corpus's video shards (RGB beside pose-control chunks), with exact resume.

Data: the train split's chunks (``data.ClipSource.chunks``), decoded once per run and kept in memory
at the model's size (the corpus's chunk size divided by ``reduce``); step s draws its batch of clips
(chunk, start) from ``numpy.random.default_rng([seed, s])``, so a resumed run sees the same batches.
Objective: the rectified-flow loss of ``model.flow_loss`` with noise from a generator seeded by
(seed, s); with probability ``reference_swap`` a clip's given first frame is a random frame of another
train chunk (its targets unchanged), which teaches the model to place bodies by the pose. AdamW, linear warm-up then cosine decay to a tenth, gradient clipping at 1.
Evaluation, on the held-out split ("test", or the train split when there is none): the flow loss of
every held-out chunk's first clip at 8 fixed (s, ε) draws (seed 1234), so successive evaluations
compare like with like. Checkpoints: ``dynamics.checkpoint`` (safetensors + JSON, atomic, ``latest``).

DDP: under torchrun (``train_in_processes``, ``marionette train observation --nproc N``) the network is
wrapped in ``DistributedDataParallel`` (gloo on CPU, NCCL on GPU); rank r draws its clips from
``default_rng([seed, step, r])`` and its noise from (seed, step, r); logged losses are averaged over
ranks; rank 0 evaluates and writes checkpoints and ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from marionette.corpus import Corpus
from marionette.distributed import process_group_from_env, rank_world, train_under_torchrun
from marionette.dynamics.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from marionette.io import check_json_fields, write_json
from marionette.observation.data import Clip, ClipSource
from marionette.observation.model import OBS_PRESETS, ObservationConfig, VideoDiT, flow_loss

HELD_OUT = "test"
EVAL_DRAWS = 8
REFERENCE_SWAP = 0.2  # the default under pose control (docs/tradeoffs.md, "Observation: reference swap ...")


@dataclass(frozen=True)
class ObservationTrainConfig:
    """Every knob of an observation training run; saved in each checkpoint's meta."""

    preset: str = "tiny"
    steps: int = 1000
    batch_size: int = 4
    frames: int | None = None  # clip length (4k + 1); None: the preset's
    reduce: int = 4  # the corpus chunk's size / the model's
    patch: int | None = None  # None: the preset's
    lr: float = 3e-4
    warmup: int = 50
    seed: int = 0
    checkpoint_every: int = 0
    control: str = "pose"  # "pose", or "actions": the pixel-AR baseline (first frame + action schedule)
    # probability that a clip's given first frame is a frame of another chunk; None: 0.2 under pose control, 0 for the
    # baseline (which can learn where bodies are only from its first frame)
    reference_swap: float | None = None

    def __post_init__(self) -> None:
        if self.preset not in OBS_PRESETS:
            raise ValueError(f"unknown observation preset {self.preset!r}; known: {sorted(OBS_PRESETS)}")
        if self.reference_swap is not None and not 0.0 <= self.reference_swap < 1.0:
            raise ValueError(f"reference_swap {self.reference_swap} is not a probability in [0, 1)")
        if self.reference_swap and self.control != "pose":
            raise ValueError("reference_swap needs pose control: the baseline learns where bodies are from its first frame")

    @property
    def swap(self) -> float:
        """The reference-swap probability in effect."""
        if self.reference_swap is not None:
            return self.reference_swap
        return REFERENCE_SWAP if self.control == "pose" else 0.0

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> ObservationTrainConfig:
        check_json_fields(cls, d, "observation train config")
        return cls(**d)


def model_config(corpus: Corpus, config: ObservationTrainConfig) -> ObservationConfig:
    """The preset's network at the corpus's chunk size divided by ``reduce``."""
    video = corpus.info["ingest"]["video"]
    h, w = int(video["height"]), int(video["width"])
    if h % config.reduce or w % config.reduce:
        raise ValueError(f"{corpus.path}: chunks of {h}×{w} do not divide by reduce={config.reduce}")
    base = OBS_PRESETS[config.preset]
    vocab: tuple[int, ...] = ()
    if config.control == "actions":
        from marionette.dynamics.data import ActionTokens

        vocab = ActionTokens.from_corpus(corpus).sizes
    return replace(base, height=h // config.reduce, width_px=w // config.reduce, frames=config.frames or base.frames,
                   patch=config.patch or base.patch, control=config.control, vocab_sizes=vocab)  # fmt: skip


def control_of(clip: Clip, control: str) -> torch.Tensor:
    """The clip's control input: its pose frames, or its action tokens (the baseline)."""
    return clip.pose if control == "pose" else clip.actions


def _lr(step: int, config: ObservationTrainConfig) -> float:
    if step < config.warmup:
        return (step + 1) / config.warmup
    progress = min((step - config.warmup) / max(config.steps - config.warmup, 1), 1.0)
    return 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * progress))


def _batch(chunks: list[Clip], frames: int, size: int, seed: int, step: int, control: str, rank: int = 0,
           swap: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """Step ``step``'s clips, their controls and their given first frames: with probability ``swap``, a clip's
    is a random frame of another chunk (reference swap), else its own frame 0."""
    rng = np.random.default_rng([seed, step] if rank == 0 else [seed, step, rank])
    picks = rng.integers(0, len(chunks), size)
    starts = [int(rng.integers(0, chunks[i].rgb.shape[0] - frames + 1)) for i in picks]
    rgb = torch.stack([chunks[i].rgb[s : s + frames] for i, s in zip(picks, starts)])
    ctrl = torch.stack([control_of(chunks[i], control)[s : s + frames] for i, s in zip(picks, starts)])
    first = rgb[:, 0].clone()
    if swap and len(chunks) > 1:
        for b in np.flatnonzero(rng.random(size) < swap):
            other = chunks[(picks[b] + 1 + rng.integers(0, len(chunks) - 1)) % len(chunks)].rgb
            first[b] = other[rng.integers(0, len(other))]
    return rgb, ctrl, first


@torch.no_grad()
def held_out_loss(model: VideoDiT, chunks: list[Clip]) -> float:
    """Mean flow loss over every held-out chunk's first clip at ``EVAL_DRAWS`` fixed noise draws."""
    model.eval()
    g = torch.Generator().manual_seed(1234)
    T = model.config.frames
    total = 0.0
    for ch in chunks:
        ctrl = control_of(ch, model.config.control)
        for _ in range(EVAL_DRAWS):
            total += float(flow_loss(model, ch.rgb[None, :T], ctrl[None, :T], g))
    model.train()
    return total / max(len(chunks) * EVAL_DRAWS, 1)


def train(corpus_path: Corpus | Path | str, out_dir: Path | str, config: ObservationTrainConfig,
          log: Callable[[str], Any] = print, *, stop_at: int | None = None) -> dict:  # fmt: skip
    """Train (or resume from ``latest_checkpoint(out_dir)``) for ``config.steps`` steps; returns a summary."""
    rank, world = rank_world()
    log = log if rank == 0 else (lambda *_: None)
    out_dir = Path(out_dir)
    config = replace(config, reference_swap=config.swap)  # saved and compared on resume as the probability in effect
    corpus = corpus_path if isinstance(corpus_path, Corpus) else Corpus(Path(corpus_path))
    mc = model_config(corpus, config)
    actions = config.control == "actions"
    src = ClipSource(corpus, "train", mc.frames, mc.size, actions=actions)
    chunks = list(src.chunks())
    if not chunks:
        first = dict(list(src.skipped.items())[:3])
        raise ValueError(f"{corpus.path}: no train chunk with a pose target and ≥ {mc.frames} frames; {len(src.skipped)} skipped, e.g. {first}")
    held_split = HELD_OUT if corpus.segment_ids(HELD_OUT) else "train"
    held = list(ClipSource(corpus, held_split, mc.frames, mc.size, actions=actions).chunks())
    model = VideoDiT(mc, seed=config.seed)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, betas=(0.9, 0.99), weight_decay=0.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: _lr(s, config))
    step, history, evals = 0, [], []
    ckpt = latest_checkpoint(out_dir)
    if ckpt is not None:
        meta = load_checkpoint(ckpt, model, opt, sched)
        if {**meta["train_config"], "checkpoint_every": 0} != {**config.to_json(), "checkpoint_every": 0}:
            raise ValueError(f"{ckpt}: was trained with another config; use a fresh out_dir")
        step, history, evals = int(meta["step"]), list(meta["losses"]), list(meta["evals"])
        log(f"resumed from {ckpt} at step {step}")
    params = sum(p.numel() for p in model.parameters())
    log(f"{len(chunks)} train chunks, {len(held)} held-out ({held_split}); clips {mc.frames}×{mc.height}×{mc.width_px}, "
        f"{mc.tokens} tokens; {params:,} parameters")  # fmt: skip
    if not evals and rank == 0:
        evals.append({"step": 0, "held_out_loss": held_out_loss(model, held)})
    net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model

    def checkpoint(at: int) -> Path | None:
        if rank != 0:
            return None
        meta = {"train_config": config.to_json(), "observation_config": mc.to_json(), "losses": history, "evals": evals,
                "kind": "observation"}  # fmt: skip
        return save_checkpoint(out_dir, at, model, opt, sched, meta)

    end = config.steps if stop_at is None else min(stop_at, config.steps)
    started = step
    model.train()
    while step < end:
        rgb, ctrl, first = _batch(chunks, mc.frames, config.batch_size, config.seed, step, config.control, rank, config.swap)
        noise = torch.Generator().manual_seed(config.seed * 1_000_003 + step if rank == 0 else hash((config.seed, step, rank)) % 2**62)
        loss = flow_loss(net, rgb, ctrl, noise, first)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        step += 1
        value = loss.detach().clone()
        if world > 1:
            dist.all_reduce(value)
            value /= world
        history.append({"step": step, "loss": float(value)})
        if config.checkpoint_every and step % config.checkpoint_every == 0 and step < end:
            checkpoint(step)
    if step > started:
        if rank == 0:
            evals.append({"step": step, "held_out_loss": held_out_loss(model, held)})
        last = checkpoint(step)
    else:
        last = ckpt
    summary = {"steps": step, "evals": evals, "checkpoint": str(last) if last else None, "parameters": params,
               "chunks": len(chunks), "held_out": len(held), "held_out_split": held_split}  # fmt: skip
    if rank == 0:
        log(f"held-out flow loss {evals[0]['held_out_loss']:.4f} at initialisation → {evals[-1]['held_out_loss']:.4f} at step {step}")
        write_json(out_dir / "summary.json", summary)
    if world > 1:
        dist.barrier()  # nobody tears the group down before rank 0 has written
    return {**summary, "losses": history}


def load_model(ckpt_dir: Path | str) -> VideoDiT:
    """A trained observation model from a checkpoint directory or a training directory (its latest)."""
    p = Path(ckpt_dir)
    ckpt = p if (p / "meta.json").exists() else latest_checkpoint(p)
    if ckpt is None:
        raise FileNotFoundError(f"{p}: neither an observation checkpoint nor a training directory with a 'latest' one")
    from marionette.dynamics.checkpoint import read_meta

    meta = read_meta(ckpt)
    if meta.get("kind") != "observation":
        raise ValueError(f"{ckpt}: not an observation-model checkpoint")
    model = VideoDiT(ObservationConfig.from_json(meta["observation_config"]))
    load_checkpoint(ckpt, model, restore_rng=False)
    return model.eval()


def train_in_processes(corpus: Path | str, out_dir: Path | str, config: ObservationTrainConfig, nproc: int) -> dict:
    """Train under ``torchrun --standalone`` with ``nproc`` processes; the summary rank 0 wrote."""
    return train_under_torchrun("marionette.observation.train", corpus, out_dir, config.to_json(), nproc)


def main(argv: list[str] | None = None) -> dict:
    """``python -m marionette.observation.train CORPUS --out DIR --config JSON`` (one process per rank under torchrun)."""
    ap = argparse.ArgumentParser(prog="python -m marionette.observation.train")
    ap.add_argument("corpus", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--config", type=Path, required=True, help="an ObservationTrainConfig JSON")
    a = ap.parse_args(argv)
    config = ObservationTrainConfig.from_json(json.loads(a.config.read_text()))
    with process_group_from_env():
        return train(a.corpus, a.out, config)


if __name__ == "__main__":
    main()
