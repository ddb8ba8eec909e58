"""Training the dynamics model (ActionGPT + PoseGPT) on a corpus's train split, with exact resume and DDP.

One step reads a batch of windows x[0..T] (``WindowSampler``), runs ActionGPT on
``action_training_pair`` and PoseGPT on ``pose_training_pair`` (teacher forcing: PoseGPT reads the
recorded root and tokens of the frame being animated), and minimises

    w_action · CE(next tokens; token 0 "no valid action" ignored)       (pooled over entities)
  + w_root   · MSE(next root stream, normalised)
  + w_body   · MSE(next body state, normalised)
  + w_drift  · mean over windows and entities of (Σ_t Δy_pred − Σ_t Δy_rec)²

where Δy is the world-vertical root displacement of a frame, R[1, :] · δ with δ the denormalised
local displacement ``E.root`` and R the frame's rotation from ``E.rot6d`` (world up = +y); the
prediction uses the predicted δ and rotation, the recording the recorded ones (metres).

  + w_hinge  · mean over known (frame, entity, key joint) of ReLU(H_j + margin − y_j)²

the penetration hinge of DESIGN (``PenetrationHinge``), on PoseGPT's predicted body: y_j is the
predicted height of key contact joint j above the root, R[1, :] · p_j with p_j its root-local position
and R the rotation of the frame being animated (the recorded one, which PoseGPT reads); H_j is the
terrain height under joint j relative to the root, taken from the batch's terrain features as the
recorded joint's height above the root minus its recorded signed clearance (so H_j is the surface under
the *recorded* joint, which a teacher-forced prediction stays within centimetres of). It needs the
terrain features (``TrainConfig.terrain``) and is 0 where the surface is unknown.

Optimisation: AdamW (betas 0.9, 0.95; weight decay on matrices and embeddings only), linear warmup
then cosine decay to ``min_lr_ratio`` of the peak (a ``LambdaLR``), gradient clipping. bf16 autocast
only where the hardware has it (CUDA with bf16), else float32; ``TrainConfig.bf16`` forces either.

Exact resume. The sampler's batches are a function of (seed, rank, world_size, epoch), so step s
(0-based, global) is batch ``s − Σ_{e' < e} batches(e')`` of the epoch e holding it. A checkpoint
holds weights, optimizer, scheduler, torch RNG and the loss history; resuming from
``latest_checkpoint(out_dir)`` continues the same loss sequence bit for bit (same config, same
world size, same device).

DDP: when ``torch.distributed`` is initialised, ActionGPT and PoseGPT are each wrapped in
``DistributedDataParallel``, rank r samples its own windows (``WindowSampler(rank=r)``), the logged
losses are averaged over ranks, and only rank 0 evaluates, logs and writes checkpoints.

Metrics: every step's terms, learning rate and gradient norm, and every evaluation, go to TensorBoard
event files under ``<out>/tensorboard`` (rank 0); the ``train-dynamics`` flow also publishes the final
figures as a Prefect artifact.

Evaluation, on every whole held-out window (split "test"; skipped when the corpus has none): the
model's next-action accuracy over frames whose next token is not 0, and the MSE of its next body state
and next root stream (normalised units), beside three baselines on the same targets: copy the last
action, the most frequent train action (per entity), and copy-last for the body / constant velocity
for the root (the root stream is a per-frame displacement, so copying it is constant velocity).
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable, Iterator
from contextlib import nullcontext
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import Tensor, nn

from marionette import geometry as geo
from marionette.corpus import Corpus
from marionette.distributed import process_group_from_env, rank_world, train_under_torchrun
from marionette.dynamics.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from marionette.dynamics.data import ActionTokens, Batch, HeldOutWindows, Normaliser, WindowData, WindowSampler
from marionette.dynamics.model import (
    PATCH_SIZE,
    PRESETS,
    DynamicsConfig,
    DynamicsModel,
    Frames,
    action_training_pair,
    body_slices,
    parameter_counts,
    pose_training_pair,
)
from marionette.io import check_json_fields, write_json
from marionette.schema import Layout

HELD_OUT_SPLIT = "test"
ROOT_PER_ENTITY = 9  # E.root (3) then E.rot6d (6)
N_PATCH = PATCH_SIZE * PATCH_SIZE  # terrain feature slots before the key joints' clearances
TENSORBOARD = "tensorboard"  # event files under the training directory (rank 0)
SUMMARY = "summary.json"  # the last run's summary (losses left out), written by rank 0
CADENCE_FIELDS = ("eval_every", "checkpoint_every")  # may change between a run and its resume


@dataclass(frozen=True)
class TrainConfig:
    """Every knob of a training run; saved as JSON in each checkpoint's meta."""

    preset: str = "tiny"  # "tiny" | "paper" (model.PRESETS)
    steps: int = 1000
    batch_size: int = 16
    window: int | None = None  # model steps per window; None: the preset's, capped to the train segments
    lr: float = 3e-4
    betas: tuple[float, float] = (0.9, 0.95)
    weight_decay: float = 0.1
    warmup: int = 100
    min_lr_ratio: float = 0.1  # cosine decays to this fraction of lr
    grad_clip: float = 1.0
    seed: int = 0
    terrain: bool = True  # load terrain features: monsters read them (DynamicsConfig.from_layout), the hinge uses them
    relative: bool = False  # the relative-position feature (DESIGN: beyond the paper)
    dropout: float = 0.0  # in both transformers
    # Long rollouts (docs/tradeoffs.md): residual heads trained on clean inputs integrate their errors and
    # leave the data within ~200 frames; absolute heads reading noised inputs stay stable over 10,000.
    residual: bool = False  # heads predict a change added to the current frame (DynamicsConfig.residual)
    input_noise: float = 0.1  # std (normalised units) of Gaussian noise on the models' root and body inputs
    w_action: float = 1.0
    w_root: float = 1.0
    w_body: float = 1.0
    w_drift: float = 0.1
    w_hinge: float = 0.1
    hinge_margin: float = 0.15  # metres, DESIGN's ReLU(H_j + 0.15 − y_j)²
    eval_every: int = 0  # 0: evaluate only at the end
    eval_batch_size: int = 64
    checkpoint_every: int = 0  # 0: checkpoint only at the end
    bf16: bool | None = None  # None: bf16 autocast where the hardware has it
    fps: float = 20.0

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; known: {sorted(PRESETS)}")
        if self.steps < 1 or self.batch_size < 1:
            raise ValueError(f"steps {self.steps} and batch_size {self.batch_size} must be ≥ 1")
        if self.window is not None and self.window < 1:
            raise ValueError(f"window {self.window} must be ≥ 1 step")

    def to_json(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_json(cls, d: dict) -> TrainConfig:
        check_json_fields(cls, d, "train config")
        return cls(**{**d, **({"betas": tuple(d["betas"])} if "betas" in d else {})})


# -- schedule and optimizer --------------------------------------------------------------------------


def _noise_seed(seed: int, step: int, rank: int) -> int:
    """The input-noise generator's seed of one (seed, step, rank): distinct for every triple."""
    return int(np.random.SeedSequence([int(seed), int(step), int(rank)]).generate_state(1, np.uint64)[0] >> 1)


def lr_factor(step: int, config: TrainConfig) -> float:
    """Multiplier of ``config.lr`` at optimizer step ``step`` (0-based): linear warmup, cosine to min_lr_ratio."""
    if step < config.warmup:
        return (step + 1) / config.warmup
    span = max(config.steps - config.warmup, 1)
    progress = min((step - config.warmup) / span, 1.0)
    return config.min_lr_ratio + (1 - config.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def make_optimizer(model: DynamicsModel, config: TrainConfig) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW over both models (decay on ≥ 2-D parameters only) and its warmup + cosine LambdaLR."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [
        {"params": [p for p in params if p.dim() >= 2], "weight_decay": config.weight_decay},
        {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0},
    ]
    opt = torch.optim.AdamW(groups, lr=config.lr, betas=config.betas)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, config))
    return opt, sched


# -- data --------------------------------------------------------------------------------------------


def resolve_window(data: WindowData, config: TrainConfig, world_size: int = 1) -> int:
    """``config.window``, or the preset's window capped so the train split fills an epoch's batches."""
    if config.window is not None:
        return int(config.window)
    longest = int(data.lengths.max()) if len(data.lengths) else 0
    length = min(int(PRESETS[config.preset]["window"]), longest - 1)
    while length >= 1:
        try:
            WindowSampler(data, length, config.batch_size, seed=config.seed, world_size=world_size)
            return length
        except ValueError:
            length = length * 3 // 4 if length > 4 else length - 1
    raise ValueError(f"{data.corpus.path}: the train split is too short for any window at batch_size {config.batch_size}")


def batches_from(sampler: WindowSampler, step: int) -> Iterator[Batch]:
    """The sampler's batches from global step ``step`` on: epoch after epoch, skipping earlier batches."""
    epoch, skip = 0, step
    while True:
        wins = sampler.windows(epoch)
        n = len(wins) // sampler.batch_size
        if skip < n:
            bs = sampler.batch_size
            for k in range(skip * bs, n * bs, bs):
                yield sampler.data.batch(wins[k : k + bs], sampler.frames)
            skip = 0
        else:
            skip -= n
        epoch += 1


def _to(frames: Frames, device: torch.device) -> Frames:
    return Frames(**{f.name: None if (v := getattr(frames, f.name)) is None else v.to(device) for f in fields(frames)})


def most_frequent_actions(data: WindowData) -> tuple[int, ...]:
    """Per entity, the most frequent non-zero token over every frame of ``data`` (0 if it has none)."""
    out = []
    for i in range(len(data.tokens.entities)):
        counts = np.zeros(data.tokens.sizes[i], np.int64)
        for a in data.action:
            counts += np.bincount(a[:, i], minlength=data.tokens.sizes[i])
        counts[0] = 0
        out.append(int(counts.argmax()) if counts.any() else 0)
    return tuple(out)


# -- losses ------------------------------------------------------------------------------------------


def vertical_displacement(root: Tensor, normaliser: Normaliser) -> Tensor:
    """Normalised root stream (..., root_dim) → world-vertical root displacement (..., N) in metres: R[1, :] · δ."""
    raw = normaliser.denormalise_root(root)  # (..., N·9), differentiable
    per = raw.unflatten(-1, (-1, ROOT_PER_ENTITY))  # (..., N, 9)
    R = geo.rot6d_to_matrix(per[..., 3:9])  # (..., N, 3, 3), rotates local into world
    return (R[..., 1, :] * per[..., 0:3]).sum(-1)  # (..., N)


def action_loss(logits: tuple[Tensor, ...], target: Tensor) -> Tensor:
    """Cross-entropy pooled over entities and frames whose next token is not 0 ("no valid action")."""
    total, count = logits[0].new_zeros(()), 0
    for i, lg in enumerate(logits):
        t = target[..., i].reshape(-1)
        total = total + F.cross_entropy(lg.reshape(-1, lg.shape[-1]).float(), t, ignore_index=0, reduction="sum")
        count += int((t != 0).sum())
    return total / max(count, 1)


class PenetrationHinge:
    """DESIGN's penetration hinge on predicted bodies (module doc: the definition of H_j and y_j)."""

    def __init__(self, layout: Layout, normaliser: Normaliser, margin: float) -> None:
        self.normaliser, self.margin = normaliser, float(margin)
        offsets = {name: 0 for name, _ in body_slices(layout)}
        at = 0
        for name, sl in body_slices(layout):
            offsets[name] = at
            at += sl.stop - sl.start
        # per entity: (entity index, body indices of the contact joints' xyz (J, 3), their feature slots)
        self.parts: list[tuple[int, Tensor, Tensor]] = []
        for i, e in enumerate(layout.articulated):
            local = [k - 1 for k in e.rig.contact_index if k > 0]  # keep index 0 is the root itself
            slots = [N_PATCH + j for j, k in enumerate(e.rig.contact_index) if k > 0]
            if local:
                base = offsets[f"{e.name}.joints"]
                idx = torch.tensor([[base + 3 * k + a for a in range(3)] for k in local])
                self.parts.append((i, idx, torch.tensor(slots)))

    def __call__(self, body_pred: Tensor, body_rec: Tensor, root_rec: Tensor, terrain: Tensor, known: Tensor) -> Tensor:
        """Mean hinge over known entries; ``body_*`` (B, T, body_dim) and ``root_rec`` (B, T, root_dim) normalised,
        ``terrain``/``known`` (B, T, N, 132) of the frames being animated."""
        pred = self.normaliser.denormalise_body(body_pred.float())
        rec = self.normaliser.denormalise_body(body_rec.float())
        root = self.normaliser.denormalise_root(root_rec.float())
        total, count = pred.new_zeros(()), 0
        for i, idx, slots in self.parts:
            up = geo.rot6d_to_matrix(root[..., ROOT_PER_ENTITY * i + 3 : ROOT_PER_ENTITY * (i + 1)])[..., 1, :]  # (B, T, 3)
            y_pred = (pred[..., idx] * up[..., None, :]).sum(-1)  # (B, T, J) height above the root
            y_rec = (rec[..., idx] * up[..., None, :]).sum(-1)
            ok = known[:, :, i, slots]
            ground = y_rec - terrain[:, :, i, slots].float()  # H_j relative to the root
            gap = F.relu(ground + self.margin - y_pred) ** 2
            total = total + torch.where(ok, gap, 0.0).sum()
            count += int(ok.sum())
        return total / max(count, 1)


def losses(model: nn.Module, action: nn.Module, pose: nn.Module, batch: Batch, normaliser: Normaliser,
           config: TrainConfig, hinge: PenetrationHinge | None = None,
           noise: torch.Generator | None = None) -> dict[str, Tensor]:  # fmt: skip
    """The weighted terms and their sum for one batch; ``action``/``pose`` may be DDP wrappers.

    With ``config.input_noise`` > 0 and a ``noise`` generator, the models read root and body inputs
    with Gaussian noise added and predict the clean next frame (targets are never noised)."""
    a_in, (root_next, tok_next) = action_training_pair(batch.frames)
    p_in, body_next = pose_training_pair(batch.frames)
    if config.input_noise and noise is not None:
        def jitter(x: Tensor) -> Tensor:
            return x + config.input_noise * torch.randn(x.shape, generator=noise).to(x.device, x.dtype)

        a_in = replace(a_in, root=jitter(a_in.root), body=jitter(a_in.body))
        p_in = replace(p_in, root=jitter(p_in.root), body=jitter(p_in.body))
    out = action(a_in)
    body = pose(p_in)
    terms = {
        "action": action_loss(out.logits, tok_next),
        "root": F.mse_loss(out.root.float(), root_next),
        "body": F.mse_loss(body.float(), body_next),
    }
    if config.w_drift:
        pred = vertical_displacement(out.root.float(), normaliser).sum(1)  # (B, N), metres over the window
        rec = vertical_displacement(root_next, normaliser).sum(1)
        terms["drift"] = ((pred - rec) ** 2).mean()
    if config.w_hinge and hinge is not None and batch.terrain_known is not None:
        nxt = batch.frames.time_slice(1, None)
        terms["hinge"] = hinge(body, body_next, nxt.root, nxt.terrain, batch.terrain_known[:, 1:])
    weights = {"action": config.w_action, "root": config.w_root, "body": config.w_body, "drift": config.w_drift,
               "hinge": config.w_hinge}  # fmt: skip
    terms["total"] = sum(weights[k] * v for k, v in terms.items())
    return terms


# -- evaluation --------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate(model: DynamicsModel, windows: HeldOutWindows, device: torch.device | str = "cpu") -> dict[str, float]:
    """The model's next-action accuracy (frames whose next token ≠ 0) and next body / root MSE (normalised)."""
    was = model.training
    model.eval()
    hits = valid = 0
    body_se = root_se = 0.0
    body_n = root_n = 0
    for batch in windows:
        frames = _to(batch.frames, torch.device(device))
        a_in, (root_next, tok_next) = action_training_pair(frames)
        out = model.action(a_in)
        pred = torch.stack([lg.argmax(-1) for lg in out.logits], dim=-1)  # (B, T, N)
        ok = tok_next != 0
        hits += int(((pred == tok_next) & ok).sum())
        valid += int(ok.sum())
        p_in, body_next = pose_training_pair(frames)
        body = model.pose(p_in)
        body_se += float(((body.float() - body_next) ** 2).sum())
        body_n += body_next.numel()
        root_se += float(((out.root.float() - root_next) ** 2).sum())
        root_n += root_next.numel()
    model.train(was)
    return {
        "action_accuracy": hits / max(valid, 1),
        "body_mse": body_se / max(body_n, 1),
        "root_mse": root_se / max(root_n, 1),
        "windows": len(windows.windows()),
    }


def baselines(windows: HeldOutWindows, most_frequent: tuple[int, ...]) -> dict[str, float]:
    """On the same targets as ``evaluate``: copy-last and most-frequent action accuracy, copy-last body
    MSE and constant-velocity root MSE (normalised units)."""
    copy_hits = freq_hits = valid = 0
    body_se = root_se = 0.0
    body_n = root_n = 0
    mf = torch.tensor(most_frequent)
    for batch in windows:
        f = batch.frames
        now, nxt = f.tokens[:, :-1], f.tokens[:, 1:]
        ok = nxt != 0
        copy_hits += int(((now == nxt) & ok).sum())
        freq_hits += int(((nxt == mf) & ok).sum())
        valid += int(ok.sum())
        body_se += float(((f.body[:, :-1] - f.body[:, 1:]) ** 2).sum())
        body_n += f.body[:, 1:].numel()
        root_se += float(((f.root[:, :-1] - f.root[:, 1:]) ** 2).sum())
        root_n += f.root[:, 1:].numel()
    return {
        "copy_last_action_accuracy": copy_hits / max(valid, 1),
        "most_frequent_action_accuracy": freq_hits / max(valid, 1),
        "copy_last_body_mse": body_se / max(body_n, 1),
        "constant_velocity_root_mse": root_se / max(root_n, 1),
    }


# -- the loop ----------------------------------------------------------------------------------------


def _check_resume(saved: dict, config: TrainConfig, ckpt: Path) -> None:
    mine = {k: v for k, v in config.to_json().items() if k not in CADENCE_FIELDS}
    theirs = {k: v for k, v in saved.items() if k not in CADENCE_FIELDS}
    if mine != theirs:
        diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        raise ValueError(f"{ckpt}: was trained with another config (differs in {diff}); use a fresh out_dir")


def train(corpus_path: Corpus | Path | str, out_dir: Path | str, config: TrainConfig,
          log: Callable[[str], Any] = print, *, stop_at: int | None = None) -> dict:  # fmt: skip
    """Train (or resume from ``latest_checkpoint(out_dir)``) for ``config.steps`` steps; returns a summary.

    ``stop_at`` ends the run after that many steps (checkpointed), as an interruption would; the
    schedule is still the one of ``config.steps``."""
    rank, world = rank_world()
    log = log if rank == 0 else (lambda *_: None)
    out_dir = Path(out_dir)
    corpus = corpus_path if isinstance(corpus_path, Corpus) else Corpus(Path(corpus_path))
    device = torch.device(f"cuda:{torch.cuda.current_device()}" if torch.cuda.is_available() else "cpu")
    use_bf16 = config.bf16 if config.bf16 is not None else (device.type == "cuda" and torch.cuda.is_bf16_supported())
    autocast = torch.autocast(device.type, dtype=torch.bfloat16) if use_bf16 else nullcontext()

    normaliser = Normaliser.from_corpus(corpus)
    tokens = ActionTokens.from_corpus(corpus)
    data = WindowData(corpus, "train", terrain=config.terrain, relative=config.relative, normaliser=normaliser, tokens=tokens,
                      fps=config.fps)  # fmt: skip
    length = resolve_window(data, config, world)
    sampler = WindowSampler(data, length, config.batch_size, seed=config.seed, rank=rank, world_size=world)
    if sampler.skipped:
        log(f"window {length}: {len(sampler.skipped)} train segments shorter than {length + 1} frames skipped")

    held = None
    if rank == 0:
        if corpus.segment_ids(HELD_OUT_SPLIT):
            hdata = WindowData(corpus, HELD_OUT_SPLIT, terrain=config.terrain, relative=config.relative, normaliser=normaliser,
                               tokens=tokens, fps=config.fps)  # fmt: skip
            held = HeldOutWindows(hdata, length, config.eval_batch_size)
            if not held.windows():
                log(f"no {HELD_OUT_SPLIT!r} segment holds a window of {length + 1} frames: evaluation skipped")
                held = None
        else:
            log(f"{corpus.path}: no {HELD_OUT_SPLIT!r} segments: evaluation skipped")

    terrain_switch = {} if config.terrain else {"terrain": (False,) * len(tokens.sizes)}
    dyn = DynamicsConfig.preset(config.preset, corpus.layout, tokens.sizes, window=length, relative_position=config.relative,
                                dropout=config.dropout, residual=config.residual,
                                **terrain_switch)  # fmt: skip
    hinge = PenetrationHinge(corpus.layout, normaliser, config.hinge_margin) if config.terrain and config.w_hinge else None
    model = DynamicsModel(dyn, seed=config.seed).to(device)
    opt, sched = make_optimizer(model, config)
    history: list[dict] = []
    evals: list[dict] = []
    step = 0
    ckpt = latest_checkpoint(out_dir)
    if ckpt is not None:
        meta = load_checkpoint(ckpt, model, opt, sched)
        _check_resume(meta["train_config"], config, ckpt)
        if DynamicsConfig.from_json(meta["dynamics_config"]) != dyn:
            raise ValueError(f"{ckpt}: its dynamics config differs from this run's")
        step, history, evals = int(meta["step"]), list(meta["losses"]), list(meta.get("evals", []))
        log(f"resumed from {ckpt} at step {step}")
    counts = parameter_counts(model)
    log(f"window {length} steps, batch {config.batch_size} × {world} ranks, parameters {counts}, bf16 {use_bf16}")

    action, pose = model.action, model.pose
    if world > 1:
        ids = [device.index] if device.type == "cuda" else None
        action = nn.parallel.DistributedDataParallel(model.action, device_ids=ids)
        pose = nn.parallel.DistributedDataParallel(model.pose, device_ids=ids)

    most_frequent = most_frequent_actions(data)
    base = baselines(held, most_frequent) if held is not None else None
    if base is not None:
        log("baselines " + json.dumps({k: round(v, 4) for k, v in base.items()}))

    def checkpoint(at: int) -> Path | None:
        if rank != 0:
            return None
        meta = {
            "train_config": config.to_json(),
            "dynamics_config": dyn.to_json(),
            "normaliser": normaliser.to_json(),
            "vocab": {"hash": tokens.vocab_hash, "sizes": list(tokens.sizes), "entities": list(tokens.entities)},
            "losses": history,
            "evals": evals,
        }
        return save_checkpoint(out_dir, at, model, opt, sched, meta)

    end = config.steps if stop_at is None else min(stop_at, config.steps)
    board = None
    if rank == 0 and step < end:  # a resumed run drops the events logged after its checkpoint
        from torch.utils.tensorboard import SummaryWriter

        board = SummaryWriter(str(out_dir / TENSORBOARD), purge_step=step + 1 if step else None)

    def run_eval(at: int) -> None:
        if held is None:
            return
        metrics = {"step": at, **evaluate(model, held, device)}
        evals.append(metrics)
        if board is not None:
            for k, v in metrics.items():
                if k not in ("step", "windows"):
                    board.add_scalar(f"eval/{k}", v, at)
        log(f"eval step {at} " + json.dumps({k: round(v, 4) for k, v in metrics.items()}))

    model.train()
    batches = batches_from(sampler, step)
    last_saved = None
    while step < end:
        batch = next(batches)
        frames = _to(batch.frames, device)
        with autocast:
            known = None if batch.terrain_known is None else batch.terrain_known.to(device)
            noise = torch.Generator().manual_seed(_noise_seed(config.seed, step, rank))  # a function of the step: exact resume
            terms = losses(model, action, pose, Batch(frames, known, batch.segments, batch.starts), normaliser, config, hinge, noise)
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        lr = opt.param_groups[0]["lr"]
        opt.step()
        sched.step()
        step += 1
        values = torch.stack([v.detach().float() for v in terms.values()] + [grad_norm.detach().float()])
        if world > 1:
            dist.all_reduce(values)
            values /= world
        record = {"step": step, **dict(zip([*terms, "grad_norm"], values.tolist(), strict=True)), "lr": lr}
        history.append(record)
        if board is not None:
            for k, v in record.items():
                if k != "step":
                    board.add_scalar(f"train/{k}", v, step)
        log(" ".join(f"{k} {v:.5g}" if isinstance(v, float) else f"{k} {v}" for k, v in record.items()))
        if config.eval_every and step % config.eval_every == 0 and step < end:
            run_eval(step)
        if config.checkpoint_every and step % config.checkpoint_every == 0 and step < end:
            last_saved = checkpoint(step)
    if not evals or evals[-1]["step"] != step:
        run_eval(step)
    resumed_done = ckpt is not None and history and step == int(meta["step"])  # nothing trained in this call
    last_saved = ckpt if resumed_done else (checkpoint(step) if rank == 0 else None)
    if board is not None:
        board.close()
    summary = {
        "steps": step,
        "window": length,
        "first": history[0] if history else None,
        "final": history[-1] if history else None,
        "eval": evals[-1] if evals else None,
        "baselines": base,
        "parameters": counts,
        "checkpoint": str(last_saved) if last_saved else None,
        "losses": history,
    }
    if rank == 0:
        write_json(out_dir / SUMMARY, {k: v for k, v in summary.items() if k != "losses"})
    if world > 1:
        dist.barrier()  # nobody returns (and tears the group down) before rank 0 has written
    return summary


# -- CLI ---------------------------------------------------------------------------------------------


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The training command's arguments: one flag per ``TrainConfig`` field (shared by ``marionette train
    dynamics`` and ``python -m marionette.dynamics.train``)."""
    ap.add_argument("corpus", type=Path)
    ap.add_argument("--out", type=Path, required=True, help="training directory (checkpoints; a rerun resumes from it)")
    ap.add_argument("--config", type=Path, help="a TrainConfig JSON; the flags below override it")
    defaults = TrainConfig()
    for f in fields(TrainConfig):
        if f.name == "betas":
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.type in ("bool", bool, "bool | None"):
            ap.add_argument(flag, action=argparse.BooleanOptionalAction, default=None)
        else:
            kind = {"int": int, "float": float, "str": str, "int | None": int}[str(f.type)]
            ap.add_argument(flag, type=kind, default=None, help=f"default {getattr(defaults, f.name)}")
    ap.add_argument("--nproc", type=int, default=1, help="processes: > 1 relaunches this command under torchrun (DDP)")


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The ``TrainConfig`` of parsed arguments: ``--config`` JSON, then the flags that were given."""
    base = {}
    if args.config:
        try:
            base = TrainConfig.from_json(json.loads(args.config.read_text())).to_json()
        except (json.JSONDecodeError, TypeError, ValueError) as exc:
            raise ValueError(f"{args.config}: not a TrainConfig JSON: {exc}") from exc
    over = {f.name: getattr(args, f.name) for f in fields(TrainConfig) if f.name != "betas" and getattr(args, f.name) is not None}
    return TrainConfig.from_json({**base, **over})


def train_in_processes(corpus: Path | str, out_dir: Path | str, config: TrainConfig, nproc: int) -> dict:
    """Train under torchrun with ``nproc`` processes on this machine (gloo on CPU, NCCL on GPU) and return
    the summary rank 0 wrote (losses left out)."""
    return train_under_torchrun("marionette.dynamics.train", corpus, out_dir, config.to_json(), nproc, SUMMARY)


def run(args: argparse.Namespace) -> dict:
    """Run a parsed training command in this process, or, with ``--nproc`` > 1 outside a process group,
    under torchrun (``train_in_processes``)."""
    config = config_from_args(args)
    if args.nproc > 1 and "WORLD_SIZE" not in os.environ:
        summary = train_in_processes(args.corpus, args.out, config, args.nproc)
        print(json.dumps(summary, indent=1))
        return summary
    with process_group_from_env():
        rank = rank_world()[0]
        summary = train(args.corpus, args.out, config)
    if rank == 0:
        print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return summary


def main(argv: list[str] | None = None) -> dict:
    """``python -m marionette.dynamics.train CORPUS --out DIR [--preset tiny] [--steps N] ...``; under
    torchrun (RANK / WORLD_SIZE / MASTER_ADDR in the environment) one process per rank."""
    ap = argparse.ArgumentParser(prog="python -m marionette.dynamics.train", description=__doc__.splitlines()[0])
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    main()
