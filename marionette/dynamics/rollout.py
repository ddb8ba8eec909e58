"""Autoregressive rollouts of a trained dynamics model, with forced tokens, scripted roots and the bridge's rules.

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

import argparse
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette import geometry as geo
from marionette.bridge.rules import RULES, RuleParams, Rules, enabled_rules
from marionette.checkpoint import latest_checkpoint, load_checkpoint, read_meta
from marionette.corpus import Corpus, as_corpus, fixed_rows, state_table, world_of_rows
from marionette.dynamics.config import DynamicsConfig
from marionette.dynamics.controls import Force, add_rollout_arguments
from marionette.dynamics.data import ActionTokens
from marionette.dynamics.features import compute_terrain_features, relative_of_rows, relative_roots, terrain_features_of
from marionette.dynamics.model import DynamicsModel, Frames
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.state import join_state, split_state
from marionette.io import write_ipc
from marionette.schema import state_schema
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
    from terrain_scan.field import open_stage

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
class _Scene:
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
        self.config = DynamicsConfig.from_json(meta["dynamics_config"])
        self.config.check_layout(self.layout)
        self.normaliser = Normaliser.from_json(meta["normaliser"])
        self.tokens = ActionTokens.from_corpus(self.corpus)
        if meta["vocab"]["hash"] != self.tokens.vocab_hash or tuple(meta["vocab"]["sizes"]) != self.tokens.sizes:
            raise ValueError(f"{self.ckpt}: trained on vocab {meta['vocab']['hash']}, the corpus has {self.tokens.vocab_hash}")
        self.fps = float(meta["train_config"].get("fps", 20.0))
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
        self.scenes: list[_Scene] = []
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
        self.scenes = []
        for b, (rows, p) in enumerate(zip(seeds, per)):
            last = rows.slice(n - 1, 1)
            world = {k: v[0] for k, v in world_of_rows(L, last).items()}
            rules = Rules(L, self.field, RuleParams(fps=self.fps), self.enabled) if self.enabled else None
            if rules is not None:
                world = rules.step(world)  # frame 0 of the rules: taken as given
            self.scenes.append(
                _Scene(
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
        for sc in self.scenes:
            if sc.rules is None:
                sc.rules = Rules(self.layout, self.field, RuleParams(fps=self.fps), wanted)
                sc.rules.step(sc.world)  # the current frame is the rules' first: taken as given
            else:
                sc.rules.enabled = fresh.enabled

    # batch-1 views of the first stream
    state = property(lambda self: self.scenes[0].state)
    world = property(lambda self: self.scenes[0].world)
    quats = property(lambda self: self.scenes[0].quats)
    tok = property(lambda self: self.scenes[0].tok)
    progress = property(lambda self: self.scenes[0].progress)

    def roots_of(self, scene: _Scene) -> np.ndarray:
        return np.stack([scene.world[e.name][0] for e in self.layout.articulated])

    @property
    def roots_world(self) -> np.ndarray:
        """World roots (N, 3) float64 of the first stream's current frame."""
        return self.roots_of(self.scenes[0])

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
        B = len(self.scenes)
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
        prev_roots = {n: np.stack([sc.world[n][0] for sc in self.scenes]) for n in names}  # (B, 3) each
        root_all = out.root[:, 0].float().numpy().astype(np.float64)  # (B, root_dim) normalised
        toks = []
        for b, sc in enumerate(self.scenes):
            if root_override[b] is not None:
                over = np.asarray(root_override[b], np.float64)
                root_all[b] = np.where(np.isfinite(over), nz.normalise_root(np.nan_to_num(over)), root_all[b])
            tok = np.array([self._sample(lg[b, 0], sc.generator) for lg in out.logits], np.int64)
            for i, v in (force_tokens[b] or {}).items():
                tok[i] = int(v)
            toks.append(tok)
        raws = nz.denormalise_root(root_all)  # (B, root_dim) state units
        bodies = np.stack([sc.body_n for sc in self.scenes])  # (B, body_dim) normalised, the current bodies
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
        for b, sc in enumerate(self.scenes):
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
        for b, sc in enumerate(self.scenes):
            tok = toks[b]
            if c.displacement_gate:  # where each action starts: the gate carries nothing there
                changed.append(np.array([tok[i] != sc.tok[i] or i in restart[b] for i in range(len(tok))]))
            frame = {name: w["joints"][b] for name, w in world.items()}
            frames.append(sc.rules.step(frame) if sc.rules is not None else frame)
        R_new = np.stack([world[n]["R"] for n in names], axis=1)  # (B, N, 3, 3)
        q_prev = np.stack([sc.quats for sc in self.scenes])  # (B, N, 4)
        quats = geo.matrix_to_quat(R_new)
        quats = np.where((np.sum(quats * q_prev, axis=-1) < 0)[..., None], -quats, quats)  # sign continuity
        joints = {n: np.stack([f[n] for f in frames]) for n in frames[0]}  # (B, K, 3) each
        states = _state_after(L, prev_roots, joints, geo.quat_to_matrix(quats))  # (B, dim) float32
        roots_c, bodies_c = nz.normalise(*split_state(states, L))
        for b, sc in enumerate(self.scenes):
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


def forced_at(force: Sequence[Force], t: int, names: Sequence[str]) -> tuple[dict[int, int], list[int]]:
    """At predicted frame ``t``: the forced token per entity index, and the entities whose action replays from
    progress 0 although its token is unchanged: a window that starts where a window of the same entity and
    token ends (back-to-back windows play the action twice). A lone window forcing the token already playing
    continues it; one forcing another token restarts at 0 because the token changed."""
    forced, restart = {}, []
    for name, first, end, token in force:
        if int(first) <= t < int(end):
            forced[names.index(name)] = int(token)
            if t == int(first) and any(n == name and int(e) == t and int(k) == int(token) for n, _, e, k in force):
                restart.append(names.index(name))
    return forced, restart


def force_windows(entity: str, tokens: Sequence[int]) -> list[Force]:
    """A token stream (one per predicted frame) as force windows, one per run of equal tokens; token 0
    ("no valid action") is left to the model. Forcing the recorded stream this way is Force-GT."""
    out, k = [], 0
    while k < len(tokens):
        end = k + 1
        while end < len(tokens) and tokens[end] == tokens[k]:
            end += 1
        if tokens[k] != 0:
            out.append((entity, k, end, int(tokens[k])))
        k = end
    return out


def _script_roots(script_root: Any, horizon: int, layout, root_dim: int) -> np.ndarray | None:
    """A (horizon, root_dim) override with NaN = no override, from an array or a dict entity → (horizon, 9)."""
    if script_root is None:
        return None
    if isinstance(script_root, dict):
        out = np.full((horizon, root_dim), np.nan)
        unknown = sorted(set(script_root) - {e.name for e in layout.articulated})
        if unknown:
            raise ValueError(f"script_root: unknown entities {unknown}")
        for i, e in enumerate(layout.articulated):
            if e.name in script_root:
                a = np.asarray(script_root[e.name], np.float64)
                if a.ndim != 2 or a.shape[1] != 9 or len(a) < horizon:
                    raise ValueError(f"script_root[{e.name!r}] has shape {a.shape}; expected ({horizon}, 9) or longer")
                out[:, 9 * i : 9 * i + 9] = a[:horizon]
        return out
    a = np.asarray(script_root, np.float64)
    if a.shape != (horizon, root_dim):
        raise ValueError(f"script_root has shape {a.shape}; expected ({horizon}, {root_dim})")
    return a


def rollout(
    ckpt_dir: Path | str,
    corpus: Corpus | Path | str,
    segment: str,
    seed_frames: int = 64,
    horizon: int = 100,
    temperature: float = 0.0,
    seed: int = 0,
    force: Sequence[Force] = (),
    script_root: Any = None,
    rules: str | Sequence[str] = "auto",
    terrain_field: Any = None,
    start: int = 0,
    cached: bool = True,
    dtype: torch.dtype = torch.float32,
) -> pa.Table:
    """Seed rows + ``horizon`` predicted rows of ``segment`` (corpus state schema, 20 fps, world roots in m).

    The seed is the segment's dynamics frames [start, start + seed_frames). ``force``: (entity, start,
    end, token) with END exclusive, in predicted-frame indices; ``terrain_field`` defaults to the
    segment's scanned stage (None when it was never scanned). ``cached=False`` recomputes each frame
    (``ModelStream``); ``dtype`` is the models' (bfloat16 for the half-precision path)."""
    c = as_corpus(corpus)
    L = c.layout
    if terrain_field is None:
        terrain_field = open_terrain_field(c, segment)
    ro = Rollout(
        ckpt_dir, c, temperature=temperature, seed=seed, rules=rules, terrain_field=terrain_field, cached=cached, dtype=dtype
    )
    view = c.dynamics_segment(segment, ro.fps)
    if seed_frames < 1 or start < 0 or view.num_rows < start + seed_frames:
        raise ValueError(
            f"{c.path}: segment {segment} has {view.num_rows} dynamics frames; a seed of {seed_frames} frames "
            f"from frame {start} does not fit"
        )
    seed_rows = view.slice(start, seed_frames)
    names = [e.name for e in L.articulated]
    for name, first, end, token in force:
        if name not in names:
            raise ValueError(f"force: unknown entity {name!r}; the scene has {names}")
        if not 1 <= int(token) < ro.tokens.sizes[names.index(name)]:
            raise ValueError(
                f"force {name}:{first}:{end}:{token}: token outside 1..{ro.tokens.sizes[names.index(name)] - 1} "
                f"({name}'s vocabulary; 0 is 'no valid action')"
            )
        if not 0 <= int(first) < int(end) or int(first) >= horizon:
            raise ValueError(
                f"force {name}:{first}:{end}:{token}: frames [{first}, {end}) are empty, negative or past the horizon {horizon}"
            )
    scripted = _script_roots(script_root, horizon, L, ro.config.root_dim)
    ro.start(seed_rows)
    states, roots, quats, toks, progs = [], [], [], [], []
    for t in range(horizon):
        forced, restart = forced_at(force, t, names)
        states.append(ro.step(forced, None if scripted is None else scripted[t], restart))
        roots.append(ro.roots_world)
        quats.append(ro.quats.copy())
        toks.append(ro.tok.copy())
        progs.append(ro.progress.copy())
    return rollout_table(
        c,
        ro,
        seed_rows,
        segment,
        seed,
        np.array(states).reshape(horizon, L.dim),
        np.array(roots).reshape(horizon, -1, 3),
        np.array(quats).reshape(horizon, -1, 4),
        np.array(toks).reshape(horizon, -1),
        np.array(progs).reshape(horizon, -1),
    )


def rollout_table(
    c: Corpus,
    ro: Rollout,
    seed_rows: pa.Table,
    segment: str,
    seed: int,
    states: np.ndarray,
    roots: np.ndarray,
    quats: np.ndarray,
    toks: np.ndarray,
    progs: np.ndarray,
    name: str | None = None,
) -> pa.Table:
    """The seed rows and the predicted rows of a rollout as one table (corpus state schema) whose segment is ``name``
    (default ``<segment>-rollout-s<seed>``)."""
    L, h = c.layout, len(states)
    schema = state_schema(L)
    name = name or f"{segment}-rollout-s{seed}"
    last = seed_rows.slice(seed_rows.num_rows - 1, 1).to_pylist()[0]
    step_frames = c.fps / ro.fps

    cols: dict[str, Any] = {
        "segment": name,
        "sample": last["sample"],
        "frame": [int(last["frame"]) + int(round((k + 1) * step_frames)) for k in range(h)],
        "t": float(last["t"]) + (np.arange(h) + 1) / ro.fps,
        "state": states,
    }
    for i, e in enumerate(L.articulated):
        tok = toks[:, i]
        clip = ro.tokens.clip_lengths[i][tok]
        cols[f"{e.name}.type_id"] = [
            int(ro.tokens.type_keys[i][k].split(":")[1]) if k else int(last[f"{e.name}.type_id"]) for k in tok
        ]
        cols[f"{e.name}.action"] = ro.tokens.composites[i][tok]
        frame = np.rint(progs[:, i] * clip)  # a clip's frames are 0 … clip − 1: a state action wraps, an event holds
        frame = np.where(ro.wraps(i, tok), frame % np.maximum(clip, 1), np.minimum(frame, np.maximum(clip - 1, 0)))
        cols[f"{e.name}.motion_frame"] = np.where(tok == 0, -1, frame).astype(np.int32)
        cols[f"{e.name}.hp"] = last[f"{e.name}.hp"]
        cols[f"{e.name}.root_world"] = roots[:, i]
        cols[f"{e.name}.rot_world"] = quats[:, i]
        cols[f"{e.name}.pos_check_m"] = np.full(h, np.nan, np.float32)
    for e in L.attachments:
        cols[f"{e.name}.type_id"] = last[f"{e.name}.type_id"]
    for name_, width in (("camera.K", 4), ("camera.pos", 3), ("camera.rot", 4)):
        cols[name_] = np.full((h, width), np.nan)
    cols["valid"] = True
    predicted = state_table(L, cols, n=h)
    seeded = seed_rows.cast(schema).set_column(0, "segment", pa.array([name] * seed_rows.num_rows))
    return pa.concat_tables([seeded, predicted])


def script_from_args(scripts: Sequence[tuple[str, Any]], horizon: int, fps: float, layout) -> dict[str, np.ndarray] | None:
    """Parsed ``--script-root`` values → the dict form of ``rollout``'s ``script_root`` (entity → (horizon, 9))."""
    if not scripts:
        return None
    names = [e.name for e in layout.articulated]
    out: dict[str, np.ndarray] = {}
    for name, spec in scripts:
        if name not in names:
            raise ValueError(f"--script-root: unknown entity {name!r}; the scene has {names}")
        arr = out.setdefault(name, np.full((horizon, 9), np.nan))
        if isinstance(spec, Path):
            a = np.load(spec, allow_pickle=False)
            if a.ndim != 2 or a.shape[1] != 9 or len(a) < horizon:
                raise ValueError(f"{spec}: a root script is ({horizon}, 9) or longer (E.root then E.rot6d), not {a.shape}")
            arr[:] = np.where(np.isfinite(a[:horizon]), a[:horizon], arr)
        else:
            start, end, velocity = spec
            if not 0 <= start < end or start >= horizon:
                raise ValueError(
                    f"--script-root {name}: frames [{start}, {end}) are empty, negative or past the horizon {horizon}"
                )
            arr[start : min(end, horizon), 0:3] = np.asarray(velocity) / fps  # metres per model frame
    return out


def write_rollout(
    ckpt: Path,
    corpus: Corpus | Path,
    segment: str,
    out: Path,
    *,
    horizon: int,
    seed_frames: int = 64,
    temperature: float = 0.0,
    seed: int = 0,
    force: Sequence = (),
    script_root: Sequence = (),
    rules: str = "auto",
    render: Path | None = None,
    size: tuple[int, int] = (352, 640),
    log=print,
) -> pa.Table:
    """The rollout command: roll ``horizon`` frames out from ``segment``, write the table to ``out`` (and render it
    through the follow camera to ``render``); ``force`` and ``script_root`` as ``add_arguments`` parses them, ``rules``
    "auto", "none" or a comma list."""
    rules_in = rules if rules in ("auto", "none") else tuple(r for r in rules.split(",") if r)
    trained = read_meta(checkpoint_dir(ckpt))["train_config"]
    c = as_corpus(corpus, trained.get("scene"))
    fps = float(trained.get("fps", 20.0))
    script = script_from_args(list(script_root), horizon, fps, c.layout)
    started = time.perf_counter()
    table = rollout(ckpt, c, segment, seed_frames, horizon, temperature, seed, list(force), script_root=script, rules=rules_in)
    took = time.perf_counter() - started
    write_ipc(out, table)
    log(f"{out}: {table.num_rows} rows ({horizon} predicted, {horizon / took:.0f} frames/s incl. loading)")
    if render is not None:
        from marionette.bridge.targets import TerrainScene, render_rows

        meta = render_rows(
            c.layout, table, render, TerrainScene.of_stage(segment_terrain(c, segment)), camera="follow", size=size
        )
        log(f"{render}: {meta.width}×{meta.height} at {meta.fps:g} fps (follow camera)")
    return table


ARGUMENTS = (
    "ckpt",
    "corpus",
    "segment",
    "out",
    "horizon",
    "seed_frames",
    "temperature",
    "seed",
    "force",
    "script_root",
    "rules",
    "render",
    "size",
)


def main(argv: list[str] | None = None) -> pa.Table:
    """``python -m marionette.dynamics.rollout DIR CORPUS --segment ID --horizon N --out STATES.arrow [...]``."""
    ap = argparse.ArgumentParser(prog="python -m marionette.dynamics.rollout", description=__doc__.splitlines()[0])
    add_rollout_arguments(ap)
    parsed = vars(ap.parse_args(argv))
    return write_rollout(**{k: parsed[k] for k in ARGUMENTS})


if __name__ == "__main__":
    main()
