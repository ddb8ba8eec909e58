"""Wan2.2-Fun-5B-Control as an observation model: a local checkpoint directory → ``WanFunControl.generate``.

Loading (local paths only; nothing here calls the Hugging Face hub, and every tensor is read through
safetensors, never unpickled):

- the transformer, either as released (``config.json`` in the original Wan / VideoX-Fun keys and
  ``diffusion_pytorch_model.safetensors`` in the original Wan parameter names, renamed by ``WAN_TO_DIFFUSERS``)
  or in diffusers format (``transformer/``), into diffusers' ``WanTransformer3DModel``;
- the VAE from ``vae/`` in diffusers ``AutoencoderKLWan`` format. The release ships ``Wan2.2_VAE.pth``, a torch
  pickle: it must be converted to safetensors offline first (docs/notes/wan2.2-fun-control.md);
- no text encoder (the release's UMT5 is a pickle too): the text context is a fixed (1, text_len, text_dim)
  embedding, zeros (every prompt token padding) unless the caller passes precomputed prompt embeddings.

Loading is strict: a parameter missing, left over or of another shape is a ValueError naming the file and
the parameters. The release's optional ``ref_conv`` (a reference-image path) is loaded; ``generate(references=)``
gives every chunk a sheet of the entities' first looks through it (``forward_with_reference``: its tokens at rotary
frame 0, before the video's frames, as Wan-Fun's reference path has them), and ``wan_train`` trains it (``references``).
A Control-Camera adapter (``add_control_adapter``) is refused.

Control inputs (VideoX-Fun's Fun-Control layout): per chunk of T = 4k + 1 frames at H × W, latents of
F = k + 1 frames at H/16 × W/16, each normalised per channel, (z − latents_mean) / latents_std:

    noisy latents    48   x
    control latents  48   VAE(pose · 2 − 1), the pose frames read as an RGB video in [−1, 1]
    mask              4   1 on latent frame 0 (given), 0 elsewhere
    masked video     48   VAE(first frame, then zeros); its frame 0 is the first frame's own latent

concatenated to the transformer's 148 input channels. Sampling is rectified flow (x_σ = (1 − σ)·x₀ + σ·ε, the
network predicts ε − x₀) by Euler steps from σ = 1 to 0 on a uniform grid warped by Wan's timestep shift; latent
frame 0 is the first frame's latent at the start and after every step, and its tokens are given timestep 0.
No classifier-free guidance (without a text encoder there is no prompt to guide by).

Relay (``generate``), as in ``marionette.observation.relay``: chunk k + 1 starts from the last decoded frame of
chunk k and the next T − 1 pose frames, so N chunks give 1 + N·(T − 1) frames, with noise from one
``torch.Generator`` seeded by ``seed``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import torch
from safetensors.torch import save_file
from torch import Tensor, nn

from marionette.chunks import relay_chunks, relay_frames, relay_step
from marionette.corpus.paths import inside
from marionette.io import atomic_path, read_json, read_tensors, write_json
from marionette.observation.references import EntityReferences, reference_sheet

if TYPE_CHECKING:  # diffusers loads a second or more of modules: imported where a model is built
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

WEIGHTS = "diffusion_pytorch_model.safetensors"
PICKLES = (".pth", ".pt", ".bin", ".ckpt", ".pkl")
RGB = 3

# Original Wan parameter name → diffusers WanTransformer3DModel name, as a prefix of whole dotted components
# ("*" is the block index). Original norm1/norm2 and diffusers norm1/norm3 have no parameters; the original's
# cross-attention norm is norm3, diffusers' is norm2.
WAN_TO_DIFFUSERS = {
    "patch_embedding": "patch_embedding",
    "text_embedding.0": "condition_embedder.text_embedder.linear_1",
    "text_embedding.2": "condition_embedder.text_embedder.linear_2",
    "time_embedding.0": "condition_embedder.time_embedder.linear_1",
    "time_embedding.2": "condition_embedder.time_embedder.linear_2",
    "time_projection.1": "condition_embedder.time_proj",
    **{
        f"blocks.*.{a}.{o}": f"blocks.*.{b}.{d}"
        for a, b in (("self_attn", "attn1"), ("cross_attn", "attn2"))
        for o, d in (("q", "to_q"), ("k", "to_k"), ("v", "to_v"), ("o", "to_out.0"), ("norm_q", "norm_q"), ("norm_k", "norm_k"))
    },
    "blocks.*.norm3": "blocks.*.norm2",
    "blocks.*.ffn.0": "blocks.*.ffn.net.0.proj",
    "blocks.*.ffn.2": "blocks.*.ffn.net.2",
    "blocks.*.modulation": "blocks.*.scale_shift_table",
    "head.head": "proj_out",
    "head.modulation": "scale_shift_table",
}
DIFFUSERS_TO_WAN = {d: o for o, d in WAN_TO_DIFFUSERS.items()}

# The original config's keys (VideoX-Fun's WanTransformer3DModel arguments): those that fix the parameter set
# (required), those the release may leave out (Wan's defaults), and those that change nothing loaded here.
WAN_REQUIRED = ("dim", "ffn_dim", "num_heads", "num_layers", "in_dim", "out_dim")
WAN_DEFAULTS = {
    "patch_size": (1, 2, 2),
    "freq_dim": 256,
    "text_dim": 4096,
    "text_len": 512,
    "eps": 1e-6,
    "qk_norm": True,
    "cross_attn_norm": True,
    "window_size": (-1, -1),
    "add_control_adapter": False,
    "add_ref_conv": False,
    "in_dim_ref_conv": 16,
}
WAN_INERT = (
    "model_type",
    "cross_attn_type",
    "in_channels",
    "hidden_size",
    "in_dim_control_adapter",
    "downscale_factor_control_adapter",
    "_class_name",
    "_diffusers_version",
    "_name_or_path",
)


def _rename(name: str, table: dict[str, str]) -> str | None:
    """``name`` with the longest matching prefix of whole dotted components replaced by its value in ``table``;
    None where nothing matches."""
    m = re.fullmatch(r"blocks\.(\d+)\.(.+)", name)
    generic = f"blocks.*.{m[2]}" if m else name
    hits = [src for src in table if generic == src or generic.startswith(src + ".")]
    if not hits:
        return None
    src = max(hits, key=len)
    out = table[src] + generic[len(src) :]
    return out.replace("*", m[1], 1) if m else out


def wan_to_diffusers_name(name: str) -> str | None:
    """An original Wan parameter name → its diffusers ``WanTransformer3DModel`` name (None: no equivalent)."""
    return _rename(name, WAN_TO_DIFFUSERS)


def diffusers_to_wan_name(name: str) -> str | None:
    """A diffusers ``WanTransformer3DModel`` parameter name → its original Wan name (None: no equivalent)."""
    return _rename(name, DIFFUSERS_TO_WAN)


def transformer_kwargs(config: dict, where: str) -> dict:
    """An original Wan config (VideoX-Fun keys) → ``WanTransformer3DModel`` arguments; a ValueError, naming
    ``where``, for keys it does not know, missing required keys, or features diffusers' class lacks."""
    unknown = sorted(set(config) - {*WAN_REQUIRED, *WAN_DEFAULTS, *WAN_INERT})
    missing = [k for k in WAN_REQUIRED if k not in config]
    if unknown or missing:
        raise ValueError(f"{where}: not an original Wan transformer config: unknown keys {unknown}, missing keys {missing}")
    c = {**WAN_DEFAULTS, **config}
    if list(c["window_size"]) != [-1, -1]:
        raise ValueError(f"{where}: window_size {c['window_size']}: diffusers' WanTransformer3DModel has only global attention")
    if not c["qk_norm"]:
        raise ValueError(f"{where}: qk_norm false: diffusers' WanTransformer3DModel always normalises queries and keys")
    if c["add_control_adapter"]:
        raise ValueError(f"{where}: add_control_adapter (a Control-Camera model): this adapter maps pose control only")
    if c["dim"] % c["num_heads"]:
        raise ValueError(f"{where}: dim {c['dim']} does not split into {c['num_heads']} heads")
    return {
        "patch_size": tuple(c["patch_size"]),
        "num_attention_heads": c["num_heads"],
        "attention_head_dim": c["dim"] // c["num_heads"],
        "in_channels": c["in_dim"],
        "out_channels": c["out_dim"],
        "text_dim": c["text_dim"],
        "freq_dim": c["freq_dim"],
        "ffn_dim": c["ffn_dim"],
        "num_layers": c["num_layers"],
        "cross_attn_norm": bool(c["cross_attn_norm"]),
        "qk_norm": "rms_norm_across_heads",
        "eps": c["eps"],
    }


def original_config(transformer: WanTransformer3DModel, text_len: int = 512, ref_conv: nn.Conv2d | None = None) -> dict:
    """The inverse of ``transformer_kwargs``: the original Wan config of a diffusers transformer. The original
    format has no RoPE table length (Wan's covers 1024 positions; a position's angles do not depend on it)."""
    c = transformer.config
    if c.image_dim is not None or c.added_kv_proj_dim is not None or c.pos_embed_seq_len is not None:
        raise ValueError("original_config: an image-conditioned (CLIP) Wan transformer has no mapping here")
    if c.qk_norm != "rms_norm_across_heads":
        raise ValueError(f"original_config: qk_norm {c.qk_norm!r} has no original equivalent")
    return {
        "model_type": "ti2v",
        "dim": c.num_attention_heads * c.attention_head_dim,
        "ffn_dim": c.ffn_dim,
        "num_heads": c.num_attention_heads,
        "num_layers": c.num_layers,
        "in_dim": c.in_channels,
        "out_dim": c.out_channels,
        "patch_size": list(c.patch_size),
        "freq_dim": c.freq_dim,
        "text_dim": c.text_dim,
        "text_len": text_len,
        "eps": c.eps,
        "qk_norm": True,
        "cross_attn_norm": c.cross_attn_norm,
        "window_size": [-1, -1],
        "add_control_adapter": False,
        "add_ref_conv": ref_conv is not None,
        "in_dim_ref_conv": ref_conv.in_channels if ref_conv is not None else 16,
    }


SHARD_FILE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,200}\.safetensors")


def index_shards(index: Path) -> list[Path]:
    """The shard files a ``*.safetensors.index.json`` names, each checked to be a plain ``*.safetensors`` name
    in the index's own directory (a model directory is untrusted input); else a ValueError naming the entry."""
    try:
        weight_map = read_json(index)["weight_map"]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{index}: not a safetensors index with a weight_map ({type(exc).__name__}: {exc})") from None
    if not isinstance(weight_map, dict):
        raise ValueError(f"{index}: weight_map is not an object")
    out = []
    for name in sorted({str(v) for v in weight_map.values()}):
        if not SHARD_FILE.fullmatch(name) or ".." in name:
            raise ValueError(f"{index}: weight_map names {name!r}, which is not a *.safetensors file beside the index")
        out.append(inside(index.parent, index.parent / name, str(index)))
    return out


def read_safetensors(directory: Path) -> tuple[dict[str, Tensor], Path]:
    """The tensors of ``directory``'s ``diffusion_pytorch_model.safetensors`` (or of the shards its
    ``.index.json`` names) and the file read; a ValueError if there are none (pickles are never loaded)."""
    single, index = directory / WEIGHTS, directory / f"{WEIGHTS}.index.json"
    if single.is_file():
        return read_tensors(single), single
    if index.is_file():
        weights: dict[str, Tensor] = {}
        for shard in index_shards(index):
            weights.update(read_tensors(shard))
        return weights, index
    pickles = sorted(p.name for p in directory.iterdir() if p.suffix in PICKLES) if directory.is_dir() else []
    hint = f"; {pickles} are torch pickles, which are never loaded here: convert them offline to safetensors" if pickles else ""
    raise ValueError(f"{directory}: no {WEIGHTS} (nor its .index.json){hint}")


def _names(keys: list[str], most: int = 8) -> str:
    return str(keys[:most])[:-1] + (f", … {len(keys) - most} more]" if len(keys) > most else "]")


def _assign(model: nn.Module, weights: dict[str, Tensor], file: Path, show=lambda k: k, unmapped: tuple[str, ...] = ()) -> None:
    """Load ``weights`` into ``model`` (built on the meta device) strictly: every parameter present, none left
    over, every shape equal; else a ValueError naming ``file`` and the parameters, in the file's names (``show``)."""
    expected = model.state_dict()
    missing = sorted(show(k) for k in expected.keys() - weights.keys())
    extra = sorted([*unmapped, *(show(k) for k in weights.keys() - expected.keys())])
    shapes = sorted(
        f"{show(k)} {tuple(weights[k].shape)} (model {tuple(expected[k].shape)})"
        for k in expected.keys() & weights.keys()
        if weights[k].shape != expected[k].shape
    )
    found = {"missing": missing, "unexpected": extra, "wrong shape": shapes}
    problems = [f"{what} {_names(keys)}" for what, keys in found.items() if keys]
    if problems:
        raise ValueError(f"{file}: does not fit {type(model).__name__}: " + "; ".join(problems))
    model.load_state_dict(weights, strict=True, assign=True)


class Backbone(NamedTuple):
    """What ``load_transformer`` reads from a checkpoint directory."""

    transformer: WanTransformer3DModel
    ref_conv: nn.Conv2d | None  # the release's reference-image patch embedding, if it has one
    text_len: int


def load_transformer(directory: Path) -> Backbone:
    """The transformer of a local directory: ``config.json`` in the original Wan keys (parameters renamed by
    ``WAN_TO_DIFFUSERS``) or in diffusers' keys, and safetensors weights. Strict (``_assign``)."""
    directory = Path(directory)
    path = directory / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{directory}: no config.json (a transformer checkpoint directory)")
    config = read_json(path)
    weights, file = read_safetensors(directory)
    from diffusers import WanTransformer3DModel

    if "num_attention_heads" in config:  # diffusers format: its own class reads its own config
        with torch.device("meta"):
            transformer = WanTransformer3DModel.from_config(config)
        _assign(transformer, weights, file)
        return Backbone(_with_rope(transformer), None, 512)
    kwargs = transformer_kwargs(config, str(path))
    with torch.device("meta"):
        transformer = WanTransformer3DModel(**kwargs)
    ref = None
    if config.get("add_ref_conv"):
        p, width = kwargs["patch_size"][1:], config["dim"]
        # a reference image's latent (B, 48, h, w) → tokens; kept so the load is strict, unused by generate
        ref = nn.Conv2d(config.get("in_dim_ref_conv", 16), width, kernel_size=p, stride=p, device="meta")
        ref_weights = {k.removeprefix("ref_conv."): weights.pop(k) for k in [k for k in weights if k.startswith("ref_conv.")]}
        _assign(ref, ref_weights, file, show=lambda k: f"ref_conv.{k}")
    unmapped = tuple(sorted(k for k in weights if wan_to_diffusers_name(k) is None))
    renamed = {wan_to_diffusers_name(k): v for k, v in weights.items() if k not in unmapped}
    _assign(transformer, renamed, file, show=lambda k: diffusers_to_wan_name(k) or k, unmapped=unmapped)
    return Backbone(_with_rope(transformer), ref, int(config.get("text_len", 512)))


def _with_rope(transformer: WanTransformer3DModel) -> WanTransformer3DModel:
    """Recompute the RoPE tables (non-persistent buffers, so still on the meta device after loading)."""
    c = transformer.config
    transformer.rope = type(transformer.rope)(c.attention_head_dim, tuple(c.patch_size), c.rope_max_seq_len)
    return transformer


def save_original(
    directory: Path, transformer: WanTransformer3DModel, text_len: int = 512, ref_conv: nn.Conv2d | None = None
) -> None:
    """Write ``transformer`` (and a ``ref_conv``) as the release lays it out: ``config.json`` in the original Wan
    keys and ``diffusion_pytorch_model.safetensors`` in the original parameter names (``load_transformer`` reads it)."""
    config = original_config(transformer, text_len, ref_conv)
    state = transformer.state_dict()
    unnamed = sorted(k for k in state if diffusers_to_wan_name(k) is None)
    if unnamed:
        raise ValueError(f"save_original: parameters with no original name: {_names(unnamed)}")
    tensors = {diffusers_to_wan_name(k): v for k, v in state.items()}
    if ref_conv is not None:
        tensors.update({f"ref_conv.{k}": v for k, v in ref_conv.state_dict().items()})
    with atomic_path(Path(directory) / WEIGHTS) as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(tmp), metadata={"format": "pt"})
    write_json(Path(directory) / "config.json", config)


def load_vae(directory: Path) -> AutoencoderKLWan:
    """A diffusers-format ``AutoencoderKLWan`` (``config.json`` + safetensors) from a local directory. Strict."""
    directory = Path(directory)
    path = directory / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{directory}: no config.json (a diffusers AutoencoderKLWan directory)")
    weights, file = read_safetensors(directory)
    from diffusers import AutoencoderKLWan

    with torch.device("meta"):
        vae = AutoencoderKLWan.from_config(read_json(path))
    _assign(vae, weights, file)
    return vae


def find_vae(root: Path) -> Path:
    """``root/vae``; a ValueError saying what to do if it is missing, in particular if the only VAE is a pickle."""
    if (root / "vae" / "config.json").is_file():
        return root / "vae"
    pickles = sorted(p.name for p in root.iterdir() if p.suffix in PICKLES and "vae" in p.name.lower())
    if pickles:
        raise ValueError(
            f"{root}: the VAE here is a torch pickle ({', '.join(pickles)}), which this adapter never unpickles: convert it "
            "offline to a diffusers AutoencoderKLWan directory (config.json + safetensors) at vae/, or pass vae=<that directory>"
        )
    raise ValueError(f"{root}: no vae/ directory (a diffusers AutoencoderKLWan: config.json + safetensors)")


def flow_sigmas(steps: int, shift: float) -> Tensor:
    """Noise levels 1 → 0 for ``steps`` Euler steps: a uniform grid σ warped by Wan's timestep shift,
    shift·σ / (1 + (shift − 1)·σ), which spends more of the steps at high noise when shift > 1."""
    s = torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64)
    return (shift * s / (1 + (shift - 1) * s)).float()


def _cast(model: nn.Module, dtype: torch.dtype) -> nn.Module:
    """``model`` in ``dtype``, but the modules diffusers keeps in float32 (``_keep_in_fp32_modules``) in float32."""
    keep = set(getattr(model, "_keep_in_fp32_modules", None) or ())
    for name, p in model.named_parameters():
        p.data = p.data.to(torch.float32 if keep & set(name.split(".")) else dtype)
    return model


def forward_with_reference(
    transformer: WanTransformer3DModel, hidden_states: Tensor, timestep: Tensor, context: Tensor, ref: Tensor
) -> Tensor:
    """``WanTransformer3DModel.forward`` with reference tokens ``ref`` (B, n, dim) in front of the video's tokens, as
    Wan-Fun's reference path has them: n is one latent frame's tokens (or 0: the plain forward, step for step), they
    sit at rotary frame 0 with the video's frames after them, at timestep 0 (a clean image), every video token
    attends to them, and they are dropped before the output head. ``timestep`` is per token (B, seq)."""
    B, C, F, H, W = hidden_states.shape
    pt, ph, pw = transformer.config.patch_size
    n = ref.shape[1]
    if n not in (0, (H // ph) * (W // pw)) or ref.shape[0] != B:
        raise ValueError(f"reference tokens {tuple(ref.shape)}: {B} × one latent frame's {(H // ph) * (W // pw)} tokens expected")
    if timestep.ndim != 2:
        raise ValueError(f"timestep {tuple(timestep.shape)}: per token (B, seq) expected")
    rotary = transformer.rope(torch.empty(B, C, F + (pt if n else 0), H, W, device="meta"))  # the reference as frame 0
    rotary = tuple(r.to(hidden_states.device) for r in rotary)
    x = transformer.patch_embedding(hidden_states).flatten(2).transpose(1, 2)  # (B, seq, dim)
    x = torch.cat([ref.to(x.dtype), x], dim=1).contiguous()
    ts = torch.cat([timestep.new_zeros(B, n), timestep], dim=1)  # (B, n + seq)
    temb, proj, ctx, _ = transformer.condition_embedder(ts.flatten(), context, None, timestep_seq_len=ts.shape[1])
    proj = proj.unflatten(2, (6, -1))  # (B, n + seq, 6, dim)
    for block in transformer.blocks:
        if torch.is_grad_enabled() and transformer.gradient_checkpointing:
            x = transformer._gradient_checkpointing_func(block, x, ctx, proj, rotary)
        else:
            x = block(x, ctx, proj, rotary)
    x, temb = x[:, n:], temb[:, n:]
    shift, scale = (transformer.scale_shift_table.unsqueeze(0).to(temb.device) + temb.unsqueeze(2)).chunk(2, dim=2)
    x = (transformer.norm_out(x.float()) * (1 + scale.squeeze(2)) + shift.squeeze(2)).type_as(x)
    x = transformer.proj_out(x).reshape(B, F // pt, H // ph, W // pw, pt, ph, pw, -1)
    return x.permute(0, 7, 1, 4, 2, 5, 3, 6).flatten(6, 7).flatten(4, 5).flatten(2, 3)


def ref_tokens(ref_conv: nn.Conv2d, latent: Tensor) -> Tensor:
    """Reference latents (B, z, 1, h, w) → their tokens (B, n, dim) through ``ref_conv`` (one latent frame's worth)."""
    return ref_conv(latent[:, :, 0].to(ref_conv.weight.dtype)).flatten(2).transpose(1, 2)


class WanFunControl:
    """Wan2.2-Fun-5B-Control with the observation model's call shape: ``generate(pose, first, chunks, steps, seed)``."""

    def __init__(
        self,
        transformer: WanTransformer3DModel,
        vae: AutoencoderKLWan,
        frames: int = 81,
        shift: float = 5.0,
        prompt_embeds: Tensor | None = None,
        text_len: int = 512,
        ref_conv: nn.Conv2d | None = None,
    ) -> None:
        c, v = transformer.config, vae.config
        self.transformer, self.vae, self.ref_conv = transformer.eval(), vae.eval(), ref_conv
        self.frames, self.shift = int(frames), float(shift)
        self.temporal, self.spatial = int(v.scale_factor_temporal), int(v.scale_factor_spatial)
        # inputs: noisy, control and masked-video latents, and a mask channel per pixel frame a latent frame spans
        if c.in_channels != 3 * v.z_dim + self.temporal or c.out_channels != v.z_dim:
            raise ValueError(
                f"transformer {c.in_channels} → {c.out_channels} channels does not fit a {v.z_dim}-channel VAE: "
                f"Fun-Control takes {3 * v.z_dim + self.temporal} (noisy, control, mask, masked video) → {v.z_dim}"
            )
        if self.frames <= 1 or (self.frames - 1) % self.temporal:
            raise ValueError(f"chunk of {frames} frames: it must be {self.temporal}k + 1 with k ≥ 1")
        if prompt_embeds is None:
            prompt_embeds = torch.zeros(text_len, c.text_dim)
        e = prompt_embeds.reshape(-1, prompt_embeds.shape[-1])
        if e.shape[1] != c.text_dim or len(e) > text_len:
            raise ValueError(f"prompt embeddings {tuple(prompt_embeds.shape)}: the transformer takes ≤ {text_len} × {c.text_dim}")
        self.device = next(transformer.parameters()).device
        self.dtype = transformer.patch_embedding.weight.dtype
        e = torch.cat([e, e.new_zeros(text_len - len(e), e.shape[1])])  # zero padding, as Wan pads its prompts
        self.context = e[None].to(self.device, self.dtype)  # (1, text_len, text_dim)
        self.mean = torch.tensor(v.latents_mean).view(1, -1, 1, 1, 1).to(self.device)
        self.std = torch.tensor(v.latents_std).view(1, -1, 1, 1, 1).to(self.device)

    @classmethod
    def from_pretrained(
        cls,
        root: Path,
        vae: Path | None = None,
        frames: int = 81,
        shift: float = 5.0,
        prompt_embeds: Tensor | None = None,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
    ) -> WanFunControl:
        """Load a local checkpoint directory: the transformer from ``root`` (release layout) or ``root/transformer``
        (diffusers layout), the VAE from ``vae`` or ``root/vae``. The transformer runs in ``dtype`` (except the
        modules diffusers keeps in float32), the VAE in float32."""
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: not a directory (only local checkpoints are loaded)")
        where = root if (root / "config.json").is_file() else root / "transformer"
        if not (where / "config.json").is_file():
            raise FileNotFoundError(f"{root}: no config.json (release layout) nor transformer/config.json (diffusers layout)")
        backbone = load_transformer(where)
        autoencoder = load_vae(Path(vae) if vae is not None else find_vae(root))
        transformer = _cast(backbone.transformer, dtype).to(device).requires_grad_(False)
        ref_conv = backbone.ref_conv.to(device, dtype).requires_grad_(False) if backbone.ref_conv is not None else None
        autoencoder = _cast(autoencoder, torch.float32).to(device).requires_grad_(False)
        return cls(transformer, autoencoder, frames, shift, prompt_embeds, backbone.text_len, ref_conv)

    def check_inputs(self, control: Tensor, first: Tensor) -> None:
        """Fail before any compute, naming the mismatch, unless ``control`` is (T, 3, H, W) pose frames in [0, 1]
        with T = 4k + 1 ≥ one chunk, ``first`` is (3, H, W) in [−1, 1], and H, W are whole latent patches."""
        if control.ndim != 4 or control.shape[1] != RGB:
            raise ValueError(f"pose video {tuple(control.shape)}: the adapter takes (T, {RGB}, H, W) pose frames")
        T, _, H, W = control.shape
        if (T - 1) % self.temporal or len(control) < self.frames:
            raise ValueError(f"pose video of {T} frames: it needs {self.temporal}k + 1, at least a chunk ({self.frames})")
        if tuple(first.shape) != (RGB, H, W):
            raise ValueError(f"first frame {tuple(first.shape)}: the pose video's frames are ({RGB}, {H}, {W})")
        _, ph, pw = self.transformer.config.patch_size
        if H % (self.spatial * ph) or W % (self.spatial * pw):
            raise ValueError(
                f"{H}×{W}: height and width must be multiples of {self.spatial * ph}×{self.spatial * pw} "
                f"(the VAE's {self.spatial}× reduction times the transformer's {ph}×{pw} patch)"
            )
        if float(control.min()) < 0.0 or float(control.max()) > 1.0:
            raise ValueError("pose video: values outside [0, 1]")
        if float(first.min()) < -1.0 or float(first.max()) > 1.0:
            raise ValueError("first frame: values outside [−1, 1]")

    def encode(self, video: Tensor) -> Tensor:
        """(T, 3, H, W) in [−1, 1] → normalised latents (1, z, 1 + (T − 1)/4, H/16, W/16) (the distribution's mode)."""
        x = video.permute(1, 0, 2, 3)[None].to(self.device, torch.float32)  # (1, 3, T, H, W)
        return (self.vae.encode(x).latent_dist.mode() - self.mean) / self.std

    def decode(self, latents: Tensor) -> Tensor:
        """Normalised latents (1, z, F, h, w) → (4(F − 1) + 1, 3, 16h, 16w) in [−1, 1], on the CPU."""
        return self.vae.decode(latents * self.std + self.mean).sample[0].permute(1, 0, 2, 3).float().cpu()

    def reference_tokens(self, sheet: Tensor) -> Tensor:
        """A reference image (3, H, W) in [−1, 1] → its tokens (1, n, dim) through the release's ``ref_conv``: the VAE's
        latent of the image as a one-frame video, patch-embedded (n = one latent frame's tokens)."""
        self.need_ref_conv()
        latent = self.encode(sheet[None])  # (1, z, 1, h, w)
        if latent.shape[1] != self.ref_conv.in_channels:
            raise ValueError(f"ref_conv takes {self.ref_conv.in_channels} latent channels; the VAE gives {latent.shape[1]}")
        return ref_tokens(self.ref_conv, latent)

    def need_ref_conv(self) -> None:
        """A ValueError unless this checkpoint has the release's reference-image path."""
        if self.ref_conv is None:
            raise ValueError(
                "this checkpoint has no reference-image path (its config has no add_ref_conv); paint without references"
            )

    def velocity(self, inp: Tensor, timestep: Tensor, ref: Tensor | None = None) -> Tensor:
        """The transformer's output for ``inp`` (B, 148, F, h, w) at per-token ``timestep`` (B, seq); with reference
        tokens ``ref`` (B, n, dim), ``forward_with_reference``."""
        if ref is None:
            return self.transformer(inp, timestep=timestep, encoder_hidden_states=self.context, return_dict=False)[0]
        return forward_with_reference(self.transformer, inp, timestep, self.context, ref)

    @torch.inference_mode()
    def sample_chunk(
        self, pose: Tensor, first: Tensor, steps: int, generator: torch.Generator, ref: Tensor | None = None
    ) -> Tensor:
        """One chunk (T, 3, H, W) in [−1, 1] from its pose frames (T, 3, H, W) in [0, 1] and first frame (3, H, W)
        (``ref``: reference tokens, ``reference_tokens``)."""
        control = self.encode(pose * 2.0 - 1.0)  # (1, z, F, h, w)
        masked = torch.zeros(pose.shape)  # the first frame, then zeros
        masked[0] = first.float().cpu()
        masked = self.encode(masked)  # (1, z, F, h, w); frame 0 is the first frame's latent (the VAE is causal)
        given = masked[:, :, :1]
        mask = torch.zeros(1, self.temporal, *control.shape[2:], device=self.device)
        mask[:, :, 0] = 1.0
        cond = torch.cat([control, mask, masked], dim=1)  # (1, 100, F, h, w)
        pt, ph, pw = self.transformer.config.patch_size
        F, h, w = control.shape[2:]
        per_token = torch.ones(F // pt, h // ph, w // pw, device=self.device)
        per_token[0] = 0.0  # frame 0 is given: its tokens sit at timestep 0
        per_token = per_token.reshape(1, -1)  # (1, seq_len)
        x = torch.randn(control.shape, generator=generator).to(self.device)
        x[:, :, :1] = given
        sigmas = flow_sigmas(steps, self.shift).tolist()
        for s, s_next in zip(sigmas[:-1], sigmas[1:]):
            inp = torch.cat([x, cond], dim=1).to(self.dtype)  # (1, 148, F, h, w)
            v = self.velocity(inp, 1000.0 * s * per_token, ref)
            x = x + (s_next - s) * v.float()
            x[:, :, :1] = given
        return self.decode(x)

    def generate(
        self,
        control: Tensor,
        first: Tensor,
        chunks: int | None = None,
        steps: int = 50,
        seed: int = 0,
        references: Sequence[tuple[int, int]] = (),
    ) -> Tensor:
        """RGB video (1 + N·(T − 1), 3, H, W) in [−1, 1] from a pose video (T', 3, H, W) in [0, 1] and a first frame
        (3, H, W) in [−1, 1], relayed over N chunks of T = ``frames`` (default: as many as the pose video holds).

        ``references`` (render-id bands, one per entity): every chunk is given, through ``ref_conv``, a reference
        sheet of each entity's crop from the first frame that showed it (the given first frame, then the generated
        ones; ``observation.references``), so a relay keeps each entity's first look."""
        self.check_inputs(control, first)
        seen = None
        if references:
            self.need_ref_conv()
            H, W = first.shape[1:]
            seen = EntityReferences(references, min(H, W // len(references)))
            seen.see(first[None].float().cpu(), control[:1])
        step = relay_step(self.frames)
        n = relay_chunks(len(control), self.frames) if chunks is None else int(chunks)
        if n < 1 or relay_frames(n, self.frames) > len(control):
            raise ValueError(f"{n} chunks need {relay_frames(n, self.frames)} pose frames; the pose video has {len(control)}")
        if steps < 1:
            raise ValueError(f"steps {steps}: at least one sampling step")
        g = torch.Generator().manual_seed(int(seed))
        out, cur = [first[None].float().cpu()], first
        for k in range(n):
            ctrl = control[k * step : k * step + self.frames]
            ref = None
            if seen is not None:
                with torch.inference_mode():
                    ref = self.reference_tokens(reference_sheet(seen.tensor(), *first.shape[1:]))
            clip = self.sample_chunk(ctrl, cur, steps, g, ref)
            if seen is not None:
                seen.see(clip[1:], ctrl[1:], offset=k * step + 1, painted=True)
            out.append(clip[1:])
            cur = clip[-1]
        return torch.cat(out, dim=0)
