"""Fine-tuning Wan2.2-Fun-Control on a corpus's pose-control chunks (``marionette train wan``).

Data: the train split's chunks at the backbone's size (the corpus's chunk size divided by ``reduce``, then
centre-cropped to whole latent patches: the VAE's 16× reduction times the transformer's 2× patch), cut into
windows of T = ``frames`` (4k + 1) frames that start where a relay would start a chunk (every T − 1 frames).
A window's three latents — its RGB, its pose video read as RGB in [−1, 1], and the masked video (its first
frame, then zeros) — are what the transformer sees, exactly as ``WanFunControl.sample_chunk`` builds them.

**The latent cache.** Encoding is the expensive, fixed part, so each window is encoded once by the VAE into
``<corpus>/derived/wan-latents/<vae>-<T>x<H>x<W>/<window>.safetensors`` (bf16; ``vae`` the sha256 of the VAE's
config and weights, ``window`` the sha256 of the window's decoded RGB and pose bytes), written atomically, and a
later run (or another rank) reads it instead of encoding: a second run encodes nothing.

**The objective** is Wan's flow matching: σ drawn uniformly and warped by the timestep shift
(shift·σ / (1 + (shift − 1)·σ)), x_σ = (1 − σ)·x₀ + σ·ε, the network predicting ε − x₀ under mean squared error;
latent frame 0 is the given first frame (x₀ there, its tokens at timestep 0, left out of the loss), as sampling
holds it. The text context is the adapter's fixed embedding (zeros: every prompt token padding).

**What trains**: every transformer weight (``lora_rank`` 0), or LoRA adapters (peft) of rank ``lora_rank`` on the
attention projections and the feed-forward layers, the backbone frozen. AdamW, warm-up then cosine decay to a
tenth, gradient clipping at 1; bf16 autocast and gradient checkpointing on request. The loop, exact resume and
the checkpoints (the trainable weights only, safetensors, with the optimizer) are ``marionette.training``'s;
the finished run writes ``<out>/model/``: the transformer with any LoRA merged, in the release's layout, and
the VAE, which ``WanFunControl.from_pretrained`` and ``marionette generate`` load.

**References** (``references``): each window also gets a reference sheet — each entity's crop from its chunk's
frames up to the window's start, as a relay takes it (``observation.references``), tiled on a grey image —
encoded once into the same cache (a directory of its own, the sheet in the window's digest), and the transformer
reads its tokens through the release's ``ref_conv`` (``wan.forward_with_reference``), which trains with it. The
exported model's settings list the reference bands, and ``marionette generate`` relays with a sheet of first looks.

**Several processes** (``--nproc``, ``--nnodes``): each rank trains on its own windows; by default every rank
holds the whole model and DDP averages the gradients. With ``fsdp`` the model is sharded instead (FSDP2,
``training.fsdp``): each transformer block is a unit whose weights are gathered for its forward and backward, the
rest (embeddings, head, ``ref_conv``) the root unit, and every rank holds only its shard of the weights, gradients
and AdamW state. A forward is then collective, so every rank computes the held-out loss. The checkpoints are the
same whole-tensor files either way (``checkpoint.full_state`` gathers the shards, rank 0 writes; each rank keeps its
shard on resume), and ``<out>/model/`` is built on rank 0 from the backbone and the final checkpoint.
``device`` cuda trains on each process's GPU (``LOCAL_RANK``); the latent cache is encoded on the CPU either way.
Under torchrun the process group routes CUDA tensors through NCCL and CPU tensors through gloo
(``distributed.process_group_from_env``), so either device trains in several processes on a GPU machine.
"""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import save_file
from torch import Tensor, nn

from marionette import training
from marionette.checkpoint import full_state, load_checkpoint, write_checkpoint
from marionette.chunks import relay_starts
from marionette.corpus import Corpus, paths
from marionette.distributed import rank_world
from marionette.io import atomic_dir, atomic_path, file_sha256, read_tensors, write_json
from marionette.observation.config import WanTrainConfig
from marionette.observation.data import Clip, ClipSource, jittered_targets
from marionette.observation.generate import WAN_SETTINGS
from marionette.observation.references import chunk_references, layout_bands, reference_sheet
from marionette.observation.wan import WanFunControl, find_vae, forward_with_reference, ref_tokens, save_original

CACHE_DIR = "wan-latents"  # under the corpus's derived products
LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "ffn.net.0.proj", "ffn.net.2")
EVAL_DRAWS = 4
HELD_OUT = "test"


def vae_key(vae_dir: Path) -> str:
    """The sha256 (16 hex) of a VAE directory's config and weights: what cached latents were encoded with."""
    h = hashlib.sha256()
    for p in sorted(Path(vae_dir).iterdir()):
        if p.name == "config.json" or p.suffix == ".safetensors":
            h.update(p.name.encode() + b"\0" + file_sha256(p).encode())
    return h.hexdigest()[:16]


def crop_box(size: tuple[int, int], multiple: int) -> tuple[int, int, int, int]:
    """(top, left, height, width) of the centred crop of ``size`` to whole multiples of ``multiple``."""
    H, W = size
    h, w = H // multiple * multiple, W // multiple * multiple
    if not h or not w:
        raise ValueError(f"{H}×{W}: smaller than one latent patch ({multiple}×{multiple}); use a smaller reduce")
    return (H - h) // 2, (W - w) // 2, h, w


def windows(clip: Clip, frames: int, box: tuple[int, int, int, int]) -> list[tuple[Tensor, Tensor]]:
    """The relay-aligned windows of a chunk: (RGB, pose) of frames k(T − 1) … k(T − 1) + T − 1, cropped to ``box``."""
    top, left, h, w = box
    rgb, pose = clip.rgb[:, :, top : top + h, left : left + w], clip.pose[:, :, top : top + h, left : left + w]
    return [(rgb[s : s + frames], pose[s : s + frames]) for s in relay_starts(len(rgb), frames)]


def window_sheets(clip: Clip, frames: int, box: tuple[int, int, int, int], bands: Sequence[tuple[int, int]]) -> list[Tensor]:
    """Per window of ``windows``, its reference sheet (3, h, w): each entity's crop from the chunk's frames up to the
    window's start (``observation.references``; what a relay has taken by then)."""
    top, left, h, w = box
    rgb, pose = clip.rgb[:, :, top : top + h, left : left + w], clip.pose[:, :, top : top + h, left : left + w]
    seen = chunk_references(rgb, pose, bands, min(h, w // len(bands)))
    return [reference_sheet(seen.tensor(upto=s), h, w) for s in relay_starts(len(rgb), frames)]


def window_digest(rgb: Tensor, pose: Tensor, sheet: Tensor | None = None) -> str:
    h = hashlib.sha256(np.ascontiguousarray(rgb.numpy()).tobytes())
    h.update(np.ascontiguousarray(pose.numpy()).tobytes())
    if sheet is not None:
        h.update(np.ascontiguousarray(sheet.numpy()).tobytes())
    return h.hexdigest()[:24]


class LatentCache:
    """Encoded windows under ``<corpus>/derived/wan-latents/<vae>-<T>x<H>x<W>/`` (module docstring); counts what this
    process ``encoded`` and what it found already there (``reused``)."""

    def __init__(self, corpus: Path, key: str, frames: int, size: tuple[int, int], references: bool = False) -> None:
        self.dir = paths.derived(corpus, CACHE_DIR) / f"{key}-{frames}x{size[0]}x{size[1]}{'-refs' if references else ''}"
        self.encoded = self.reused = 0

    def path(self, rgb: Tensor, pose: Tensor, sheet: Tensor | None = None) -> Path:
        return self.dir / f"{window_digest(rgb, pose, sheet)}.safetensors"

    def ensure(self, path: Path, rgb: Tensor, pose: Tensor, model: WanFunControl, sheet: Tensor | None = None) -> None:
        """Encode the window into ``path`` unless it is there: its RGB, its pose video read as RGB in [−1, 1], and the
        masked video (the first frame, then zeros), each (z, F, h, w), and its reference sheet (z, 1, h, w) when
        given, stored in bf16."""
        if path.is_file():
            self.reused += 1
            return
        with torch.no_grad():
            masked = torch.zeros_like(rgb)
            masked[0] = rgb[0]
            out = {"x0": model.encode(rgb)[0], "control": model.encode(pose * 2.0 - 1.0)[0], "masked": model.encode(masked)[0]}
            if sheet is not None:
                out["ref"] = model.encode(sheet[None])[0]
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            save_file({k: v.to(torch.bfloat16).contiguous().cpu() for k, v in out.items()}, str(tmp))
        self.encoded += 1


def read_latents(path: Path) -> dict[str, Tensor]:
    """A cached window's {"x0", "control", "masked"[, "ref"]} in float32."""
    return {k: v.float() for k, v in read_tensors(path).items()}


def summed(values: list[float], device: torch.device | None = None) -> list[float]:
    """``values`` summed over the ranks of the process group (as they are in one process); ``device``: where the
    group's backend sums (a GPU under NCCL)."""
    if rank_world()[1] == 1:
        return values
    t = torch.tensor(values, dtype=torch.float64, device=device)
    torch.distributed.all_reduce(t)
    return t.tolist()


def input_box(corpus: Corpus, config: WanTrainConfig, model: WanFunControl) -> tuple[tuple[int, int], tuple[int, int, int, int]]:
    """The chunks' size at ``reduce`` and the crop of it the backbone takes (whole latent patches)."""
    video = corpus.info.video
    H, W = int(video["height"]), int(video["width"])
    if H % config.reduce or W % config.reduce:
        raise ValueError(f"{corpus.path}: chunks of {H}×{W} do not divide by reduce={config.reduce}")
    size = (H // config.reduce, W // config.reduce)
    _, ph, pw = model.transformer.config.patch_size
    return size, crop_box(size, model.spatial * max(ph, pw))


def cache_split(
    corpus: Corpus,
    split: str,
    config: WanTrainConfig,
    model: WanFunControl,
    cache: LatentCache,
    jitter: str | None = None,
    bands: Sequence[tuple[int, int]] = (),
) -> list[Path]:
    """The cache files of every window of the split's chunks (the first ``max_chunks``): rank r of w encodes the
    windows k ≡ r (mod w) that are missing, then every rank waits for the others, so the encoding fans out over
    the ranks and each reads all of them after. With ``bands``, each window carries its reference sheet."""
    rank, world = rank_world()
    size, box = input_box(corpus, config, model)
    paths: list[Path] = []
    for k, clip in enumerate(ClipSource(corpus, split, config.frames, size, jitter=jitter).chunks()):
        if config.max_chunks and k >= config.max_chunks:
            break
        wins = windows(clip, config.frames, box)
        sheets = window_sheets(clip, config.frames, box, bands) if bands else [None] * len(wins)
        for (rgb, pose), sheet in zip(wins, sheets):
            path = cache.path(rgb, pose, sheet)
            if len(paths) % world == rank:
                cache.ensure(path, rgb, pose, model, sheet)
            paths.append(path)
    if world > 1:
        torch.distributed.barrier()
    return paths


class Windows(Sequence):
    """Cached windows read from disk when a batch asks for them (memory stays one batch's, at any corpus size)."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return read_latents(self.paths[i])


def flow_batch(
    latents: Sequence[dict[str, Tensor]], picks: Sequence[int], generator: torch.Generator, shift: float, temporal: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """The transformer's input (B, 148, F, h, w), its per-frame σ (B, F) (0 on frame 0), the target ε − x₀, x₀ and
    the reference sheets' latents (B, z, 1, h, w) (None without)."""
    items = [latents[i] for i in picks]  # each read once
    x0 = torch.stack([lat["x0"] for lat in items])
    cond_parts = []
    for lat in items:
        mask = torch.zeros(temporal, *lat["x0"].shape[1:])
        mask[:, 0] = 1.0
        cond_parts.append(torch.cat([lat["control"], mask, lat["masked"]]))
    cond = torch.stack(cond_parts)
    u = torch.rand(len(picks), generator=generator)
    sigma = shift * u / (1 + (shift - 1) * u)
    eps = torch.randn(x0.shape, generator=generator)
    s = sigma.view(-1, 1, 1, 1, 1)
    x = (1 - s) * x0 + s * eps
    x[:, :, :1] = x0[:, :, :1]
    per_frame = sigma[:, None].expand(-1, x0.shape[2]).clone()
    per_frame[:, 0] = 0.0
    refs = torch.stack([lat["ref"] for lat in items]) if "ref" in items[0] else None
    return torch.cat([x, cond], dim=1), per_frame, eps - x0, x0, refs


def flow_loss(
    transformer: nn.Module,
    patch: Sequence[int],
    context: Tensor,
    inp: Tensor,
    per_frame: Tensor,
    target: Tensor,
    bf16: bool,
    refs: Tensor | None = None,
) -> Tensor:
    """Mean squared error of the predicted velocity on every latent frame but the given one (``patch``: the
    transformer's (t, h, w) patch size; each token's timestep is its latent frame's σ). With reference latents
    ``refs``, ``transformer`` is a ``Referenced`` one. The batch moves to the device of ``context`` (the model's)."""
    inp, per_frame, target = (t.to(context.device) for t in (inp, per_frame, target))
    pt, ph, pw = patch
    B, _, F, h, w = inp.shape
    per_token = per_frame[:, ::pt, None].expand(B, F // pt, (h // ph) * (w // pw)).reshape(B, -1)
    with torch.autocast(inp.device.type, dtype=torch.bfloat16, enabled=bf16):
        if refs is None:
            v = transformer(inp, timestep=1000.0 * per_token, encoder_hidden_states=context.expand(B, -1, -1), return_dict=False)[
                0
            ]
        else:
            v = transformer(inp, 1000.0 * per_token, context.expand(B, -1, -1), refs.to(context.device))
    return ((v.float() - target) ** 2)[:, :, 1:].mean()


class Referenced(nn.Module):
    """The transformer (plain or LoRA-wrapped) and the release's ``ref_conv`` as one module whose forward takes the
    reference sheets' latents: what DDP wraps and a checkpoint holds when a run trains with references."""

    def __init__(self, transformer: nn.Module, ref_conv: nn.Conv2d) -> None:
        super().__init__()
        self.transformer, self.ref_conv = transformer, ref_conv
        object.__setattr__(self, "_base", diffusers_transformer(transformer))  # the same modules, not registered twice

    def forward(self, inp: Tensor, timestep: Tensor, context: Tensor, refs: Tensor) -> Tensor:
        return forward_with_reference(self._base, inp, timestep, context, ref_tokens(self.ref_conv, refs))


def diffusers_transformer(module: nn.Module) -> nn.Module:
    """The ``WanTransformer3DModel`` of a module that trains: itself, inside peft's LoRA wrapper, or a ``Referenced``'s."""
    if isinstance(module, Referenced):
        module = module.transformer
    return module.base_model.model if hasattr(module, "base_model") else module  # LoRA sits inside


class Trainable(nn.Module):
    """The trainable parameters of the transformer as one module of their own (shared, not copied), so that a
    checkpoint holds them and nothing of the frozen backbone."""

    def __init__(self, transformer: nn.Module) -> None:
        super().__init__()
        self.names = [n for n, p in transformer.named_parameters() if p.requires_grad]
        self.params = nn.ParameterList([p for p in transformer.parameters() if p.requires_grad])


def add_lora(transformer: nn.Module, rank: int, alpha: float, seed: int) -> nn.Module:
    """``transformer`` with LoRA adapters (peft) on ``LORA_TARGETS``, everything else frozen."""
    from peft import LoraConfig, get_peft_model

    torch.manual_seed(seed)
    return get_peft_model(transformer, LoraConfig(r=rank, lora_alpha=alpha, target_modules=list(LORA_TARGETS)))


def trainable_transformer(model: WanFunControl, config: WanTrainConfig, device: torch.device) -> nn.Module:
    """What trains, in float32 on ``device``: the transformer (every weight, or LoRA adapters at ``lora_rank`` and the
    rest frozen; gradient checkpointing on request), and under ``references`` the release's ``ref_conv`` with it
    (``Referenced``)."""
    transformer = model.transformer.float().requires_grad_(True)
    if config.lora_rank:
        transformer.requires_grad_(False)
        transformer = add_lora(transformer, config.lora_rank, config.alpha, config.seed)
    if config.gradient_checkpointing:
        diffusers_transformer(transformer).enable_gradient_checkpointing()
    transformer.train()
    if config.references:  # the reference path trains with the rest (and is all that sees the sheets)
        transformer = Referenced(transformer, model.ref_conv.float().requires_grad_(True))
    return transformer.to(device)


@torch.no_grad()
def held_out_loss(
    transformer: nn.Module,
    patch: Sequence[int],
    context: Tensor,
    latents: Sequence[dict[str, Tensor]],
    config: WanTrainConfig,
    temporal: int,
) -> float:
    """Mean flow loss of every held-out window at ``EVAL_DRAWS`` fixed (σ, ε) draws (seed 1234)."""
    transformer.eval()
    g = torch.Generator().manual_seed(1234)
    total = 0.0
    for i in range(len(latents)):
        for _ in range(EVAL_DRAWS):
            inp, per_frame, target, _, refs = flow_batch(latents, [i], g, config.shift, temporal)
            total += float(flow_loss(transformer, patch, context, inp, per_frame, target, config.bf16, refs))
    transformer.train()
    return total / max(len(latents) * EVAL_DRAWS, 1)


def export_model(
    transformer: nn.Module, backbone: Path, out: Path, text_len: int, ref_conv: nn.Module | None, settings: dict
) -> Path:
    """Write ``out`` as a loadable checkpoint: the transformer (LoRA merged) in the release's layout, the VAE, and
    the chunk length and shift it was trained with (``generate.WAN_SETTINGS``)."""
    base = transformer.merge_and_unload() if hasattr(transformer, "merge_and_unload") else transformer
    with atomic_dir(out) as tmp:
        save_original(tmp, base, text_len=text_len, ref_conv=ref_conv)
        shutil.copytree(find_vae(Path(backbone)), tmp / "vae")
        write_json(tmp / WAN_SETTINGS, settings)
    return out


def trained_model(
    transformer: nn.Module, model: WanFunControl, config: WanTrainConfig, last: Path | None, sharded: bool
) -> tuple[nn.Module, nn.Module | None]:
    """The trained transformer (LoRA-wrapped or not) and ``ref_conv``, whole in this process, for ``export_model``.
    Sharded (FSDP), the weights are rebuilt from the backbone on the CPU with the final checkpoint ``last`` loaded
    into them: it holds every trained weight whole, and the frozen ones are the backbone's."""
    if sharded:
        if last is None:
            raise ValueError("an FSDP run exports its model from its final checkpoint, and there is none")
        backbone = WanFunControl.from_pretrained(Path(config.backbone), frames=config.frames, shift=config.shift)
        transformer = trainable_transformer(backbone, config, torch.device("cpu"))
        load_checkpoint(last, Trainable(transformer), restore_rng=False)
    if isinstance(transformer, Referenced):
        return transformer.transformer, transformer.ref_conv
    return transformer, model.ref_conv


def train(
    corpus_path: Corpus | Path | str,
    out_dir: Path | str,
    config: WanTrainConfig,
    log: Callable[[str], Any] = print,
    *,
    stop_at: int | None = None,
    progress: bool = False,
) -> dict:
    """Fine-tune (or resume from the latest checkpoint in ``out_dir``) for ``config.steps`` steps; returns a summary
    (``encoded`` / ``reused``: the windows the latent cache encoded and read). ``stop_at`` ends the run early
    (checkpointed), as an interruption would."""
    rank, world = rank_world()
    sharded = config.fsdp and world > 1  # each rank holds a shard of the weights: every forward is collective
    device = torch.device("cuda", torch.cuda.current_device()) if config.device == "cuda" else torch.device("cpu")
    log = training.rank_zero_log(log)
    out_dir = Path(out_dir)
    corpus = corpus_path if isinstance(corpus_path, Corpus) else Corpus(Path(corpus_path))
    backbone = Path(config.backbone)
    model = WanFunControl.from_pretrained(backbone, frames=config.frames, shift=config.shift)
    bands: tuple[tuple[int, int], ...] = ()
    if config.references:
        if model.ref_conv is None:
            raise ValueError(f"{backbone}: --references trains the release's reference path, and this checkpoint has no ref_conv")
        bands = layout_bands(corpus.layouts.values())
    box = input_box(corpus, config, model)[1]
    cache = LatentCache(corpus.path, vae_key(find_vae(backbone)), config.frames, box[2:], config.references)
    jitter = jittered_targets(corpus, config.jitter_root_m, config.jitter_joint_deg, config.jitter_time_s, config.seed, log)
    latents = Windows(cache_split(corpus, "train", config, model, cache, jitter, bands))  # held out: the recorded state's
    held_split = HELD_OUT if corpus.segment_ids(HELD_OUT) else "train"
    held = Windows(cache_split(corpus, held_split, config, model, cache, bands=bands))
    if not len(latents):
        raise ValueError(f"{corpus.path}: no train window of {config.frames} frames with a pose target")
    encoded, reused = (int(v) for v in summed([cache.encoded, cache.reused], device))
    log(f"latent cache {cache.dir}: {encoded} windows encoded, {reused} already there")
    transformer = trainable_transformer(model, config, device)
    if sharded:  # before the optimizer, which then holds the shards
        training.fsdp(transformer, diffusers_transformer(transformer).blocks, device)
    trainable = Trainable(transformer)
    opt = torch.optim.AdamW(trainable.parameters(), lr=config.lr, betas=(0.9, 0.99), weight_decay=0.0)
    sched = training.warmup_cosine(opt, config.warmup, config.steps, 0.1)
    # the checkpoint's tensors are whole whatever the sharding: a run may resume with or without FSDP
    run = training.resume(out_dir, trainable, opt, sched, {"train_config": config}, may_change=(*training.CADENCE_FIELDS, "fsdp"))
    if run.resumed_from is not None:
        log(f"resumed from {run.resumed_from} at step {run.step}")
    n_train = sum(p.numel() for p in trainable.parameters())
    log(f"{len(latents)} train windows, {len(held)} held-out ({held_split}); {n_train:,} trainable parameters")
    context, patch = model.context.float().to(device), tuple(model.transformer.config.patch_size)
    evaluates = rank == 0 or sharded  # rank 0 alone, unless the forward is collective

    def evaluate(step: int) -> None:
        loss = held_out_loss(transformer, patch, context, held, config, model.temporal)
        run.evals.append({"step": step, "held_out_loss": loss})

    if not run.evals and evaluates:
        evaluate(0)
    net = transformer if sharded else training.ddp(transformer, device)

    def checkpoint(at: int) -> Path | None:
        if rank != 0 and not sharded:
            return None
        weights, optimizer_state = full_state(trainable, opt, keep=rank == 0)  # sharded: every rank gathers
        if rank != 0:
            return None
        meta = {
            "train_config": config.to_json(),
            "losses": run.history,
            "evals": run.evals,
            "kind": "wan",
            "names": trainable.names,
        }
        return write_checkpoint(out_dir, at, weights, optimizer_state, sched, meta)

    def loss_at(step: int) -> dict[str, Tensor]:
        rng = np.random.default_rng([config.seed, step] if rank == 0 else [config.seed, step, rank])
        picks = rng.integers(0, len(latents), config.batch_size).tolist()
        g = training.noise_generator(config.seed, step, rank)
        inp, per_frame, target, _, refs = flow_batch(latents, picks, g, config.shift, model.temporal)
        return {"loss": flow_loss(net, patch, context, inp, per_frame, target, config.bf16, refs)}

    end = config.steps if stop_at is None else min(stop_at, config.steps)
    training.run_steps(
        run,
        end,
        loss_at,
        trainable,
        opt,
        sched,
        seed=config.seed,
        objective="loss",
        grad_clip=1.0,
        checkpoint=checkpoint,
        checkpoint_every=config.checkpoint_every,
        log=log,
        progress=progress,
        desc="train wan" + (f" (LoRA rank {config.lora_rank})" if config.lora_rank else ""),
    )
    if run.step > run.started and evaluates:
        evaluate(run.step)
    last = training.final_checkpoint(run, checkpoint)
    exported = None
    if rank == 0 and run.step >= config.steps:
        settings = {"frames": config.frames, "shift": config.shift}
        if bands:
            settings["reference_bands"] = [list(b) for b in bands]
        plain, ref_conv = trained_model(transformer, model, config, last, sharded)
        exported = export_model(plain, backbone, out_dir / "model", model.context.shape[1], ref_conv, settings)
        log(f"wrote {exported}: `marionette generate {exported} --pose ... --first-frame ...` paints with it")
    evals = run.evals
    if rank == 0:
        log(
            f"held-out flow loss {evals[0]['held_out_loss']:.4f} at the backbone → {evals[-1]['held_out_loss']:.4f} at step {run.step}"
        )
    summary = {
        "steps": run.step,
        "evals": evals,
        "checkpoint": str(last) if last else None,
        "model": str(exported) if exported else None,
        "trainable_parameters": n_train,
        "windows": len(latents),
        "held_out": len(held),
        "held_out_split": held_split,
        "encoded": encoded,
        "reused": reused,
        "losses": run.history,
    }
    return training.finish(out_dir, summary)


TRAINER = training.Trainer("marionette.observation.wan_train", train, WanTrainConfig, __doc__.splitlines()[0])
add_arguments, run, main = TRAINER.add_arguments, TRAINER.run, TRAINER.main  # the command's arguments, run it, its python -m


if __name__ == "__main__":
    main()
