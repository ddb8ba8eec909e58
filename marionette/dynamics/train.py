"""Training the dynamics model (ActionGPT + PoseGPT) on a corpus's train split, with exact resume and DDP.

One step reads a batch of windows x[0..T] (``WindowSampler``), runs ActionGPT on
``action_training_pair`` and PoseGPT on ``pose_training_pair`` (teacher forcing: PoseGPT reads the
recorded root and tokens of the frame being animated), and minimises

    w_action · CE(next tokens, smoothed; token 0 "no valid action" ignored)  (pooled over entities)
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
(0-based, global) is batch ``s − Σ_{e' < e} batches(e')`` of the epoch e holding it, and its input
noise and dropout are drawn from seeds of (seed, s, rank). A checkpoint holds weights, optimizer,
scheduler, torch RNG and the loss history; resuming from ``latest_checkpoint(out_dir)`` (the step
loop, resume check and checkpoints are ``marionette.training``'s, shared with the observation
trainer) continues the same loss sequence bit for bit (same config, same world size, same device).
``loader_workers`` k > 0 has k DataLoader worker processes stack the batches, handed back in the order
one process stacks them (``dynamics.data``, "Loader workers"): the losses do not depend on k, and a
resumed run may change it.

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

import json
from collections.abc import Callable, Generator
from contextlib import nullcontext
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from marionette import geometry as geo
from marionette import training
from marionette.checkpoint import save_checkpoint
from marionette.corpus import Corpus
from marionette.distributed import rank_world
from marionette.dynamics.config import PATCH_SIZE, PRESETS, ROOT_PER_ENTITY, DynamicsConfig, TrainConfig
from marionette.dynamics.data import ActionTokens, Batch, HeldOutWindows, WindowData, WindowSampler, ended_events, train_batches
from marionette.dynamics.model import DynamicsModel, Frames, action_training_pair, parameter_counts, pose_training_pair
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.state import body_slices
from marionette.schema import Layout

HELD_OUT_SPLIT = "test"
N_PATCH = PATCH_SIZE * PATCH_SIZE  # terrain feature slots before the key joints' clearances
TENSORBOARD = "tensorboard"  # event files under the training directory (rank 0)
SUMMARY = training.SUMMARY
LOADER_FIELDS = ("loader_workers",)  # how batches are stacked, not which: a resumed run may change them


# -- schedule and optimizer --------------------------------------------------------------------------


def make_optimizer(model: DynamicsModel, config: TrainConfig) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW over both models (decay on ≥ 2-D parameters only) and its warmup + cosine LambdaLR."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [
        {"params": [p for p in params if p.dim() >= 2], "weight_decay": config.weight_decay},
        {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0},
    ]
    opt = torch.optim.AdamW(groups, lr=config.lr, betas=config.betas)
    return opt, training.warmup_cosine(opt, config.warmup, config.steps, config.min_lr_ratio)


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


def batches_from(sampler: WindowSampler, step: int, workers: int = 0) -> Generator[Batch, None, None]:
    """The sampler's batches from global step ``step`` on: epoch after epoch, skipping earlier batches; stacked
    by ``workers`` DataLoader workers (0: in this process), the same batches in the same order either way."""
    return train_batches(sampler, step, workers)


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


def action_loss(logits: tuple[Tensor, ...], target: Tensor, smoothing: float = 0.0) -> Tensor:
    """Cross-entropy pooled over entities and frames whose next token is not 0 ("no valid action"), its targets
    smoothed by ``smoothing`` (spread over the tokens the frame allows: a logit of −inf, a played-out event's
    (``ActionGPT.ending``), is a token that cannot follow and gets none)."""
    total, count = logits[0].new_zeros(()), 0
    for i, lg in enumerate(logits):
        t = target[..., i].reshape(-1)
        flat = lg.reshape(-1, lg.shape[-1]).float()
        keep = t != 0
        logp = F.log_softmax(flat[keep], dim=-1)
        nll = -logp.gather(1, t[keep, None])[:, 0]
        if smoothing:
            allowed = torch.isfinite(logp)
            uniform = -torch.where(allowed, logp, 0.0).sum(-1) / allowed.sum(-1)
            nll = (1 - smoothing) * nll + smoothing * uniform
        total = total + nll.sum()
        count += int(keep.sum())
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


def losses(
    model: nn.Module,
    action: nn.Module,
    pose: nn.Module,
    batch: Batch,
    normaliser: Normaliser,
    config: TrainConfig,
    hinge: PenetrationHinge | None = None,
    noise: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """The weighted terms and their sum for one batch; ``action``/``pose`` may be DDP wrappers.

    With a ``noise`` generator, the models read their inputs with Gaussian noise added and predict the clean next
    frame (targets are never noised): std ``config.input_noise`` on the bodies and PoseGPT's roots,
    ``config.root_noise`` on ActionGPT's roots (None: 0 with the displacement gate, which carries them, else
    ``config.input_noise``)."""
    a_in, (root_next, tok_next) = action_training_pair(batch.frames)
    p_in, body_next = pose_training_pair(batch.frames)
    root_std = config.root_noise if config.root_noise is not None else 0.0 if config.displacement_gate else config.input_noise
    if (config.input_noise or root_std) and noise is not None:

        def jitter(x: Tensor, std: float) -> Tensor:
            return x + std * torch.randn(x.shape, generator=noise).to(x.device, x.dtype)

        a_in = replace(a_in, root=jitter(a_in.root, root_std), body=jitter(a_in.body, config.input_noise))
        p_in = replace(p_in, root=jitter(p_in.root, config.input_noise), body=jitter(p_in.body, config.input_noise))
    out = action(a_in)
    body = pose(p_in)
    terms = {
        "action": action_loss(out.logits, tok_next, config.label_smoothing),
        "root": F.mse_loss(out.root.float(), root_next),
        "body": F.mse_loss(body.float(), body_next),
    }
    if out.proposal is not None:  # the displacement gate's head, trained on its own (the blend trains the gate)
        terms["proposal"] = F.mse_loss(out.proposal.float(), root_next)
    if config.w_drift:
        pred = vertical_displacement(out.root.float(), normaliser).sum(1)  # (B, N), metres over the window
        rec = vertical_displacement(root_next, normaliser).sum(1)
        terms["drift"] = ((pred - rec) ** 2).mean()
    if config.w_hinge and hinge is not None and batch.terrain_known is not None:
        nxt = batch.frames.time_slice(1, None)
        terms["hinge"] = hinge(body, body_next, nxt.root, nxt.terrain, batch.terrain_known[:, 1:])
    weights = {
        "action": config.w_action,
        "root": config.w_root,
        "proposal": config.w_root,
        "body": config.w_body,
        "drift": config.w_drift,
        "hinge": config.w_hinge,
    }
    terms["total"] = sum(weights[k] * v for k, v in terms.items())
    return terms


# -- evaluation --------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate(model: DynamicsModel, windows: HeldOutWindows, device: torch.device | str = "cpu") -> dict[str, float]:
    """The model's next-action accuracy (frames whose next token ≠ 0) and next body / root MSE (normalised)."""
    was = model.training
    model.eval()
    hits = valid = changes = called = false_calls = 0
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
        change = ok & (tok_next != a_in.tokens)
        changes += int(change.sum())
        called += int((change & (pred == tok_next)).sum())
        false_calls += int((ok & ~change & (pred != tok_next)).sum())
        p_in, body_next = pose_training_pair(frames)
        body = model.pose(p_in)
        body_se += float(((body.float() - body_next) ** 2).sum())
        body_n += body_next.numel()
        root_se += float(((out.root.float() - root_next) ** 2).sum())
        root_n += root_next.numel()
    model.train(was)
    return {
        "action_accuracy": hits / max(valid, 1),
        # the next action against copy-last, frame by frame: of the frames whose next token differs from the current
        # one, how many the model called; of the frames that keep it, how many it called a change on
        "action_changes": changes,
        "changes_called": called,
        "false_changes": false_calls,
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


def _windows(
    corpus: Corpus, config: TrainConfig, log: Callable[[str], Any]
) -> tuple[WindowData, WindowSampler, HeldOutWindows | None]:
    """This rank's train windows and their sampler, and (rank 0, when a held-out segment holds one) the
    held-out windows."""
    rank, world = rank_world()
    normaliser = Normaliser.from_corpus(corpus)
    tokens = ActionTokens.from_corpus(corpus)
    data = WindowData(
        corpus, "train", terrain=config.terrain, relative=config.relative, normaliser=normaliser, tokens=tokens, fps=config.fps
    )
    length = resolve_window(data, config, world)
    sampler = WindowSampler(data, length, config.batch_size, seed=config.seed, rank=rank, world_size=world)
    if sampler.skipped:
        log(f"window {length}: {len(sampler.skipped)} train segments shorter than {length + 1} frames skipped")
    if rank != 0:
        return data, sampler, None
    if not corpus.segment_ids(HELD_OUT_SPLIT):
        log(f"{corpus.path}: no {HELD_OUT_SPLIT!r} segments: evaluation skipped")
        return data, sampler, None
    hdata = WindowData(
        corpus,
        HELD_OUT_SPLIT,
        terrain=config.terrain,
        relative=config.relative,
        normaliser=normaliser,
        tokens=tokens,
        fps=config.fps,
    )
    held = HeldOutWindows(hdata, length, config.eval_batch_size)
    if not held.windows():
        log(f"no {HELD_OUT_SPLIT!r} segment holds a window of {length + 1} frames: evaluation skipped")
        return data, sampler, None
    return data, sampler, held


def train(
    corpus_path: Corpus | Path | str,
    out_dir: Path | str,
    config: TrainConfig,
    log: Callable[[str], Any] = print,
    *,
    stop_at: int | None = None,
    progress: bool = False,
) -> dict:
    """Train (or resume from the latest checkpoint in ``out_dir``) for ``config.steps`` steps; returns a summary.

    ``stop_at`` ends the run after that many steps (checkpointed), as an interruption would; the
    schedule is still the one of ``config.steps``. ``progress``: a progress bar over the steps (rank 0)."""
    rank, world = rank_world()
    log = training.rank_zero_log(log)
    out_dir = Path(out_dir)
    corpus = corpus_path if isinstance(corpus_path, Corpus) else Corpus(Path(corpus_path), scene=config.scene)
    device, use_bf16, autocast = _device(config)
    data, sampler, held = _windows(corpus, config, log)
    normaliser, length = data.normaliser, sampler.length
    dyn = _dynamics_config(config, corpus, data, length)
    hinge = PenetrationHinge(corpus.layout, normaliser, config.hinge_margin) if config.terrain and config.w_hinge else None
    model = DynamicsModel(dyn, seed=config.seed).to(device)
    opt, sched = make_optimizer(model, config)
    configs = {"train_config": config, "dynamics_config": dyn}
    run = training.resume(out_dir, model, opt, sched, configs, may_change=(*training.CADENCE_FIELDS, *LOADER_FIELDS))
    if run.resumed_from is not None:
        log(f"resumed from {run.resumed_from} at step {run.step}")
    counts = parameter_counts(model)
    log(f"window {length} steps, batch {config.batch_size} × {world} ranks, parameters {counts}, bf16 {use_bf16}")
    action, pose = training.ddp(model.action, device), training.ddp(model.pose, device)
    base = baselines(held, most_frequent_actions(data)) if held is not None else None
    if base is not None:
        log("baselines " + json.dumps({k: round(v, 4) for k, v in base.items()}))

    def checkpoint(at: int) -> Path | None:
        if rank != 0:
            return None
        return save_checkpoint(out_dir, at, model, opt, sched, _checkpoint_meta(config, dyn, data, run))

    end = config.steps if stop_at is None else min(stop_at, config.steps)
    board = _Board(out_dir, run.step, end, rank)

    def run_eval(at: int) -> None:
        if held is None:
            return
        metrics = {"step": at, **evaluate(model, held, device)}
        run.evals.append(metrics)
        board.scalars("eval", metrics, at, skip=("step", "windows"))
        log(f"eval step {at} " + json.dumps({k: round(v, 4) for k, v in metrics.items()}))

    batches = batches_from(sampler, run.step, config.loader_workers)

    def loss_at(step: int) -> dict[str, Tensor]:
        batch = next(batches)
        frames = _to(batch.frames, device)
        with autocast:
            known = None if batch.terrain_known is None else batch.terrain_known.to(device)
            noise = training.noise_generator(config.seed, step, rank)
            return losses(
                model, action, pose, Batch(frames, known, batch.segments, batch.starts), normaliser, config, hinge, noise
            )

    try:
        training.run_steps(
            run,
            end,
            loss_at,
            model,
            opt,
            sched,
            seed=config.seed,
            objective="total",
            grad_clip=config.grad_clip,
            checkpoint=checkpoint,
            checkpoint_every=config.checkpoint_every,
            evaluate=run_eval,
            eval_every=config.eval_every,
            on_record=lambda record: board.scalars("train", record, record["step"], skip=("step",)),
            log=log,
            progress=progress,
            desc="train dynamics",
        )
    finally:
        batches.close()  # the loader's workers stop here (before the evaluation, or on an error)
    if not run.evals or run.evals[-1]["step"] != run.step:
        run_eval(run.step)
    last = training.final_checkpoint(run, checkpoint)
    board.close()
    return training.finish(out_dir, _summary(run, length, base, counts, last))


def _summary(run: training.Run, length: int, base: dict | None, counts: dict, last: Path | None) -> dict:
    """``summary.json``: steps, window, first and final losses, the last evaluation, the baselines, parameter counts,
    the final checkpoint and every logged loss."""
    return {
        "steps": run.step,
        "window": length,
        "first": run.history[0] if run.history else None,
        "final": run.history[-1] if run.history else None,
        "eval": run.evals[-1] if run.evals else None,
        "baselines": base,
        "parameters": counts,
        "checkpoint": str(last) if last else None,
        "losses": run.history,
    }


def _device(config: TrainConfig) -> tuple[torch.device, bool, Any]:
    """This process's device (its CUDA device, else the CPU), whether it trains in bf16 (``config.bf16``, by default
    where CUDA supports it) and the autocast context that does."""
    device = torch.device(f"cuda:{torch.cuda.current_device()}" if torch.cuda.is_available() else "cpu")
    use_bf16 = config.bf16 if config.bf16 is not None else (device.type == "cuda" and torch.cuda.is_bf16_supported())
    return device, use_bf16, torch.autocast(device.type, dtype=torch.bfloat16) if use_bf16 else nullcontext()


def _checkpoint_meta(config: TrainConfig, dyn: DynamicsConfig, data: WindowData, run: training.Run) -> dict:
    """What a checkpoint carries beside the tensors: both configs, the normaliser, the vocabulary it was trained
    with, and the run's losses and evaluations so far."""
    tokens = data.tokens
    return {
        "train_config": config.to_json(),
        "dynamics_config": dyn.to_json(),
        "normaliser": data.normaliser.to_json(),
        "vocab": {"hash": tokens.vocab_hash, "sizes": list(tokens.sizes), "entities": list(tokens.entities)},
        "losses": run.history,
        "evals": run.evals,
    }


def _dynamics_config(config: TrainConfig, corpus: Corpus, data: WindowData, length: int) -> DynamicsConfig:
    """The model's configuration: the preset's sizes for this corpus's layout and vocabularies, the window, and the
    switches of ``config`` (an anchor or gate is off with residual heads)."""
    tokens = data.tokens
    terrain_switch = {} if config.terrain else {"terrain": (False,) * len(tokens.sizes)}
    return DynamicsConfig.preset(
        config.preset,
        corpus.layout,
        tokens.sizes,
        window=length,
        relative_position=config.relative,
        dropout=config.dropout,
        residual=config.residual,
        body_anchor=config.body_anchor and not config.residual,
        rotation_anchor=config.rotation_anchor and not config.residual,
        displacement_gate=config.displacement_gate and not config.residual,
        adaptive_copy=config.adaptive_copy,
        pose_progress=config.pose_progress,
        token_classes=tokens.class_indices(corpus.vocab) if config.token_classes else (),
        clip_frames=tokens.event_lengths(corpus.vocab) if config.time_left else (),
        source_fps=float(corpus.fps),
        model_fps=float(data.fps),
        events_end=ended_events(data, tokens.event_lengths(corpus.vocab), corpus.fps / data.fps) if config.events_end else (),
        **terrain_switch,
    )


class _Board:
    """A run's TensorBoard scalars under ``<out>/tensorboard``, written by rank 0 while steps remain (a resumed run
    drops the events logged after its checkpoint); otherwise nothing is written."""

    def __init__(self, out_dir: Path, start: int, end: int, rank: int) -> None:
        self.writer = None
        if rank == 0 and start < end:
            from torch.utils.tensorboard import SummaryWriter  # tensorboard's writer loads protobuf: only when it writes

            self.writer = SummaryWriter(str(out_dir / TENSORBOARD), purge_step=start + 1 if start else None)

    def scalars(self, prefix: str, record: dict, step: int, skip: tuple[str, ...]) -> None:
        if self.writer is not None:
            for k, v in record.items():
                if k not in skip:
                    self.writer.add_scalar(f"{prefix}/{k}", v, step)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


# -- commands ----------------------------------------------------------------------------------------


TRAINER = training.Trainer("marionette.dynamics.train", train, TrainConfig, __doc__.splitlines()[0])
add_arguments, run, main = TRAINER.add_arguments, TRAINER.run, TRAINER.main  # the command's arguments, run it, its python -m


if __name__ == "__main__":
    main()
