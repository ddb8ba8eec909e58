"""A small control-conditioned video diffusion transformer: pose-control video + first frame → RGB video.

The network (``VideoDiT``) is a DiT over patches of reduced-resolution pixels. A clip of T frames of
H × W enters as one token per (frame, p × p patch): each token concatenates, per pixel of its patch,

- the noisy RGB x_s (3 channels),
- the pose-control frame (3: the bridge's height, identity, inverse depth in [0, 1]),
- the given video and its mask, as Wan-Fun-Control's masked-video latents: on frame 0 the first frame (3)
  and 1, on every other frame zeros,

projected to ``width``, plus fixed sine–cosine embeddings of the frame index and of the patch row
and column. Blocks are pre-norm self-attention over all T·(H/p)·(W/p) tokens and an MLP, each
modulated (shift, scale, gate; zero-initialised gates, "adaLN-Zero") by an embedding of the noise
level s. A linear head returns, per patch, the velocity (3 channels per pixel).

Why the first frame sits on frame 0 only: a token of frame t then has no local copy of the first frame,
so where a body is comes from its pose pixels and what it looks like from attention to frame 0. Given the
first frame on every frame's tokens, the network learns to redraw the first frame's bodies under any pose (docs/tradeoffs.md, "does the model follow the pose?").

Objective: rectified flow. x_s = (1 − s)·x₀ + s·ε with ε ~ N(0, I), s ~ U(0, 1); the network predicts
v = ε − x₀; the loss is the MSE of v over frames 1..T−1 (frame 0 is given). Training may give a clip
another clip's frame as its first frame (``flow_loss(..., first=)``, the trainer's ``reference_swap``):
its targets stay its own frames, so the pose, not the first frame, must say where bodies are. Sampling integrates
dx/ds = v from s = 1 to 0 with ``steps`` Euler steps on a uniform grid, with frame 0 held at the
first frame's noised value x_s = (1 − s)·first + s·ε₀ so that it is consistent with every step.

Persistent entity references (``reference_bands``, ``observation.references``): a model with reference slots
also reads, per entity slot, a crop of that entity (RGB and its mask, ``reference_size`` pixels square) as
(r/p)² tokens of its own — a linear patch embedding of their own, the patch row and column embeddings and a learnt
embedding of the slot — that every token attends to and none is painted from; a slot with nothing seen is zeros.
With ``reference_paint`` each crop is also laid over its entity's pixels in every frame (``references.paint``: 3
colour channels and a mask, four more input channels a pixel), so a token reads the look of the body it paints
where it paints it; tokens alone must find the right slot by attention (docs/tradeoffs.md, "Persistent entity
references").

The pixel-AR baseline of the paper is the same network with ``control="actions"``: no pose channels;
instead each frame's tokens get the sum of per-entity embeddings of that frame's action tokens (the
action schedule), so it must infer where bodies are from the first frame and the actions alone.

A video longer than one chunk is painted by the relay, ``observation.relay``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from marionette.observation.config import POSE, RGB, ObservationConfig
from marionette.observation.references import paint


def sincos(positions: Tensor, dim: int) -> Tensor:
    """(n,) positions → (n, dim) sine–cosine embeddings (base 10000)."""
    half = dim // 2
    freq = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float64, device=positions.device) / half)
    ang = positions.double()[:, None] * freq[None]
    return torch.cat([ang.sin(), ang.cos()], dim=-1).float()


class Block(nn.Module):
    def __init__(self, c: ObservationConfig) -> None:
        super().__init__()
        self.heads = c.heads
        self.norm1 = nn.LayerNorm(c.width, elementwise_affine=False)
        self.qkv = nn.Linear(c.width, 3 * c.width)
        self.proj = nn.Linear(c.width, c.width)
        self.norm2 = nn.LayerNorm(c.width, elementwise_affine=False)
        self.mlp = nn.Sequential(nn.Linear(c.width, c.mlp_ratio * c.width), nn.GELU(), nn.Linear(c.mlp_ratio * c.width, c.width))
        self.modulation = nn.Linear(c.width, 6 * c.width)  # shift/scale/gate for attention and MLP

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        B, N, C = x.shape
        s1, c1, g1, s2, c2, g2 = self.modulation(cond)[:, None].chunk(6, dim=-1)  # (B, 1, C) each
        h = self.norm1(x) * (1 + c1) + s1
        q, k, v = self.qkv(h).view(B, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)  # (B, nh, N, hs)
        a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(B, N, C)
        x = x + g1 * self.proj(a)
        return x + g2 * self.mlp(self.norm2(x) * (1 + c2) + s2)


class VideoDiT(nn.Module):
    """Velocity of the noisy RGB of a clip, given its pose frames, its first frame and the noise level."""

    def __init__(self, config: ObservationConfig, seed: int = 0) -> None:
        super().__init__()
        c = self.config = config
        g = torch.Generator().manual_seed(int(seed))
        p = c.patch
        self.embed = nn.Linear(c.in_channels * p * p, c.width)
        # the baseline's action schedule: per entity, an embedding of its token added to every token of that frame
        self.actions = nn.ModuleList(nn.Embedding(v, c.width) for v in c.vocab_sizes) if c.control == "actions" else None
        self.time = nn.Sequential(nn.Linear(c.width, c.width), nn.SiLU(), nn.Linear(c.width, c.width))
        self.blocks = nn.ModuleList(Block(c) for _ in range(c.layers))
        self.norm = nn.LayerNorm(c.width, elementwise_affine=False)
        self.final_mod = nn.Linear(c.width, 2 * c.width)
        self.head = nn.Linear(c.width, RGB * p * p)
        if c.references:  # each entity's reference (RGB and its mask) as tokens of its own, a learnt slot embedding each
            self.ref_embed = nn.Linear((RGB + 1) * p * p, c.width)
            self.ref_slot = nn.Embedding(c.references, c.width)
        # the given frame's noise level (handoff_noise), added to the time embedding; zero at first
        self.given_level = nn.Linear(c.width, c.width) if c.handoff_noise else None
        with torch.no_grad():
            for m in self.modules():
                if isinstance(m, nn.Linear):
                    m.weight.normal_(0.0, m.in_features**-0.5, generator=g)
                    m.bias.zero_()
                elif isinstance(m, nn.Embedding):
                    m.weight.normal_(0.0, 0.02, generator=g)
            for b in self.blocks:  # adaLN-Zero: every block starts as the identity
                b.modulation.weight.zero_()
            self.final_mod.weight.zero_()
            self.head.weight.zero_()
            if self.given_level is not None:
                self.given_level.weight.zero_()
        hp, wp = c.height // p, c.width_px // p
        t, r, q = torch.meshgrid(torch.arange(c.frames), torch.arange(hp), torch.arange(wp), indexing="ij")
        third = (c.width // 3) // 2 * 2
        pos = torch.cat(
            [sincos(t.reshape(-1), third), sincos(r.reshape(-1), third), sincos(q.reshape(-1), c.width - 2 * third)], -1
        )
        self.register_buffer("pos", pos, persistent=False)  # (tokens, width)
        if c.references:
            n = c.reference_size // p
            r, q = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
            ref_pos = torch.cat(
                [torch.zeros(n * n, third), sincos(r.reshape(-1), third), sincos(q.reshape(-1), c.width - 2 * third)], -1
            )
            self.register_buffer("ref_pos", ref_pos, persistent=False)  # (patches of a reference, width)

    def patchify(self, x: Tensor) -> Tensor:
        """(B, T, C, H, W) → (B, T·(H/p)·(W/p), C·p·p)."""
        B, T, C, H, W = x.shape
        p = self.config.patch
        x = x.reshape(B, T, C, H // p, p, W // p, p).permute(0, 1, 3, 5, 2, 4, 6)
        return x.reshape(B, T * (H // p) * (W // p), C * p * p)

    def unpatchify(self, x: Tensor) -> Tensor:
        """(B, tokens, C·p·p) → (B, T, C, H, W)."""
        c, p = self.config, self.config.patch
        B = x.shape[0]
        hp, wp = c.height // p, c.width_px // p
        x = x.reshape(B, c.frames, hp, wp, -1, p, p).permute(0, 1, 4, 2, 5, 3, 6)
        return x.reshape(B, c.frames, -1, c.height, c.width_px)

    def forward(
        self, x_s: Tensor, control: Tensor, first: Tensor, s: Tensor, refs: Tensor | None = None, level: Tensor | None = None
    ) -> Tensor:
        """x_s (B, T, 3, H, W); control: pose (B, T, 3, H, W), or action tokens (B, T, N) for the baseline;
        first (B, 3, H, W); s (B,); refs (B, E, 4, r, r), the entity references of a model with reference slots
        (None: none seen); level (B,): the noise σ on ``first`` of a model with ``handoff_noise`` (None: clean)
        → velocity (B, T, 3, H, W)."""
        c = self.config
        B, T = x_s.shape[:2]
        given = torch.zeros(B, T, RGB + 1, *x_s.shape[3:], dtype=x_s.dtype, device=x_s.device)  # Wan's masked video + mask
        given[:, 0, :RGB], given[:, 0, RGB] = first, 1.0
        parts = [x_s, control, given] if c.control == "pose" else [x_s, given]
        if c.references:
            r = c.reference_size
            if refs is None:
                refs = torch.zeros(B, c.references, RGB + 1, r, r, dtype=x_s.dtype, device=x_s.device)
            if tuple(refs.shape) != (B, c.references, RGB + 1, r, r):
                raise ValueError(f"references {tuple(refs.shape)}: the model takes ({B}, {c.references}, {RGB + 1}, {r}, {r})")
            refs = refs.to(x_s.dtype)
            if c.reference_paint:
                parts.append(paint(refs, control, c.reference_bands))  # in the references' dtype, x_s's
        tokens = self.embed(self.patchify(torch.cat(parts, dim=2))) + self.pos
        if self.actions is not None:
            per_frame = sum(emb(control[..., i]) for i, emb in enumerate(self.actions))  # (B, T, width)
            tokens = (tokens.view(B, T, -1, c.width) + per_frame[:, :, None]).view(B, -1, c.width)
        n = tokens.shape[1]
        if c.references:
            per = self.ref_embed(self.patchify(refs)).view(B, c.references, -1, c.width)
            per = per + self.ref_pos + self.ref_slot.weight[:, None]
            tokens = torch.cat([tokens, per.reshape(B, -1, c.width)], dim=1)
        cond = self.time(sincos(s * 1000.0, c.width).to(x_s.dtype))  # (B, width)
        if self.given_level is not None:  # a given frame without a level is clean: level 0, as trained
            level = torch.zeros(B, device=x_s.device) if level is None else level
            cond = cond + self.given_level(sincos(level * 1000.0, c.width).to(x_s.dtype))
        for block in self.blocks:
            tokens = block(tokens, cond)
        tokens = tokens[:, :n]  # the references' tokens are read, never painted
        shift, scale = self.final_mod(cond)[:, None].chunk(2, dim=-1)
        return self.unpatchify(self.head(self.norm(tokens) * (1 + scale) + shift))


def check_inputs(config: ObservationConfig, control: Tensor, first: Tensor) -> None:
    """Fail before any compute, naming the mismatch, unless the control is (T, 3, H, W) pose frames at the
    model's size (or (T, N) action tokens within the vocabularies, for the baseline) and first is (3, H, W)."""
    h, w = config.size
    if config.control == "pose":
        if control.ndim != 4 or control.shape[1] != POSE or tuple(control.shape[2:]) != (h, w):
            raise ValueError(
                f"pose video {tuple(control.shape)}: the model takes (T, {POSE}, {h}, {w}) pose frames (height, id, inverse depth)"
            )
    else:
        n = len(config.vocab_sizes)
        if control.ndim != 2 or control.shape[1] != n or control.dtype != torch.int64:
            raise ValueError(f"action schedule {tuple(control.shape)} {control.dtype}: the baseline takes (T, {n}) int64 tokens")
        for i, v in enumerate(config.vocab_sizes):
            if int(control[:, i].min()) < 0 or int(control[:, i].max()) >= v:
                raise ValueError(f"action schedule: entity {i}'s tokens leave its vocabulary of {v}")
    if len(control) < config.frames:
        raise ValueError(f"control of {len(control)} frames: a chunk needs {config.frames}")
    if first.shape != (RGB, h, w):
        raise ValueError(f"first frame {tuple(first.shape)}: the model takes ({RGB}, {h}, {w})")


def flow_loss(
    model: VideoDiT,
    rgb: Tensor,
    control: Tensor,
    generator: torch.Generator,
    first: Tensor | None = None,
    refs: Tensor | None = None,
    level: Tensor | None = None,
) -> Tensor:
    """Rectified-flow loss of a batch of clips (B, T, 3, H, W) under their control, frames 1..T−1 (module doc);
    ``first`` (B, 3, H, W): the given first frames, if not the clips' own frame 0; ``refs``: entity references;
    ``level`` (B,): the noise σ on the given first frames (``handoff_noise``)."""
    B = rgb.shape[0]
    if first is not None:
        rgb = torch.cat([first[:, None], rgb[:, 1:]], dim=1)
    s = torch.rand(B, generator=generator).to(rgb.device)
    eps = torch.randn(rgb.shape, generator=generator).to(rgb.device)
    x_s = (1 - s)[:, None, None, None, None] * rgb + s[:, None, None, None, None] * eps
    v = model(x_s, control, rgb[:, 0], s, refs, level)
    return F.mse_loss(v[:, 1:], (eps - rgb)[:, 1:])


@torch.no_grad()
def sample_chunk(
    model: VideoDiT,
    control: Tensor,
    first: Tensor,
    steps: int,
    generator: torch.Generator,
    refs: Tensor | None = None,
    level: Tensor | None = None,
) -> Tensor:
    """One chunk (B, T, 3, H, W) in [−1, 1] from its control (B, T, ...) and first frames (B, 3, H, W) by Euler
    steps (``refs``: entity references, for a model with reference slots; ``level``: the noise σ on ``first``)."""
    B, T = control.shape[:2]
    x = torch.randn(B, T, RGB, *first.shape[2:], generator=generator).to(first.device)  # CPU noise: the same video on any device
    eps0 = x[:, 0].clone()
    grid = torch.linspace(1.0, 0.0, steps + 1)
    for k in range(steps):
        s, s_next = float(grid[k]), float(grid[k + 1])
        x[:, 0] = (1 - s) * first + s * eps0  # the given frame, noised to this level
        v = model(x, control, first, torch.full((B,), s, device=first.device), refs, level)
        x = x + (s_next - s) * v
    x[:, 0] = first
    return x.clamp(-1.0, 1.0)
