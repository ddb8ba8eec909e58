"""The dynamics model: ActionGPT (root motion and next actions) and PoseGPT (the next body pose).

Both are causal transformers over frames, shaped like nanoGPT: pre-norm blocks (LayerNorm),
multi-head self-attention with rotary position embeddings (RoPE, base 10000) on queries and keys,
a 4× GELU MLP. Each frame enters as a concatenation of named features projected to the width, and
linear heads read the predictions out. Sizes come from the scene layout and the action vocabularies;
nothing here knows the duel scene.

The state vector splits, from the layout, into

- the **root stream** (``root_dim`` = 9 per articulated entity): for every articulated entity in
  layout order its root displacement ``E.root`` (3, its local frame), then its ``E.rot6d`` (6);
- the **body state** (``body_dim``): everything else, in state order: every articulated entity's
  root-local ``E.joints``, then every attachment's ``points``. The attachments' points (the weapon
  sub-state ActionGPT reads) are the body's tail, ``body[..., config.weapon[0]:config.weapon[1]]``.

Alignment, for training on a window of frames x[0..T] (``action_training_pair``, ``pose_training_pair``):

- ActionGPT step t reads root[t], tokens[t], progress[t], weapon[t] (from body[t]), terrain[t] and
  relative[t], and with ``clip_frames`` each entity's time left in its event at t (``ActionGPT.time_left``:
  seconds, capped at 4, and the inverse of the source frames left, 1 on an event's last frame: a sharp
  signal of the frame an event ends, which progress alone, 1.5/clip length per model frame, is not);
  it predicts root[t+1] and the logits of tokens[t+1]. With ``events_end``, where an entity's current token is an
  event with at most source_fps / model_fps source frames left, (1 − progress[t]) · clip length ≤ 1.5, the next
  token cannot be the same (by the vocab's definition an event's motion_frame never wraps; the train split is
  checked, ``data.ended_events``): that logit is −inf, so the model names what follows where copy-last cannot.
- PoseGPT step t reads body[t] and the conditions of the frame being animated: tokens[t+1] (the
  caller's, possibly overridden), root[t+1] (likewise), terrain[t+1] and relative[t+1], and with
  ``pose_progress`` the progress[t+1] of each token there (a rollout's: it restarts at 0 where a token is
  forced); it predicts body[t+1].

Heads: anchored, gated or residual, as ``config.DynamicsConfig`` switches them (its docstring defines each).
Inputs are expected normalised by the caller.

Attention window and streaming. ``forward`` over T frames lets frame i attend to frames
max(0, i − window + 1)..i (plain causal attention when T ≤ window, a band mask beyond). ``step``
feeds one frame and keeps at most ``window`` keys and values per layer, the keys stored already
rotated at their absolute positions, in ring buffers (no copy of the window per frame). A RoPE score
depends only on the difference of positions (the angles are computed in float64, so far positions
lose nothing), so ``step`` at frame t equals
``forward`` over the whole stream at frame t, up to float rounding. For a one-layer model that is
also ``forward`` over the last ``window`` frames alone, positions restarting at 0. With more layers it
is not: a cached key of layer l ≥ 2 was computed when its frame was newest, from that frame's own
window, so a stream's receptive field reaches L·(window − 1) frames back while a recomputed window
sees only ``window`` frames. Exact window recomputation costs a full ``forward`` per frame.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from marionette.dynamics.config import N_TOKEN_CLASSES, ROOT_PER_ENTITY, DynamicsConfig, TransformerSpec

ROPE_BASE = 10000.0


# -- inputs, outputs, cache --------------------------------------------------------------------------


@dataclass
class Frames:
    """Per-frame inputs, batch first (B, T, ...), N articulated entities in config order.

    ``root`` (B, T, root_dim) and ``body`` (B, T, body_dim) float; ``tokens`` (B, T, N) int64;
    ``progress`` (B, T, N) in [0, 1] (ActionGPT only); ``terrain`` (B, T, N, terrain_features), read
    only for entities whose terrain switch is on; ``relative`` (B, T, N, 3), read only when
    ``relative_position`` is on; ``skip`` (B, T, root_dim), what ActionGPT's displacement gate carries
    over (a rollout's own proposal before the rules), ``root`` when None; ``changed`` (B, T, N) bool, whether
    each entity's action starts at the frame (the gate carries nothing there), when None derived from
    ``tokens`` (a token unlike the frame before; never at the first frame)."""

    root: Tensor
    body: Tensor
    tokens: Tensor
    progress: Tensor | None = None
    terrain: Tensor | None = None
    relative: Tensor | None = None
    skip: Tensor | None = None
    changed: Tensor | None = None

    def time_slice(self, start: int | None = None, stop: int | None = None) -> Frames:
        """The frames [start, stop) of every input."""
        return Frames(**{f.name: None if (v := getattr(self, f.name)) is None else v[:, start:stop] for f in fields(self)})

    @property
    def length(self) -> int:
        return self.root.shape[1]


@dataclass
class ActionOutputs:
    """ActionGPT's predictions per frame: the next root stream (B, T, root_dim) and per entity the
    logits (B, T, vocab) of its next action token; with the displacement gate, ``proposal`` is the root head's own
    prediction (B, T, root_dim) before the gate blends the carried displacement in (None without the gate)."""

    root: Tensor
    logits: tuple[Tensor, ...]
    proposal: Tensor | None = None


@dataclass(frozen=True)
class KVCache:
    """Per layer, ring buffers (B, heads, window, head_dim) of the keys and values of the last ≤ window
    frames, keys rotated at their absolute positions; ``position`` is the absolute index of the next
    frame and ``count`` the frames written so far (frame k sits in slot k mod window).

    ``step`` writes into the buffers in place and returns a cache sharing them: an older cache object
    of the same stream sees the new frames. Fork a stream with ``clone()``. Attention is a sum over
    keys, so their slot order does not matter; a ring buffer avoids copying the window every frame."""

    keys: tuple[Tensor, ...]
    values: tuple[Tensor, ...]
    position: int
    count: int = 0

    @property
    def length(self) -> int:
        """Frames held: min(count, window)."""
        return min(self.count, self.keys[0].shape[2]) if self.keys else 0

    def clone(self) -> KVCache:
        """A copy with its own buffers."""
        return KVCache(tuple(k.clone() for k in self.keys), tuple(v.clone() for v in self.values), self.position, self.count)


def action_training_pair(frames: Frames) -> tuple[Frames, tuple[Tensor, Tensor]]:
    """ActionGPT inputs x[0..T−1] and targets (root[1..T], tokens[1..T]) from a window x[0..T]."""
    return frames.time_slice(None, -1), (frames.root[:, 1:], frames.tokens[:, 1:])


def pose_training_pair(frames: Frames) -> tuple[Frames, Tensor]:
    """PoseGPT inputs and target body[1..T] from a window x[0..T]: step t reads body[t] and the
    tokens, progress (read with ``pose_progress``), root, terrain and relative features of frame t+1."""
    nxt = frames.time_slice(1, None)
    return replace(nxt, body=frames.body[:, :-1]), frames.body[:, 1:]


# -- the transformer ---------------------------------------------------------------------------------


def rope_angles(positions: Tensor, head_dim: int) -> tuple[Tensor, Tensor]:
    """cos and sin (T, head_dim/2) of the RoPE angles p·base^(−2i/head_dim), computed in float64."""
    inv_freq = ROPE_BASE ** (-torch.arange(0, head_dim, 2, dtype=torch.float64, device=positions.device) / head_dim)
    angles = positions.to(torch.float64)[:, None] * inv_freq[None, :]
    return angles.cos().float(), angles.sin().float()


def apply_rope(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """Rotate (B, H, T, head_dim) by the angles of its T positions; dims i and i + head_dim/2 form a pair."""
    x1, x2 = x.float().chunk(2, dim=-1)  # (B, H, T, hd/2) each, rotated in float32
    return torch.cat([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1).to(x.dtype)


class SelfAttention(nn.Module):
    def __init__(self, spec: TransformerSpec, dropout: float) -> None:
        super().__init__()
        self.heads, self.dropout = spec.heads, dropout
        self.qkv = nn.Linear(spec.width, 3 * spec.width, bias=False)
        self.out = nn.Linear(spec.width, spec.width, bias=False)

    def forward(
        self,
        x: Tensor,
        cos: Tensor,
        sin: Tensor,
        ring: tuple[Tensor, Tensor, int, int] | None = None,
        mask: Tensor | None = None,
    ) -> Tensor:
        """``ring`` = (key buffer, value buffer, slot, filled): one new frame is written at ``slot`` and
        attends to the ``filled`` frames the buffers then hold (itself included)."""
        B, T, C = x.shape
        q, k, v = self.qkv(x).split(C, dim=-1)
        q, k, v = (t.view(B, T, self.heads, C // self.heads).transpose(1, 2) for t in (q, k, v))  # (B, nh, T, hs)
        q, k = apply_rope(q, cos, sin), apply_rope(k, cos, sin)
        if ring is not None:  # one new frame after the cached ones: it may see them all
            kbuf, vbuf, slot, filled = ring
            kbuf[:, :, slot] = k[:, :, 0].to(kbuf.dtype)
            vbuf[:, :, slot] = v[:, :, 0].to(vbuf.dtype)
            k, v = kbuf[:, :, :filled].to(q.dtype), vbuf[:, :, :filled].to(q.dtype)  # (B, nh, filled, hs)
        y = F.scaled_dot_product_attention(
            q, k, v, attn_mask=mask, is_causal=ring is None and mask is None, dropout_p=self.dropout if self.training else 0.0
        )  # (B, nh, T, hs)
        y = y.transpose(1, 2).reshape(B, T, C)
        return F.dropout(self.out(y), self.dropout, self.training)


class MLP(nn.Module):
    def __init__(self, spec: TransformerSpec, dropout: float) -> None:
        super().__init__()
        self.fc = nn.Linear(spec.width, spec.mlp_ratio * spec.width, bias=False)
        self.proj = nn.Linear(spec.mlp_ratio * spec.width, spec.width, bias=False)
        self.dropout = dropout

    def forward(self, x: Tensor) -> Tensor:
        return F.dropout(self.proj(F.gelu(self.fc(x))), self.dropout, self.training)


class Block(nn.Module):
    def __init__(self, spec: TransformerSpec, dropout: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(spec.width, bias=False)
        self.attn = SelfAttention(spec, dropout)
        self.norm2 = nn.LayerNorm(spec.width, bias=False)
        self.mlp = MLP(spec, dropout)

    def forward(
        self,
        x: Tensor,
        cos: Tensor,
        sin: Tensor,
        ring: tuple[Tensor, Tensor, int, int] | None = None,
        mask: Tensor | None = None,
    ) -> Tensor:
        x = x + self.attn(self.norm1(x), cos, sin, ring, mask)
        return x + self.mlp(self.norm2(x))


class CausalTransformer(nn.Module):
    """Pre-norm blocks with RoPE self-attention over a sliding window of frames."""

    def __init__(self, spec: TransformerSpec, window: int, dropout: float) -> None:
        super().__init__()
        self.spec, self.window = spec, window
        self.blocks = nn.ModuleList(Block(spec, dropout) for _ in range(spec.layers))
        self.norm = nn.LayerNorm(spec.width, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        """(B, T, width) → (B, T, width); frame i sees frames max(0, i − window + 1)..i."""
        length = x.shape[1]
        pos = torch.arange(length, device=x.device)
        cos, sin = rope_angles(pos, self.spec.head_dim)
        mask = None
        if length > self.window:
            lag = pos[:, None] - pos[None, :]  # (T, T) query − key
            mask = (lag >= 0) & (lag < self.window)
        for block in self.blocks:
            x = block(x, cos, sin, mask=mask)
        return self.norm(x)

    def step(self, x: Tensor, cache: KVCache) -> tuple[Tensor, KVCache]:
        """One frame (B, 1, width) at ``cache.position`` → (B, 1, width) and the cache with it written
        (in place: the ring buffers hold the last ``window`` frames, this one included)."""
        if x.shape[1] != 1:
            raise ValueError(f"step takes one frame at a time, not {x.shape[1]}")
        if cache.keys[0].shape[0] != x.shape[0] or cache.keys[0].shape[2] != self.window:
            raise ValueError(f"a cache of {tuple(cache.keys[0].shape)} does not fit batch {x.shape[0]}, window {self.window}")
        cos, sin = rope_angles(torch.tensor([cache.position], device=x.device), self.spec.head_dim)
        slot, filled = cache.count % self.window, min(cache.count + 1, self.window)
        for block, k, v in zip(self.blocks, cache.keys, cache.values, strict=True):
            x = block(x, cos, sin, ring=(k, v, slot, filled))
        return self.norm(x), KVCache(cache.keys, cache.values, cache.position + 1, cache.count + 1)

    def cache_empty(self, batch: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> KVCache:
        """A cache holding no frames (ring buffers of ``window`` slots), the next frame at position 0."""
        shape = (batch, self.spec.heads, self.window, self.spec.head_dim)
        keys = tuple(torch.zeros(shape, device=device, dtype=dtype) for _ in range(self.spec.layers))
        values = tuple(torch.zeros(shape, device=device, dtype=dtype) for _ in range(self.spec.layers))
        return KVCache(keys, values, 0, 0)


# -- the two models ----------------------------------------------------------------------------------


def _terrain_mlp(features: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(features, hidden), nn.GELU(), nn.Linear(hidden, out))


def _generator(seed: int | torch.Generator) -> torch.Generator:
    return seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(int(seed))


class _FrameGPT(nn.Module, ABC):
    """A causal transformer fed by per-frame features; subclasses say which features and which heads."""

    config: DynamicsConfig
    spec: TransformerSpec

    def _materialize(self, seed: int | torch.Generator) -> None:
        """Allocate the parameters (built on the meta device) and draw them from ``seed``'s generator.

        GPT-2 initialisation: N(0, 0.02) in the transformer and heads, scaled by 1/√(2·layers) on the
        residual projections; the feature encoders N(0, 1/fan_in) so unit-scale inputs arrive at unit
        scale; action embeddings N(0, 1), on the scale of the normalised inputs beside them."""
        self.to_empty(device="cpu")
        g = _generator(seed)
        encoders = ("input", "terrain_mlp")
        with torch.no_grad():
            for name, m in self.named_modules():
                if isinstance(m, nn.Linear):
                    if name.startswith(encoders):
                        std = m.in_features**-0.5
                    elif name.endswith(("attn.out", "mlp.proj")):
                        std = 0.02 / math.sqrt(2 * self.spec.layers)
                    else:
                        std = 0.02
                    m.weight.normal_(0.0, std, generator=g)
                    if m.bias is not None:
                        m.bias.zero_()
                elif isinstance(m, nn.Embedding):
                    m.weight.normal_(0.0, 1.0, generator=g)
                elif isinstance(m, nn.LayerNorm):
                    m.weight.fill_(1.0)
                    if m.bias is not None:
                        m.bias.zero_()

    def _zero_heads(self, *heads: nn.Linear) -> None:
        """Zero the output heads, so an untrained model predicts its anchor (module doc: the baselines)."""
        with torch.no_grad():
            for head in heads:
                head.weight.zero_()
                head.bias.zero_()

    def _build_encoders(self, spec: TransformerSpec, config: DynamicsConfig, own_dims: int) -> None:
        c = config
        self.embed = nn.ModuleDict({e: nn.Embedding(v, spec.action_embed) for e, v in zip(c.entities, c.vocab_sizes)})
        if c.token_classes:
            self.class_embed = nn.ModuleDict({e: nn.Embedding(N_TOKEN_CLASSES + 1, spec.action_embed) for e in c.entities})
        self._class_tables: dict[tuple[int, torch.device], Tensor] = {}  # (entity, device) → token → class, built once
        # (config field, device) → per entity: token → clip length, built once
        self._clip_tables: dict[tuple[str, torch.device], list[Tensor]] = {}
        on = [e for e, t in zip(c.entities, c.terrain) if t]
        self.terrain_mlp = nn.ModuleDict({e: _terrain_mlp(c.terrain_features, spec.terrain_hidden, spec.terrain_out) for e in on})
        in_dim = own_dims + c.n_entities * spec.action_embed + len(on) * spec.terrain_out
        in_dim += 3 * c.n_entities if c.relative_position else 0
        self.input = nn.Linear(in_dim, spec.width)
        self.transformer = CausalTransformer(spec, c.window, c.dropout)

    def _shared_features(self, frames: Frames) -> list[Tensor]:
        """Action embeddings, terrain features (entities with terrain on) and relative roots, each (B, T, ·)."""
        c = self.config
        B, T = frames.root.shape[:2]
        if frames.tokens.shape != (B, T, c.n_entities):
            raise ValueError(f"tokens {tuple(frames.tokens.shape)} should be (B, T, {c.n_entities}) = {(B, T, c.n_entities)}")
        feats = [self.embed[e](frames.tokens[..., i]) for i, e in enumerate(c.entities)]
        if c.token_classes:
            for i, e in enumerate(c.entities):
                key = (i, frames.tokens.device)
                if key not in self._class_tables:  # not per call: a rollout runs this every frame
                    self._class_tables[key] = torch.tensor(c.token_classes[i], dtype=torch.long, device=key[1])
                feats[i] = feats[i] + self.class_embed[e](self._class_tables[key][frames.tokens[..., i]])
        if len(self.terrain_mlp):
            if frames.terrain is None:
                raise ValueError(f"terrain features are on for {list(self.terrain_mlp)} but none were given")
            for i, e in enumerate(c.entities):
                if e in self.terrain_mlp:
                    feats.append(self.terrain_mlp[e](frames.terrain[:, :, i]))
        if c.relative_position:
            if frames.relative is None:
                raise ValueError("relative_position is on but no relative roots were given")
            feats.append(frames.relative.reshape(B, T, 3 * c.n_entities))
        return feats

    @abstractmethod
    def features(self, frames: Frames) -> Tensor:
        """The per-frame input features (B, T, in_dim) of this model."""

    @abstractmethod
    def read_out(self, frames: Frames, h: Tensor) -> Any:
        """Predictions from the transformer's output h (B, T, width)."""

    def forward(self, frames: Frames) -> Any:
        """Predictions for every frame of a (B, T) sequence, causally (see the module doc for the window)."""
        return self.read_out(frames, self.transformer(self.input(self.features(frames))))

    def step(self, frames: Frames, cache: KVCache) -> tuple[Any, KVCache]:
        """Predictions for one frame (B, 1, ...) after those in ``cache``, and the cache with it appended."""
        h, cache = self.transformer.step(self.input(self.features(frames)), cache)
        return self.read_out(frames, h), cache

    def cache_empty(self, batch: int) -> KVCache:
        """An empty cache for ``batch`` streams, on this model's device and dtype."""
        p = self.input.weight
        return self.transformer.cache_empty(batch, p.device, p.dtype)


# source frames of float32 progress rounding allowed when an event's frames left are compared with a model step
# (``ActionGPT.ending`` and the train split's check of the rule, ``data.ended_events``)
PLAYED_OUT_SLACK = 1e-3
GATE_INIT = 2.0  # the displacement gate's initial logit: g = 0.88, mostly the current displacement


class ActionGPT(_FrameGPT):
    """Next root stream and next action of every entity, from the root stream, current actions,
    their progress, the weapon sub-state and optional terrain and relative features.

    The logits of entity i's next token are ``head_i(h) + copy_gain[i] · onehot(current token)``: one
    learned scalar per entity lets the model hold the current action and spend the head on when it
    changes. It starts at log(99 (vocab − 1)) and the heads at zero, so an untrained model gives the current
    token 0.99 and predicts copy-last exactly. Actions persist for tens of frames, so copy-last is a strong
    baseline (~0.98 next-token accuracy on the synthetic corpus) that a head alone learns only slowly. With
    ``adaptive_copy`` the gain is ``copy_gain[i] + stay_head(h)[i]`` (the stay head starts at zero)."""

    def __init__(self, config: DynamicsConfig, seed: int | torch.Generator = 0) -> None:
        super().__init__()
        self.config, self.spec = config, config.action_gpt
        c, s = config, config.action_gpt
        with torch.device("meta"):
            # root, progress, weapon, and with clip_frames each entity's time left (2 per entity)
            own = c.root_dim + c.n_entities + c.weapon_dim + (2 * c.n_entities if c.clip_frames else 0)
            self._build_encoders(s, c, own_dims=own)
            self.root_head = nn.Linear(s.width, c.root_dim)
            self.action_heads = nn.ModuleDict({e: nn.Linear(s.width, v) for e, v in zip(c.entities, c.vocab_sizes)})
            self.copy_gain = nn.Parameter(torch.empty(c.n_entities))
            if c.displacement_gate:
                self.gate_head = nn.Linear(s.width, c.root_dim)
            if c.adaptive_copy:
                self.stay_head = nn.Linear(s.width, c.n_entities)
        self._materialize(seed)
        rot6d = [k % ROOT_PER_ENTITY >= 3 for k in range(c.root_dim)]  # per entity: E.root (3) then E.rot6d (6)
        self.register_buffer("rotation_mask", torch.tensor(rot6d, dtype=torch.float32), persistent=False)
        self._zero_heads(self.root_head, *self.action_heads.values())
        if c.adaptive_copy:
            self._zero_heads(self.stay_head)
        if c.displacement_gate:
            self._zero_heads(self.gate_head)
            nn.init.constant_(self.gate_head.bias, GATE_INIT)
        with torch.no_grad():  # initial P(next token = current) = 0.99 (the heads start at 0)
            self.copy_gain.copy_(torch.tensor([math.log(99.0 * (v - 1)) if v > 1 else 0.0 for v in c.vocab_sizes]))

    def features(self, frames: Frames) -> Tensor:
        c = self.config
        if frames.progress is None:
            raise ValueError("ActionGPT reads the actions' progress; frames.progress is None")
        weapon = frames.body[..., c.weapon[0] : c.weapon[1]]
        progress = frames.progress.to(frames.root.dtype)
        left = [self.time_left(frames.tokens, progress)] if c.clip_frames else []
        return torch.cat([frames.root, progress, weapon, *left, *self._shared_features(frames)], dim=-1)

    def _frames_left(self, field: str, tokens: Tensor, progress: Tensor) -> Tensor:
        """(B, T, N) float64: each entity's source frames left in its token by the config's ``field`` (per entity, per
        token: a length, 0 = does not end on its own → inf)."""
        key = (field, tokens.device)
        if key not in self._clip_tables:  # not per call: a rollout runs this every frame
            tables = getattr(self.config, field)
            self._clip_tables[key] = [torch.tensor(t, dtype=torch.float64, device=tokens.device) for t in tables]
        return torch.stack(
            [
                torch.where(table[tokens[..., i]] > 0, (1 - progress[..., i].double()) * table[tokens[..., i]], math.inf)
                for i, table in enumerate(self._clip_tables[key])
            ],
            -1,
        )

    def ending(self, frames: Frames) -> Tensor:
        """(B, T, N) bool: where an entity's event has played out by the next model frame (``events_end``)."""
        c = self.config
        step = c.source_fps / c.model_fps
        return self._frames_left("events_end", frames.tokens, frames.progress) <= step + PLAYED_OUT_SLACK

    def time_left(self, tokens: Tensor, progress: Tensor) -> Tensor:
        """Each entity's time left in its event (B, T, 2N): seconds, (1 − progress) · clip length / source fps capped
        at 4 s, then the inverse of the source frames left (1 on an event's last frame, ½ on the one before, → 0
        early on); a token that does not end on its own (clip length 0: a loop, no action) reads 4 s and 0."""
        c = self.config
        frames_left = self._frames_left("clip_frames", tokens, progress)  # (B, T, N) source frames
        seconds = (frames_left / c.source_fps).clamp(max=4.0)
        inverse = 1.0 / frames_left.clamp(min=1.0)
        return torch.cat([seconds, inverse], -1).to(progress.dtype)

    @staticmethod
    def action_starts(frames: Frames) -> Tensor:
        """(B, T, N) bool: ``frames.changed``, or a token unlike the frame before (not at the first frame)."""
        if frames.changed is not None:
            return frames.changed.bool()
        tok = frames.tokens
        return torch.cat([torch.zeros_like(tok[:, :1], dtype=torch.bool), tok[:, 1:] != tok[:, :-1]], dim=1)

    def read_out(self, frames: Frames, h: Tensor) -> ActionOutputs:
        root = self.root_head(h)  # (B, T, root_dim)
        if self.config.residual:
            root = frames.root + root
        elif self.config.rotation_anchor:
            root = root + self.rotation_mask.to(h.dtype) * frames.root
        proposal = None
        if self.config.displacement_gate:
            # The head is trained on its own (train.losses' "proposal" term) and blended in fixed: the blend's loss
            # trains the gate. Through the blend alone the head learnt with (1 − g) ≈ 0.12 of the gradient on the
            # frames that carry, and was poor where it stands alone, where an action starts (docs/tradeoffs.md).
            proposal = root
            g = torch.sigmoid(self.gate_head(h)) * (1 - self.rotation_mask.to(h.dtype))
            g = g * (~self.action_starts(frames)).to(h.dtype).repeat_interleave(ROOT_PER_ENTITY, dim=-1)
            fixed = root.detach()
            root = fixed + g * ((frames.root if frames.skip is None else frames.skip) - fixed)
        logits = []
        stay = self.stay_head(h) if self.config.adaptive_copy else None  # (B, T, N)
        ending = self.ending(frames) if self.config.events_end else None
        for i, (e, v) in enumerate(zip(self.config.entities, self.config.vocab_sizes)):
            current = F.one_hot(frames.tokens[..., i], v).to(h.dtype)  # (B, T, v)
            gain = self.copy_gain[i].to(h.dtype) + (0.0 if stay is None else stay[..., i : i + 1])
            lg = self.action_heads[e](h) + gain * current
            if ending is not None:  # a played-out event does not go on: its logit is dropped
                lg = lg.masked_fill(ending[..., i : i + 1] & current.bool(), -math.inf)
            logits.append(lg)
        return ActionOutputs(root=root, logits=tuple(logits), proposal=proposal)


class PoseGPT(_FrameGPT):
    """The next body state from the current one and the actions, root stream and terrain of the frame
    being animated (see the module doc for the alignment and for ``body_anchor``'s gain)."""

    def __init__(self, config: DynamicsConfig, seed: int | torch.Generator = 0) -> None:
        super().__init__()
        self.config, self.spec = config, config.pose_gpt
        c, s = config, config.pose_gpt
        with torch.device("meta"):
            self._build_encoders(s, c, own_dims=c.body_dim + c.root_dim + (c.n_entities if c.pose_progress else 0))
            self.body_head = nn.Linear(s.width, c.body_dim)
            if c.body_anchor:
                self.body_gain = nn.Parameter(torch.empty(c.body_dim))
        self._materialize(seed)
        self._zero_heads(self.body_head)
        if c.body_anchor:
            nn.init.ones_(self.body_gain)

    def features(self, frames: Frames) -> Tensor:
        own = [frames.body, frames.root]
        if self.config.pose_progress:
            if frames.progress is None:
                raise ValueError("PoseGPT reads the progress of the frame it animates (pose_progress); frames.progress is None")
            own.append(frames.progress.to(frames.root.dtype))
        return torch.cat([*own, *self._shared_features(frames)], dim=-1)

    def read_out(self, frames: Frames, h: Tensor) -> Tensor:
        body = self.body_head(h)  # (B, T, body_dim)
        if self.config.body_anchor:
            return self.body_gain.to(h.dtype) * frames.body + body
        return frames.body + body if self.config.residual else body


class DynamicsModel(nn.Module):
    """ActionGPT and PoseGPT of one config, their parameters drawn from one seeded generator."""

    def __init__(self, config: DynamicsConfig, seed: int = 0) -> None:
        super().__init__()
        self.config = config
        g = _generator(seed)
        self.action = ActionGPT(config, g)
        self.pose = PoseGPT(config, g)


def parameter_counts(model: DynamicsModel) -> dict[str, int]:
    """Parameters of ActionGPT, PoseGPT and both."""
    a = sum(p.numel() for p in model.action.parameters())
    p = sum(p.numel() for p in model.pose.parameters())
    return {"ActionGPT": a, "PoseGPT": p, "total": a + p}
