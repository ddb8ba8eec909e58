"""Training the observation model on a corpus's video shards (RGB beside pose-control chunks), with exact resume.

Data: the train split's chunks, indexed from the shards' headers (``data.ClipSource.index``) and decoded
at the model's size (the corpus's chunk size divided by ``reduce``) when a batch first needs them, kept
while they fit in ``cache_mb`` (``data.ChunkStore``: a small corpus is decoded once per run, a large one
streams in bounded memory); step s draws its batch of clips (chunk, start) from
``numpy.random.default_rng([seed, s])``, so a resumed run sees the same batches whatever the cache.
Objective: the rectified-flow loss of ``model.flow_loss`` with noise from a generator seeded by
(seed, s); with probability ``reference_swap`` a clip's given first frame is a random frame of another
train chunk (its targets unchanged), which teaches the model to place bodies by the pose. AdamW, linear
warm-up then cosine decay to a tenth, gradient clipping at 1 (the loop, resume and checkpoints are
``marionette.training``'s, shared with the dynamics trainer).
Evaluation, on the held-out split ("test", or the train split when there is none): the flow loss of
every held-out chunk's first clip at 8 fixed (s, ε) draws (seed 1234), so successive evaluations
compare like with like. Checkpoints: ``marionette.checkpoint`` (safetensors + JSON, atomic, ``latest``).

DDP: under torchrun (``train_in_processes``, ``marionette train observation --nproc N``) the network is
wrapped in ``DistributedDataParallel`` (gloo on CPU, NCCL on GPU); rank r draws its clips from
``default_rng([seed, step, r])`` and its noise from (seed, step, r); logged losses are averaged over
ranks; rank 0 evaluates and writes checkpoints and ``summary.json``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from marionette import training
from marionette.checkpoint import latest_checkpoint, load_checkpoint, read_config, read_meta, save_checkpoint
from marionette.corpus import Corpus
from marionette.distributed import rank_world
from marionette.observation.config import OBS_PRESETS, ObservationConfig, ObservationTrainConfig
from marionette.observation.data import ChunkStore, Clip, ClipSource, jittered_targets
from marionette.observation.model import VideoDiT, flow_loss
from marionette.observation.references import REF_PATCHES, EntityReferences, band_masks, chunk_references, layout_bands

HELD_OUT = "test"
EVAL_DRAWS = 8


def model_config(corpus: Corpus, config: ObservationTrainConfig) -> ObservationConfig:
    """The preset's network at the corpus's chunk size divided by ``reduce``."""
    video = corpus.info.video
    h, w = int(video["height"]), int(video["width"])
    if h % config.reduce or w % config.reduce:
        raise ValueError(f"{corpus.path}: chunks of {h}×{w} do not divide by reduce={config.reduce}")
    base = OBS_PRESETS[config.preset]
    patch = config.patch or base.patch
    bands: tuple[tuple[int, int], ...] = ()
    if config.references:
        bands = layout_bands(corpus.layouts.values())
        if not bands:
            raise ValueError(f"{corpus.path}: no rendered entity (no rig with an id_band) to take references of")
    vocab: tuple[int, ...] = ()
    if config.control == "actions":
        from marionette.corpus.vocab import ActionTokens

        vocab = ActionTokens.from_corpus(corpus).sizes
    return replace(
        base,
        height=h // config.reduce,
        width_px=w // config.reduce,
        frames=config.frames or base.frames,
        patch=patch,
        control=config.control,
        vocab_sizes=vocab,
        reference_bands=bands,
        reference_size=REF_PATCHES * patch if bands else 0,
        reference_paint=bool(bands) and config.reference_paint,
        handoff_noise=config.handoff_noise,
    )


def control_of(clip: Clip, control: str) -> torch.Tensor:
    """The clip's control input: its pose frames, or its action tokens (the baseline)."""
    return clip.pose if control == "pose" else clip.actions


def _noise_seed(seed: int, step: int, rank: int) -> int:
    # The seeds of the flow-matching noise (s, ε) at step s, not training.noise_seed's: the checkpoints written
    # with these resume to an uninterrupted run's weights only while the seeds stay.
    return seed * 1_000_003 + step if rank == 0 else hash((seed, step, rank)) % 2**62


class ChunkReferences:
    """The entity references of each chunk of a store (``references.chunk_references``), found when a chunk is first
    asked for and kept (a few KiB a chunk)."""

    def __init__(self, chunks: Sequence[Clip], config: ObservationConfig) -> None:
        self.chunks, self.config = chunks, config
        self._refs: dict[int, EntityReferences] = {}

    def __call__(self, i: int) -> EntityReferences:
        if i not in self._refs:
            ch, c = self.chunks[i], self.config
            self._refs[i] = chunk_references(ch.rgb, ch.pose, c.reference_bands, c.reference_size)
        return self._refs[i]


def _batch(
    chunks: Sequence[Clip],
    frames: int,
    size: int,
    seed: int,
    step: int,
    control: str,
    rank: int = 0,
    swap: float = 0.0,
    refs_of: ChunkReferences | None = None,
    drift: float = 0.0,
    bands: tuple[tuple[int, int], ...] = (),
    noise: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Step ``step``'s clips, their controls, their given first frames (with probability ``swap`` a random frame
    of another chunk, reference swap, else the clip's own frame 0, whose pixels of each entity of ``bands`` are
    shifted by a colour drawn from N(0, ``drift``²) per channel) and, with ``refs_of``, their entity references
    (each from the clip's own chunk up to the clip's start, as ``references.EntityReferences`` takes it); with
    ``noise``, every given first frame noised by N(0, σ²) with σ ~ U[0, ``noise``] per clip, and those σ (else None)."""
    rng = np.random.default_rng([seed, step] if rank == 0 else [seed, step, rank])
    picks = rng.integers(0, len(chunks), size)
    starts = [int(rng.integers(0, chunks[i].rgb.shape[0] - frames + 1)) for i in picks]
    rgb = torch.stack([chunks[i].rgb[s : s + frames] for i, s in zip(picks, starts)])
    ctrl = torch.stack([control_of(chunks[i], control)[s : s + frames] for i, s in zip(picks, starts)])
    first = rgb[:, 0].clone()
    own = torch.ones(size, dtype=torch.bool)  # the clips whose first frame is their own frame 0
    if swap and len(chunks) > 1:
        for b in np.flatnonzero(rng.random(size) < swap):
            other = chunks[(picks[b] + 1 + rng.integers(0, len(chunks) - 1)) % len(chunks)].rgb
            first[b] = other[rng.integers(0, len(other))]
            own[b] = False
    if drift and bands:
        masks = band_masks(ctrl[:, 0], bands).float()  # (B, E, H, W) of the clips' own frame 0; bands never overlap
        shift = torch.from_numpy(rng.normal(0.0, drift, (size, len(bands), 3))).float()  # (B, E, 3)
        first[own] = (first + torch.einsum("behw,bec->bchw", masks, shift))[own].clamp(-1.0, 1.0)
    refs = torch.stack([refs_of(int(i)).tensor(upto=s) for i, s in zip(picks, starts)]) if refs_of is not None else None
    level = None
    if noise:  # drawn last, so that the clips, swaps and drifts of a run without it stay the same
        level = torch.from_numpy(rng.uniform(0.0, noise, size)).float()
        first = first + level[:, None, None, None] * torch.from_numpy(rng.standard_normal(first.shape)).float()
    return rgb, ctrl, first, refs, level


@torch.no_grad()
def held_out_loss(model: VideoDiT, chunks: Sequence[Clip]) -> float:
    """Mean flow loss over every held-out chunk's first clip at ``EVAL_DRAWS`` fixed noise draws (a model with
    reference slots given what frame 0 shows)."""
    model.eval()
    g = torch.Generator().manual_seed(1234)
    c = model.config
    T = c.frames
    total = 0.0
    for ch in chunks:
        ctrl = control_of(ch, c.control)
        refs = None
        if c.references:
            refs = chunk_references(ch.rgb[:1], ch.pose[:1], c.reference_bands, c.reference_size).tensor()[None]
        for _ in range(EVAL_DRAWS):
            total += float(flow_loss(model, ch.rgb[None, :T], ctrl[None, :T], g, refs=refs))
    model.train()
    return total / max(len(chunks) * EVAL_DRAWS, 1)


def train(
    corpus_path: Corpus | Path | str,
    out_dir: Path | str,
    config: ObservationTrainConfig,
    log: Callable[[str], Any] = print,
    *,
    stop_at: int | None = None,
    progress: bool = False,
) -> dict:
    """Train (or resume from the latest checkpoint in ``out_dir``) for ``config.steps`` steps; returns a summary.

    ``stop_at`` ends the run after that many steps (checkpointed), as an interruption would; ``progress``:
    a progress bar over the steps (rank 0)."""
    rank = rank_world()[0]
    log = training.rank_zero_log(log)
    out_dir = Path(out_dir)
    config = replace(config, reference_swap=config.swap)  # saved and compared on resume as the probability in effect
    corpus = corpus_path if isinstance(corpus_path, Corpus) else Corpus(Path(corpus_path))
    mc = model_config(corpus, config)
    actions = config.control == "actions"
    jitter = jittered_targets(corpus, config.jitter_root_m, config.jitter_joint_deg, config.jitter_time_s, config.seed, log)
    src = ClipSource(corpus, "train", mc.frames, mc.size, actions=actions, jitter=jitter)  # held out: the recorded state's
    chunks = ChunkStore(src, budget_bytes=config.cache_mb << 20)
    if not len(chunks):
        first = dict(list(src.skipped.items())[:3])
        raise ValueError(
            f"{corpus.path}: no train chunk with a pose target and ≥ {mc.frames} frames; {len(src.skipped)} skipped, e.g. {first}"
        )
    held_split = HELD_OUT if corpus.segment_ids(HELD_OUT) else "train"
    held = ChunkStore(ClipSource(corpus, held_split, mc.frames, mc.size, actions=actions), budget_bytes=config.cache_mb << 20)
    model = VideoDiT(mc, seed=config.seed)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, betas=(0.9, 0.99), weight_decay=0.0)
    sched = training.warmup_cosine(opt, config.warmup, config.steps, 0.1)
    run = training.resume(
        out_dir,
        model,
        opt,
        sched,
        {"train_config": config, "observation_config": mc},
        may_change=(*training.CADENCE_FIELDS, "cache_mb"),
    )
    if run.resumed_from is not None:
        log(f"resumed from {run.resumed_from} at step {run.step}")
    params = sum(p.numel() for p in model.parameters())
    log(
        f"{len(chunks)} train chunks, {len(held)} held-out ({held_split}); clips {mc.frames}×{mc.height}×{mc.width_px}, "
        f"{mc.tokens} tokens; {params:,} parameters"
    )
    if not run.evals and rank == 0:
        run.evals.append({"step": 0, "held_out_loss": held_out_loss(model, held)})
    net = training.ddp(model, torch.device("cpu"))
    refs_of = ChunkReferences(chunks, mc) if mc.references else None
    drift_bands = (mc.reference_bands or layout_bands(corpus.layouts.values())) if config.first_frame_drift else ()

    def checkpoint(at: int) -> Path | None:
        if rank != 0:
            return None
        meta = {
            "train_config": config.to_json(),
            "observation_config": mc.to_json(),
            "losses": run.history,
            "evals": run.evals,
            "kind": "observation",
        }
        return save_checkpoint(out_dir, at, model, opt, sched, meta)

    def loss_at(step: int) -> dict[str, torch.Tensor]:
        rgb, ctrl, first, refs, level = _batch(
            chunks,
            mc.frames,
            config.batch_size,
            config.seed,
            step,
            config.control,
            rank,
            config.swap,
            refs_of,
            config.first_frame_drift,
            drift_bands,
            config.handoff_noise,
        )
        noise = torch.Generator().manual_seed(_noise_seed(config.seed, step, rank))
        return {"loss": flow_loss(net, rgb, ctrl, noise, first, refs, level)}

    end = config.steps if stop_at is None else min(stop_at, config.steps)
    training.run_steps(
        run,
        end,
        loss_at,
        model,
        opt,
        sched,
        seed=config.seed,
        objective="loss",
        grad_clip=1.0,
        checkpoint=checkpoint,
        checkpoint_every=config.checkpoint_every,
        log=log,
        progress=progress,
        desc=f"train observation ({config.control})",
    )
    if run.step > run.started and rank == 0:
        run.evals.append({"step": run.step, "held_out_loss": held_out_loss(model, held)})
    last = training.final_checkpoint(run, checkpoint)
    evals = run.evals
    if rank == 0:
        log(
            f"held-out flow loss {evals[0]['held_out_loss']:.4f} at initialisation → {evals[-1]['held_out_loss']:.4f} at step {run.step}"
        )
    summary = {
        "steps": run.step,
        "evals": evals,
        "checkpoint": str(last) if last else None,
        "parameters": params,
        "chunks": len(chunks),
        "held_out": len(held),
        "held_out_split": held_split,
        "losses": run.history,
    }
    return training.finish(out_dir, summary)


def load_model(ckpt_dir: Path | str) -> VideoDiT:
    """A trained observation model from a checkpoint directory or a training directory (its latest)."""
    p = Path(ckpt_dir)
    ckpt = p if (p / "meta.json").exists() else latest_checkpoint(p)
    if ckpt is None:
        raise FileNotFoundError(f"{p}: neither an observation checkpoint nor a training directory with a 'latest' one")

    meta = read_meta(ckpt)
    if meta.get("kind") != "observation":
        raise ValueError(f"{ckpt}: not an observation-model checkpoint")
    model = VideoDiT(read_config(ckpt, meta, "observation_config", ObservationConfig))
    load_checkpoint(ckpt, model, restore_rng=False)
    return model.eval()


TRAINER = training.Trainer("marionette.observation.train", train, ObservationTrainConfig, __doc__.splitlines()[0])
add_arguments, run, main = TRAINER.add_arguments, TRAINER.run, TRAINER.main  # the command's arguments, run it, its python -m


if __name__ == "__main__":
    main()
