"""The rollout engine: a trained dynamics model stepped one frame at a time, with forced tokens, scripted roots and
the bridge's rules in the loop (``Rollout``; ``rollout.rollout`` runs it over a horizon).

A rollout is seeded with the first ``seed_frames`` rows of a segment's dynamics view (20 fps): they
are fed, one frame at a time, through ActionGPT's and PoseGPT's ``step`` to fill the KV caches. Then,
per predicted frame t = 0, 1, ... (counted from the first frame after the seed):

1. ActionGPT's output of the previous frame gives the next root stream and per-entity logits; tokens
   are sampled at ``temperature`` from one ``torch.Generator`` seeded by ``seed`` (temperature 0:
   argmax, deterministic). Token 0 ("no valid action", never a training target) is not sampled.
2. ``force`` entries (entity, start, end, token) replace the token for start ≤ t < end (END exclusive).
3. Progress: an unchanged token advances by (source fps / model fps) / clip length, i.e. 1.5 clip
   frames per 20 fps step (docs/architecture.md); a "state" action wraps to [0, 1), an "event" holds at
   1. A changed token restarts at 0. Forcing the token already playing is an unchanged token: it
   continues (so forcing the recorded stream, Force-GT, keeps the recording's progress); only a window
   that starts where a window of the same token ends replays it from 0 (``forced_at``).
4. ``root_override`` (the scripted root, state units) replaces root-stream channels where it is finite;
   nothing else changes.
5. PoseGPT reads the current body and the (possibly overridden) tokens and root of the frame being
   animated and gives the next body; root + body are joined and denormalised.
6. The new state becomes world skeletons (its root integrated from the previous world root), the rules
   (``bridge.rules.Rules``, at the model's fps) correct them, and the state is re-derived from the
   corrected skeletons (``geometry.world_to_state``); that corrected frame is what ActionGPT reads next.

Terrain features (for entities whose switch is on) are re-derived each frame with
``features.compute_terrain_features`` from the corrected world state. PoseGPT reads the terrain of the frame
being animated before that frame's body exists, so its features there are computed from the predicted
root with the previous frame's root-local body (an approximation; ActionGPT reads exact ones).
The relative feature (``relative_position`` models) is re-derived the same way: from the corrected world
roots for ActionGPT, from the predicted roots for PoseGPT.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette import geometry as geo
from marionette.bridge.rules import RULES, RuleParams, Rules, enabled_rules
from marionette.checkpoint import latest_checkpoint, load_checkpoint, read_config, read_meta
from marionette.corpus import MODEL_FPS, Corpus, as_corpus, fixed_rows, world_of_rows
from marionette.dynamics.config import DynamicsConfig
from marionette.dynamics.data import ActionTokens
from marionette.dynamics.features import compute_terrain_features, relative_of_rows, relative_roots, terrain_features_of
from marionette.dynamics.model import DynamicsModel, Frames
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.state import join_state, split_state
from terrain_scan.field import open_stage
from terrain_scan.store import segment_terrain


def checkpoint_dir(ckpt: Path | str) -> Path:
    """A checkpoint directory itself, or the newest one under a training output directory."""
    p = Path(ckpt)
    if (p / "meta.json").exists():
        return p
    found = latest_checkpoint(p)
    if found is None:
        raise FileNotFoundError(f"{p}: neither a checkpoint nor a training directory with a 'latest' checkpoint")
    return found


def open_terrain_field(corpus: Corpus, segment: str):
    """The segment's stage as a ``LayeredField``, or None when the stage was never scanned."""

    stage = segment_terrain(corpus, segment)
    return open_stage(stage.dir) if stage is not None else None


class ModelStream:
    """One of the two models fed one frame at a time: through its sliding-window KV cache, or, with
    ``cached=False``, by recomputing ``forward`` over the frames that can still reach the newest one
    (the last layers·(window − 1) + 1: a layer-l output sees l·(window − 1) frames back), which gives
    the cached result up to float rounding at a cost that grows with the window."""

    def __init__(self, model: Any, cached: bool = True) -> None:
        self.model, self.cached = model, cached
        self.reach = model.spec.layers * (model.config.window - 1) + 1
        self.reset(1)

    def reset(self, batch: int) -> None:
        self.cache = self.model.cache_empty(batch)
        self.history: list[Frames] = []

    def step(self, frames: Frames) -> Any:
        if self.cached:
            out, self.cache = self.model.step(frames, self.cache)
            return out
        self.history = [*self.history[-(self.reach - 1) :], frames] if self.reach > 1 else [frames]
        out = self.model(_concat(self.history))
        if isinstance(out, torch.Tensor):
            return out[:, -1:]
        return type(out)(root=out.root[:, -1:], logits=tuple(lg[:, -1:] for lg in out.logits))


def _concat(frames: Sequence[Frames]) -> Frames:
    """Frames joined along time."""
    first = frames[0]
    skip = None
    if any(f.skip is not None for f in frames):  # the seed frames have none: their own root
        skip = torch.cat([f.root if f.skip is None else f.skip for f in frames], dim=1)
    return Frames(
        **{
            k: None if getattr(first, k) is None else torch.cat([getattr(f, k) for f in frames], dim=1)
            for k in ("root", "body", "tokens", "progress", "terrain", "relative", "changed")
        },
        skip=skip,
    )


@dataclass
class StreamFrame:
    """One stream's current frame: state (float64), world joints, root rotations, tokens, progress, its
    rules (stateful: the collider's lift) and its sampler."""

    state: np.ndarray  # (dim,)
    world: dict[str, np.ndarray]  # name → (K, 3) world joints
    quats: np.ndarray  # (N, 4)
    body_n: np.ndarray  # (body_dim,) normalised body the models read
    tok: np.ndarray  # (N,) int64
    progress: np.ndarray  # (N,)
    rules: Rules | None
    generator: torch.Generator


def _stream_seed(seed: int, b: int) -> int:
    """The sampler seed of stream b of a batch: ``seed`` itself for stream 0 (a batch of one is a plain
    rollout), otherwise drawn from SeedSequence([seed, b]) so streams of nearby seeds never coincide."""
    return int(seed) if b == 0 else int(np.random.SeedSequence([int(seed), b]).generate_state(1, np.uint64)[0] >> 1)


class Rollout:
    """A streaming rollout of one checkpoint over one scene: ``start(seed_rows)`` then ``step()`` per frame;
    ``start_batch``/``step_batch`` run B streams through the models as one batch (stream b has its own
    sampler, ``_stream_seed(seed, b)``, and its own rules; all share the terrain field, so the seeds must
    lie on one stage), which is how the rollout benchmark's batch 16 runs."""

    def __init__(
        self,
        ckpt: Path | str,
        corpus: Corpus | Path | str,
        *,
        temperature: float = 0.0,
        seed: int = 0,
        rules: str | Sequence[str] = "auto",
        terrain_field: Any = None,
        cached: bool = True,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.ckpt = checkpoint_dir(ckpt)
        meta = read_meta(self.ckpt)
        self.corpus = as_corpus(corpus, meta["train_config"].get("scene"))  # the scene the model was trained on
        self.layout = self.corpus.layout
        self.config = read_config(self.ckpt, meta, "dynamics_config", DynamicsConfig)
        self.config.check_layout(self.layout)
        self.normaliser = Normaliser.from_json(meta["normaliser"])
        self.tokens = ActionTokens.from_corpus(self.corpus)
        if meta["vocab"]["hash"] != self.tokens.vocab_hash or tuple(meta["vocab"]["sizes"]) != self.tokens.sizes:
            raise ValueError(f"{self.ckpt}: trained on vocab {meta['vocab']['hash']}, the corpus has {self.tokens.vocab_hash}")
        self.fps = float(meta["train_config"].get("fps", MODEL_FPS))
        self.model = DynamicsModel(self.config)
        load_checkpoint(self.ckpt, self.model, restore_rng=False)
        self.model.eval().to(dtype)
        self.dtype = dtype
        self.action_stream = ModelStream(self.model.action, cached)
        self.pose_stream = ModelStream(self.model.pose, cached)
        self.temperature, self.seed = float(temperature), int(seed)
        self.field = terrain_field
        if rules == "auto":
            self.enabled: tuple[str, ...] = enabled_rules(self.layout, terrain_field)
        elif rules == "none" or rules is None:
            self.enabled = ()
        else:
            self.enabled = tuple(rules)
        # per entity, per token: clip frames advanced per model step, and whether the action wraps ("state")
        ratio = self.corpus.fps / self.fps
        self._advance = [ratio / c for c in self.tokens.clip_lengths]
        types = self.corpus.vocab.get("entity_types", {})
        kinds = {(k, a["token"]): a.get("kind") for k in types for a in types[k]["actions"]}
        self._wraps = [
            np.array([kinds.get(self.tokens.type_token(i, t)) == "state" for t in range(self.tokens.sizes[i])])
            for i in range(len(self.tokens.entities))
        ]
        self.streams: list[StreamFrame] = []
        self.t = 0

    # -- features --------------------------------------------------------------------------------

    def _terrain(self, joints_world: dict[str, np.ndarray], R: np.ndarray) -> list[np.ndarray] | list[None]:
        """Terrain features, per stream (N, 132), of world skeletons (name → (B, K, 3)) with root rotations
        (B, N, 3, 3): the whole batch in one call."""
        if not any(self.config.terrain):
            return [None] * len(R)
        return list(terrain_features_of(self.layout, joints_world, R, self.field)[0])

    def _relative(self, roots: np.ndarray, R: np.ndarray) -> np.ndarray | None:
        """The relative feature (N, 3) at world roots (N, 3) and rotations (N, 3, 3), when the model reads it."""
        return relative_roots(roots, R).astype(np.float32) if self.config.relative_position else None

    def _frames(
        self,
        root_n: Sequence,
        body_n: Sequence,
        tokens: Sequence,
        progress: Sequence | None,
        terrain: Sequence | None,
        relative: Sequence | None,
        skip: Sequence | None = None,
        changed: Sequence | None = None,
    ) -> Frames:
        """One frame of B streams (per-stream arrays, or None for an input the model does not read) as Frames (B, 1, ·)."""

        def t(parts: Sequence | None) -> torch.Tensor | None:
            if parts is None or parts[0] is None:
                return None
            return torch.as_tensor(np.stack([np.asarray(p, np.float32) for p in parts])).to(self.dtype)[:, None]

        toks = torch.as_tensor(np.stack([np.asarray(k, np.int64) for k in tokens]))[:, None]
        return Frames(
            root=t(root_n),
            body=t(body_n),
            tokens=toks,
            progress=t(progress),
            terrain=t(terrain),
            relative=t(relative),
            skip=t(skip),
            changed=None if changed is None else torch.as_tensor(np.stack(changed)).bool()[:, None],
        )

    # -- the stream ------------------------------------------------------------------------------

    def start(self, seed_rows: pa.Table) -> None:
        """Fill both caches from dynamics-view rows (corpus state schema) and reset the rules and the sampler."""
        self.start_batch([seed_rows])

    @torch.inference_mode()
    def start_batch(self, seeds: Sequence[pa.Table]) -> None:
        """``start`` for B streams at once; every seed has the same number of rows (the caches share positions)."""
        if not seeds:
            raise ValueError("start_batch needs at least one seed")
        n = seeds[0].num_rows
        if n < 1:
            raise ValueError("a rollout needs at least one seed frame")
        names = [str(t["segment"][0].as_py()) if t.num_rows and "segment" in t.column_names else "?" for t in seeds]
        if any(t.num_rows != n for t in seeds):
            raise ValueError(f"batched seeds need equal lengths, not {dict(zip(names, (t.num_rows for t in seeds)))}")
        known = set(self.corpus.segments["segment"].to_pylist())  # a rollout table's segments are not: nothing to compare
        stages = {seg: self.corpus.segment_row(seg)["stage"] for seg in names if seg in known}
        if len(set(stages.values())) > 1:
            raise ValueError(f"a batch shares one terrain field, but its seeds lie on several stages: {stages}")
        L, nz = self.layout, self.normaliser
        per = []  # per stream: (root_n, body_n, tokens, progress, terrain, relative), each (n, ...)
        for rows in seeds:
            state = fixed_rows(rows["state"], L.dim).astype(np.float32)
            root, body = split_state(state, L)
            root_n, body_n = nz.normalise(root, body)
            tokens, progress = self.tokens.encode(L, rows, where=str(self.corpus.path))
            terrain = compute_terrain_features(L, rows, self.field)[0] if any(self.config.terrain) else [None] * n
            rel = relative_of_rows(L, rows) if self.config.relative_position else [None] * n
            per.append((root_n, body_n, tokens, progress, terrain, rel, state))
        B = len(seeds)
        self.action_stream.reset(B)
        self.pose_stream.reset(B)
        col = lambda j, k: [p[j][k] for p in per]  # noqa: E731  field j of frame k, per stream
        # the gate's: where each seed action starts, as ActionGPT derives it from a window's tokens in training
        starts = [np.concatenate([np.zeros((1, len(p[2][0])), bool), p[2][1:] != p[2][:-1]]) for p in per]
        for k in range(n):
            seen = [x[k] for x in starts] if self.config.displacement_gate else None
            out = self.action_stream.step(
                self._frames(col(0, k), col(1, k), col(2, k), col(3, k), col(4, k), col(5, k), changed=seen)
            )
            if k + 1 < n:  # PoseGPT step k animates frame k + 1 from body k
                prog = col(3, k + 1) if self.config.pose_progress else None
                self.pose_stream.step(self._frames(col(0, k + 1), col(1, k), col(2, k + 1), prog, col(4, k + 1), col(5, k + 1)))
        self._out = out
        self.streams = []
        for b, (rows, p) in enumerate(zip(seeds, per)):
            last = rows.slice(n - 1, 1)
            world = {k: v[0] for k, v in world_of_rows(L, last).items()}
            rules = Rules(L, self.field, RuleParams(fps=self.fps), self.enabled) if self.enabled else None
            if rules is not None:
                world = rules.step(world)  # frame 0 of the rules: taken as given
            self.streams.append(
                StreamFrame(
                    state=p[6][-1].astype(np.float64),
                    world=world,
                    quats=np.stack([fixed_rows(last[f"{e.name}.rot_world"], 4)[0] for e in L.articulated]),
                    body_n=p[1][-1],
                    tok=p[2][-1].copy(),
                    progress=p[3][-1].astype(np.float64),
                    rules=rules,
                    generator=torch.Generator().manual_seed(_stream_seed(self.seed, b)),
                )
            )
        self.t = 0

    def set_rules(self, enabled: Sequence[str]) -> None:
        """Switch rules on or off mid-rollout, for every stream (a rule switched on starts from the current frame; the
        collider needs the terrain field, the cap two articulated entities: ``Rules`` says which is missing)."""
        wanted = tuple(r for r in RULES if r in set(enabled))
        if unknown := set(enabled) - set(RULES):
            raise ValueError(f"unknown rules {sorted(unknown)}; known: {list(RULES)}")
        fresh = Rules(self.layout, self.field, RuleParams(fps=self.fps), wanted)  # checks what the rules need
        self.enabled = wanted
        for sc in self.streams:
            if sc.rules is None:
                sc.rules = Rules(self.layout, self.field, RuleParams(fps=self.fps), wanted)
                sc.rules.step(sc.world)  # the current frame is the rules' first: taken as given
            else:
                sc.rules.enabled = fresh.enabled

    # batch-1 views of the first stream
    state = property(lambda self: self.streams[0].state)
    world = property(lambda self: self.streams[0].world)
    quats = property(lambda self: self.streams[0].quats)
    tok = property(lambda self: self.streams[0].tok)
    progress = property(lambda self: self.streams[0].progress)

    def roots_of(self, stream: StreamFrame) -> np.ndarray:
        return np.stack([stream.world[e.name][0] for e in self.layout.articulated])

    @property
    def roots_world(self) -> np.ndarray:
        """World roots (N, 3) float64 of the first stream's current frame."""
        return self.roots_of(self.streams[0])

    def wraps(self, entity: int, tokens: np.ndarray) -> np.ndarray:
        """Per token of ``entity`` (entity index): whether its action is a "state" (progress wraps) or not (holds at 1)."""
        return self._wraps[entity][tokens]

    def _sample(self, logits: torch.Tensor, generator: torch.Generator) -> int:
        lg = logits.reshape(-1).double().clone()
        if lg.numel() > 1:
            lg[0] = -torch.inf
        if self.temperature <= 0:
            return int(lg.argmax())
        p = torch.softmax(lg / self.temperature, dim=-1)
        return int(torch.multinomial(p, 1, generator=generator))

    def step(
        self, force_tokens: dict[int, int] | None = None, root_override: np.ndarray | None = None, restart: Sequence[int] = ()
    ) -> np.ndarray:
        """Predict, correct and return the next state row (dim,) float32.

        ``force_tokens``: entity index → token for this frame; ``restart``: entity indices whose progress
        restarts even if the token is unchanged (a replayed action, ``forced_at``); ``root_override``: root
        stream (root_dim,) in state units, NaN = the model's value."""
        return self.step_batch([force_tokens], [root_override], [restart])[0]

    @torch.inference_mode()
    def step_batch(
        self,
        force_tokens: Sequence[dict[int, int] | None] | None = None,
        root_override: Sequence[np.ndarray | None] | None = None,
        restart: Sequence[Sequence[int]] | None = None,
    ) -> np.ndarray:
        """``step`` for every stream: per-stream controls (or None), the next state rows (B, dim) float32."""
        L, c, nz = self.layout, self.config, self.normaliser
        B = len(self.streams)
        force_tokens = [None] * B if force_tokens is None else list(force_tokens)
        root_override = [None] * B if root_override is None else list(root_override)
        restart = [()] * B if restart is None else list(restart)
        if not len(force_tokens) == len(root_override) == len(restart) == B:
            raise ValueError(
                f"step_batch: {B} streams but {len(force_tokens)} force, {len(root_override)} root and "
                f"{len(restart)} restart entries"
            )
        out = self._out
        names = [e.name for e in L.articulated]
        prev_roots = {n: np.stack([sc.world[n][0] for sc in self.streams]) for n in names}  # (B, 3) each
        root_all = out.root[:, 0].float().numpy().astype(np.float64)  # (B, root_dim) normalised
        toks = []
        for b, sc in enumerate(self.streams):
            if root_override[b] is not None:
                over = np.asarray(root_override[b], np.float64)
                root_all[b] = np.where(np.isfinite(over), nz.normalise_root(np.nan_to_num(over)), root_all[b])
            tok = np.array([self._sample(lg[b, 0], sc.generator) for lg in out.logits], np.int64)
            for i, v in (force_tokens[b] or {}).items():
                tok[i] = int(v)
            toks.append(tok)
        raws = nz.denormalise_root(root_all)  # (B, root_dim) state units
        bodies = np.stack([sc.body_n for sc in self.streams])  # (B, body_dim) normalised, the current bodies
        terrains: list = [None] * B
        relatives: list = [None] * B
        if any(c.terrain) or c.relative_position:  # the frame being animated: predicted root, current body
            guess = join_state(raws, nz.denormalise_body(bodies.astype(np.float64)), L)
            gw = _world_after(L, guess, prev_roots)
            roots_g = np.stack([gw[n]["joints"][:, 0] for n in names], axis=1)  # (B, N, 3)
            R_g = np.stack([gw[n]["R"] for n in names], axis=1)  # (B, N, 3, 3)
            terrains = self._terrain({n: gw[n]["joints"] for n in names}, R_g)
            relatives = [self._relative(r, R) for r, R in zip(roots_g, R_g)]
        progs = []  # each stream's progress at the new frame: a new, forced or replayed token restarts at 0
        for b, sc in enumerate(self.streams):
            prog = np.zeros(len(toks[b]))
            for i, tok in enumerate(toks[b]):
                if tok != 0 and tok == sc.tok[i] and i not in restart[b]:
                    p = sc.progress[i] + self._advance[i][tok]
                    prog[i] = p % 1.0 if self._wraps[i][tok] else min(p, 1.0)
            progs.append(prog)
        # PoseGPT animates the new frames from the current bodies (and, with pose_progress, where in its clip each is)
        pose_in = self._frames(root_all, bodies, toks, progs if c.pose_progress else None, terrains, relatives)
        body_n = self.pose_stream.step(pose_in)
        new = join_state(raws, nz.denormalise_body(body_n[:, 0].float().numpy().astype(np.float64)), L)
        # world skeletons, the rules (per stream: they hold state), and the state re-derived from the corrected skeletons
        world = _world_after(L, new, prev_roots)
        frames, changed = [], []
        for b, sc in enumerate(self.streams):
            tok = toks[b]
            if c.displacement_gate:  # where each action starts: the gate carries nothing there
                changed.append(np.array([tok[i] != sc.tok[i] or i in restart[b] for i in range(len(tok))]))
            frame = {name: w["joints"][b] for name, w in world.items()}
            frames.append(sc.rules.step(frame) if sc.rules is not None else frame)
        R_new = np.stack([world[n]["R"] for n in names], axis=1)  # (B, N, 3, 3)
        q_prev = np.stack([sc.quats for sc in self.streams])  # (B, N, 4)
        quats = geo.matrix_to_quat(R_new)
        quats = np.where((np.sum(quats * q_prev, axis=-1) < 0)[..., None], -quats, quats)  # sign continuity
        joints = {n: np.stack([f[n] for f in frames]) for n in frames[0]}  # (B, K, 3) each
        states = _state_after(L, prev_roots, joints, geo.quat_to_matrix(quats))  # (B, dim) float32
        roots_c, bodies_c = nz.normalise(*split_state(states, L))
        for b, sc in enumerate(self.streams):
            sc.state, sc.world, sc.quats, sc.tok, sc.progress = (
                states[b].astype(np.float64),
                frames[b],
                quats[b],
                toks[b],
                progs[b],
            )
            sc.body_n = bodies_c[b]
        roots_w = np.stack([joints[n][:, 0] for n in names], axis=1)  # (B, N, 3)
        terrains = self._terrain(joints, geo.quat_to_matrix(quats))
        relatives = [self._relative(r, geo.quat_to_matrix(q)) for r, q in zip(roots_w, quats)]
        # ActionGPT reads the corrected frames
        # (its displacement gate carries over the proposed root stream, not the rules' corrections of it, and nothing
        # where an action starts: a new, forced or replayed token)
        skip = root_all if c.displacement_gate else None
        self._out = self.action_stream.step(
            self._frames(roots_c, bodies_c, toks, progs, terrains, relatives, skip, changed or None)
        )
        self.t += 1
        return states


def _world_after(layout, states: np.ndarray, prev_roots: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """World skeletons of one new state row per stream (B, dim): per entity "joints" (B, K, 3) and "R"
    (B, 3, 3), each root advanced from ``prev_roots[name]`` (B, 3) by x = x_prev + R δ in float64
    (``geometry.state_to_world``'s integration, one step, for the whole batch at once)."""
    s = np.asarray(states, np.float64)
    B = len(s)
    out: dict[str, dict[str, np.ndarray]] = {}
    for e in layout.articulated:
        R = geo.rot6d_to_matrix(s[:, layout.slice(f"{e.name}.rot6d")])
        root = prev_roots[e.name] + np.einsum("bij,bj->bi", R, s[:, layout.slice(f"{e.name}.root")])
        local = s[:, layout.slice(f"{e.name}.joints")].reshape(B, e.rig.n_keep - 1, 3)
        out[e.name] = {"joints": np.concatenate([root[:, None, :], geo.to_world(local, root, R)], axis=1), "R": R}
    for e in layout.attachments:
        owner = out[e.owner]
        local = s[:, layout.slice(f"{e.name}.points")].reshape(B, e.rig.n_keep, 3)
        out[e.name] = {"joints": geo.to_world(local, owner["joints"][:, 0], owner["R"]), "R": owner["R"]}
    return out


def _state_after(layout, prev_roots: dict[str, np.ndarray], joints: dict[str, np.ndarray], R: np.ndarray) -> np.ndarray:
    """State rows (B, dim) float32 of one new world frame per stream (``geometry.world_to_state``, one step):
    root displacement Rᵀ (x − x_prev), root-local joints and points, 6D rotation; ``R`` (B, N, 3, 3)."""
    B = len(R)
    state = np.zeros((B, layout.dim), np.float64)
    frames = {}
    for i, e in enumerate(layout.articulated):
        X, Ri = np.asarray(joints[e.name], np.float64), R[:, i]
        root = X[:, 0]
        frames[e.name] = (root, Ri)
        state[:, layout.slice(f"{e.name}.root")] = np.einsum("bji,bj->bi", Ri, root - prev_roots[e.name])
        state[:, layout.slice(f"{e.name}.joints")] = geo.to_local(X[:, 1:], root, Ri).reshape(B, -1)
        state[:, layout.slice(f"{e.name}.rot6d")] = geo.matrix_to_rot6d(Ri)
    for e in layout.attachments:
        root, Ri = frames[e.owner]
        state[:, layout.slice(f"{e.name}.points")] = geo.to_local(joints[e.name], root, Ri).reshape(B, -1)
    return state.astype(np.float32)
