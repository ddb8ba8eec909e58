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
   1. A changed token, or the first frame of a force window, restarts at 0.
4. ``root_override`` (the scripted root, state units) replaces root-stream channels where it is finite;
   nothing else changes.
5. PoseGPT reads the current body and the (possibly overridden) tokens and root of the frame being
   animated and gives the next body; root + body are joined and denormalised.
6. The new state becomes world skeletons (its root integrated from the previous world root), the rules
   (``bridge.rules.Rules``, at the model's fps) correct them, and the state is re-derived from the
   corrected skeletons (``geometry.world_to_state``); that corrected frame is what ActionGPT reads next.

Terrain features (for entities whose switch is on) are re-derived each frame with
``data.compute_terrain_features`` from the corrected world state. PoseGPT reads the terrain of the frame
being animated before that frame's body exists, so its features there are computed from the predicted
root with the previous frame's root-local body (an approximation; ActionGPT reads exact ones).
The relative feature (``relative_position`` models) is re-derived the same way: from the corrected world
roots for ActionGPT, from the predicted roots for PoseGPT.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette import geometry as geo
from marionette.bridge.rules import RULES, RuleParams, Rules, enabled_rules
from marionette.corpus import Corpus, _fixed, world_of_rows
from marionette.dynamics.checkpoint import latest_checkpoint, load_checkpoint, read_meta
from marionette.dynamics.data import (
    ActionTokens,
    Normaliser,
    _as_corpus,
    compute_terrain_features,
    relative_of_rows,
    relative_roots,
)
from marionette.dynamics.model import DynamicsConfig, DynamicsModel, Frames, join_state, split_state
from marionette.io import write_ipc
from marionette.schema import state_schema

Force = tuple[str, int, int, int]  # (entity, start, end exclusive, token), predicted-frame indices


def _checkpoint_dir(ckpt: Path | str) -> Path:
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
    from terrain_scan.scan import stage_dir

    d = stage_dir(corpus.path, corpus.segment_row(segment)["stage"])
    return open_stage(d) if (d / "manifest.json").exists() and any((d / "chunks").glob("*")) else None


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
    return Frames(**{k: None if getattr(first, k) is None else torch.cat([getattr(f, k) for f in frames], dim=1)
                     for k in ("root", "body", "tokens", "progress", "terrain", "relative")})  # fmt: skip


class Rollout:
    """A streaming rollout of one checkpoint over one scene: ``start(seed_rows)`` then ``step()`` per frame."""

    def __init__(self, ckpt: Path | str, corpus: Corpus | Path | str, *, temperature: float = 0.0, seed: int = 0,
                 rules: str | Sequence[str] = "auto", terrain_field: Any = None, cached: bool = True,
                 dtype: torch.dtype = torch.float32) -> None:  # fmt: skip
        self.corpus = _as_corpus(corpus)
        self.layout = self.corpus.layout
        self.ckpt = _checkpoint_dir(ckpt)
        meta = read_meta(self.ckpt)
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
            enabled: tuple[str, ...] = enabled_rules(self.layout, terrain_field)
        elif rules == "none" or rules is None:
            enabled = ()
        else:
            enabled = tuple(rules)
        self.rules = Rules(self.layout, terrain_field, RuleParams(fps=self.fps), enabled) if enabled else None
        # per entity, per token: clip frames advanced per model step, and whether the action wraps ("state")
        ratio = self.corpus.fps / self.fps
        self._advance = [ratio / c for c in self.tokens.clip_lengths]
        self._wraps = []
        types = self.corpus.vocab.get("entity_types", {})
        for i in range(len(self.tokens.entities)):
            kinds = {(k, a["token"]): a.get("kind") for k in types for a in types[k]["actions"]}
            self._wraps.append(np.array([kinds.get(self.tokens.type_token(i, t)) == "state" for t in range(self.tokens.sizes[i])]))

    # -- features --------------------------------------------------------------------------------

    def _terrain(self, state: np.ndarray, roots: np.ndarray, quats: np.ndarray) -> torch.Tensor | None:
        """Terrain features (1, 1, N, 132) of one state row at world roots (N, 3) and rotations (N, 4)."""
        if not any(self.config.terrain):
            return None
        cols: dict[str, Any] = {"state": pa.FixedSizeListArray.from_arrays(pa.array(state.astype(np.float32)), self.layout.dim)}
        for i, e in enumerate(self.layout.articulated):
            cols[f"{e.name}.root_world"] = pa.FixedSizeListArray.from_arrays(pa.array(roots[i].astype(np.float64)), 3)
            cols[f"{e.name}.rot_world"] = pa.FixedSizeListArray.from_arrays(pa.array(quats[i].astype(np.float64)), 4)
        feats, _ = compute_terrain_features(self.layout, pa.table(cols), self.field)
        return torch.from_numpy(feats).to(self.dtype)[None]

    def _relative(self, roots: np.ndarray, R: np.ndarray) -> np.ndarray | None:
        """The relative feature (N, 3) at world roots (N, 3) and rotations (N, 3, 3), when the model reads it."""
        return relative_roots(roots, R).astype(np.float32) if self.config.relative_position else None

    def _frames(self, root_n: np.ndarray, body_n: np.ndarray, tokens: np.ndarray, progress: np.ndarray | None,
                terrain: torch.Tensor | None, relative: np.ndarray | None = None) -> Frames:  # fmt: skip
        t = lambda a: torch.as_tensor(np.asarray(a, np.float32)).to(self.dtype)[None, None]  # noqa: E731  (1, 1, ·)
        return Frames(root=t(root_n), body=t(body_n), tokens=torch.as_tensor(np.asarray(tokens, np.int64))[None, None],
                      progress=None if progress is None else t(progress), terrain=terrain,
                      relative=None if relative is None else t(relative))  # fmt: skip

    # -- the stream ------------------------------------------------------------------------------

    @torch.no_grad()
    def start(self, seed_rows: pa.Table) -> None:
        """Fill both caches from dynamics-view rows (corpus state schema) and reset the rules and the sampler."""
        n = seed_rows.num_rows
        if n < 1:
            raise ValueError("a rollout needs at least one seed frame")
        L = self.layout
        state = _fixed(seed_rows["state"], L.dim).astype(np.float32)
        root, body = split_state(state, L)
        root_n, body_n = self.normaliser.normalise(root, body)
        tokens, progress = self.tokens.encode(L, seed_rows, where=str(self.corpus.path))
        terrain = None
        if any(self.config.terrain):
            terrain = torch.from_numpy(compute_terrain_features(L, seed_rows, self.field)[0]).to(self.dtype)[None]  # (1, n, N, 132)
        rel = relative_of_rows(L, seed_rows) if self.config.relative_position else [None] * n  # (n, N, 3)
        self.generator = torch.Generator().manual_seed(self.seed)
        self.action_stream.reset(1)
        self.pose_stream.reset(1)
        for k in range(n):
            tk = None if terrain is None else terrain[:, k : k + 1]
            frames = self._frames(root_n[k], body_n[k], tokens[k], progress[k], tk, rel[k])
            out = self.action_stream.step(frames)
            if k + 1 < n:  # PoseGPT step k animates frame k + 1 from body k
                tn = None if terrain is None else terrain[:, k + 1 : k + 2]
                frames = self._frames(root_n[k + 1], body_n[k], tokens[k + 1], None, tn, rel[k + 1])
                self.pose_stream.step(frames)
        self._out = out
        self.state = state[-1].astype(np.float64)
        self.body_n, self.tok, self.progress = body_n[-1], tokens[-1].copy(), progress[-1].astype(np.float64)
        last = seed_rows.slice(n - 1, 1)
        self.world = {k: v[0] for k, v in world_of_rows(L, last).items()}  # name → (K, 3) world joints
        self.quats = np.stack([_fixed(last[f"{e.name}.rot_world"], 4)[0] for e in L.articulated])
        self.t = 0
        if self.rules is not None:
            self.rules.reset()
            self.world = self.rules.step(self.world)  # frame 0 of the rules: taken as given

    @property
    def roots_world(self) -> np.ndarray:
        """World roots (N, 3) float64 of the current frame."""
        return np.stack([self.world[e.name][0] for e in self.layout.articulated])

    def _sample(self, logits: torch.Tensor) -> int:
        lg = logits.reshape(-1).double().clone()
        if lg.numel() > 1:
            lg[0] = -torch.inf
        if self.temperature <= 0:
            return int(lg.argmax())
        p = torch.softmax(lg / self.temperature, dim=-1)
        return int(torch.multinomial(p, 1, generator=self.generator))

    @torch.no_grad()
    def step(self, force_tokens: dict[int, int] | None = None, root_override: np.ndarray | None = None,
             restart: Sequence[int] = ()) -> np.ndarray:  # fmt: skip
        """Predict, correct and return the next state row (dim,) float32.

        ``force_tokens``: entity index → token for this frame; ``restart``: entity indices whose progress
        restarts even if the token is unchanged (a force window's first frame); ``root_override``: root
        stream (root_dim,) in state units, NaN = the model's value."""
        L, c, nz = self.layout, self.config, self.normaliser
        out = self._out
        root_n = out.root[0, 0].float().numpy().astype(np.float64)
        if root_override is not None:
            over = np.asarray(root_override, np.float64)
            root_n = np.where(np.isfinite(over), nz.normalise_root(np.nan_to_num(over)), root_n)
        tok = np.array([self._sample(lg[0, 0]) for lg in out.logits], np.int64)
        for i, v in (force_tokens or {}).items():
            tok[i] = int(v)
        prog = np.zeros(len(tok))
        for i in range(len(tok)):
            if tok[i] != 0 and tok[i] == self.tok[i] and i not in restart:
                p = self.progress[i] + self._advance[i][tok[i]]
                prog[i] = p % 1.0 if self._wraps[i][tok[i]] else min(p, 1.0)
        # PoseGPT animates the new frame from the current body
        root_raw = nz.denormalise_root(root_n)
        terrain = relative = None
        if any(c.terrain) or c.relative_position:
            guess = join_state(root_raw, nz.denormalise_body(self.body_n.astype(np.float64)), L)
            gw = geo.state_to_world(L, np.stack([self.state, guess]), dict(zip([e.name for e in L.articulated], self.roots_world)))
            g_roots = np.stack([gw[e.name]["joints"][1, 0] for e in L.articulated])
            g_R = np.stack([gw[e.name]["R"][1] for e in L.articulated])
            terrain = self._terrain(guess, g_roots, geo.matrix_to_quat(g_R))
            relative = self._relative(g_roots, g_R)
        frames = self._frames(root_n, self.body_n, tok, None, terrain, relative)
        body_n = self.pose_stream.step(frames).float()
        new = join_state(root_raw, nz.denormalise_body(body_n[0, 0].numpy().astype(np.float64)), L)
        # world skeletons, the rules, and the state re-derived from the corrected skeletons
        anchors = {e.name: self.world[e.name][0] for e in L.articulated}
        world = geo.state_to_world(L, np.stack([self.state, new]), anchors)
        frame = {name: w["joints"][1] for name, w in world.items()}
        if self.rules is not None:
            frame = self.rules.step(frame)
        quats = geo.quat_continuity(np.stack([self.quats, geo.matrix_to_quat(np.stack([world[e.name]["R"][1] for e in L.articulated]))]), 0)[1]
        joints = {n: np.stack([self.world[n], frame[n]]) for n in frame}
        rots = {e.name: np.stack([self.quats[i], quats[i]]) for i, e in enumerate(L.articulated)}
        state = geo.world_to_state(L, joints, rots)[1]
        self.state, self.world, self.quats = state.astype(np.float64), frame, quats
        self.tok, self.progress = tok, prog
        # ActionGPT reads the corrected frame
        root_c, body_c = split_state(state, L)
        root_cn, self.body_n = nz.normalise(root_c, body_c)
        terrain = self._terrain(state, self.roots_world, quats)
        relative = self._relative(self.roots_world, geo.quat_to_matrix(quats))
        frames = self._frames(root_cn, self.body_n, tok, prog, terrain, relative)
        self._out = self.action_stream.step(frames)
        self.t += 1
        return state


def _script_roots(script_root: Any, horizon: int, layout, root_dim: int) -> np.ndarray | None:
    """A (horizon, root_dim) override with NaN = no override, from an array or a dict entity → (horizon, 9)."""
    if script_root is None:
        return None
    if isinstance(script_root, dict):
        out = np.full((horizon, root_dim), np.nan)
        for i, e in enumerate(layout.articulated):
            if e.name in script_root:
                out[:, 9 * i : 9 * i + 9] = np.asarray(script_root[e.name], np.float64)[:horizon]
        return out
    a = np.asarray(script_root, np.float64)
    if a.shape != (horizon, root_dim):
        raise ValueError(f"script_root has shape {a.shape}; expected ({horizon}, {root_dim})")
    return a


def rollout(ckpt_dir: Path | str, corpus: Corpus | Path | str, segment: str, seed_frames: int = 64, horizon: int = 100,
            temperature: float = 0.0, seed: int = 0, force: Sequence[Force] = (), script_root: Any = None,
            rules: str | Sequence[str] = "auto", terrain_field: Any = None, start: int = 0, cached: bool = True,
            dtype: torch.dtype = torch.float32) -> pa.Table:  # fmt: skip
    """Seed rows + ``horizon`` predicted rows of ``segment`` (corpus state schema, 20 fps, world roots in m).

    The seed is the segment's dynamics frames [start, start + seed_frames). ``force``: (entity, start,
    end, token) with END exclusive, in predicted-frame indices; ``terrain_field`` defaults to the
    segment's scanned stage (None when it was never scanned). ``cached=False`` recomputes each frame
    (``ModelStream``); ``dtype`` is the models' (bfloat16 for the half-precision path)."""
    c = _as_corpus(corpus)
    L = c.layout
    if terrain_field is None:
        terrain_field = open_terrain_field(c, segment)
    ro = Rollout(ckpt_dir, c, temperature=temperature, seed=seed, rules=rules, terrain_field=terrain_field, cached=cached,
                 dtype=dtype)  # fmt: skip
    view = c.dynamics_segment(segment, ro.fps)
    if seed_frames < 1 or start < 0 or view.num_rows < start + seed_frames:
        raise ValueError(f"{c.path}: segment {segment} has {view.num_rows} dynamics frames; a seed of {seed_frames} frames "
                         f"from frame {start} does not fit")  # fmt: skip
    seed_rows = view.slice(start, seed_frames)
    names = [e.name for e in L.articulated]
    for name, _start, _end, token in force:
        if name not in names:
            raise ValueError(f"force: unknown entity {name!r}; the scene has {names}")
        if not 0 <= int(token) < ro.tokens.sizes[names.index(name)]:
            raise ValueError(f"force: token {token} outside {name}'s vocabulary of {ro.tokens.sizes[names.index(name)]}")
    scripted = _script_roots(script_root, horizon, L, ro.config.root_dim)
    ro.start(seed_rows)
    states, roots, quats, toks, progs = [], [], [], [], []
    for t in range(horizon):
        forced, restart = {}, []
        for name, first, end, token in force:
            if int(first) <= t < int(end):
                forced[names.index(name)] = int(token)
                if t == int(first):
                    restart.append(names.index(name))
        states.append(ro.step(forced, None if scripted is None else scripted[t], restart))
        roots.append(ro.roots_world)
        quats.append(ro.quats.copy())
        toks.append(ro.tok.copy())
        progs.append(ro.progress.copy())
    return _table(c, ro, seed_rows, segment, seed, np.array(states).reshape(horizon, L.dim), np.array(roots).reshape(horizon, -1, 3),
                  np.array(quats).reshape(horizon, -1, 4), np.array(toks).reshape(horizon, -1), np.array(progs).reshape(horizon, -1))  # fmt: skip


def _table(c: Corpus, ro: Rollout, seed_rows: pa.Table, segment: str, seed: int, states: np.ndarray, roots: np.ndarray,
           quats: np.ndarray, toks: np.ndarray, progs: np.ndarray) -> pa.Table:  # fmt: skip
    L, h = c.layout, len(states)
    schema = state_schema(L)
    name = f"{segment}-rollout-s{seed}"
    last = seed_rows.slice(seed_rows.num_rows - 1, 1).to_pylist()[0]
    step_frames = c.fps / ro.fps

    def fixed(x: np.ndarray, w: int, t: pa.DataType | None = None) -> pa.Array:
        return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(x).reshape(-1), t or pa.float64()), w)

    cols: dict[str, Any] = {
        "segment": pa.array([name] * h),
        "sample": pa.array([last["sample"]] * h),
        "frame": pa.array([int(last["frame"]) + int(round((k + 1) * step_frames)) for k in range(h)], pa.int32()),
        "t": pa.array(float(last["t"]) + (np.arange(h) + 1) / ro.fps),
        "state": fixed(states.astype(np.float32), L.dim, pa.float32()),
    }
    for i, e in enumerate(L.articulated):
        tok = toks[:, i]
        type_ids = [int(ro.tokens.type_keys[i][k].split(":")[1]) if k else int(last[f"{e.name}.type_id"]) for k in tok]
        clip = ro.tokens.clip_lengths[i][tok]
        cols[f"{e.name}.type_id"] = pa.array(type_ids, pa.int32())
        cols[f"{e.name}.action"] = pa.array(ro.tokens.composites[i][tok], pa.int32())
        cols[f"{e.name}.motion_frame"] = pa.array(np.where(tok == 0, -1, np.rint(progs[:, i] * clip)).astype(np.int32))
        cols[f"{e.name}.hp"] = pa.array([last[f"{e.name}.hp"]] * h, pa.float32())
        cols[f"{e.name}.root_world"] = fixed(roots[:, i], 3)
        cols[f"{e.name}.rot_world"] = fixed(quats[:, i], 4)
        cols[f"{e.name}.pos_check_m"] = pa.array(np.full(h, np.nan, np.float32))
    for e in L.attachments:
        cols[f"{e.name}.type_id"] = pa.array([last[f"{e.name}.type_id"]] * h, pa.int32())
    cols["camera.K"] = fixed(np.full((h, 4), np.nan), 4)
    cols["camera.pos"] = fixed(np.full((h, 3), np.nan), 3)
    cols["camera.rot"] = fixed(np.full((h, 4), np.nan), 4)
    cols["valid"] = pa.array(np.ones(h, bool))
    predicted = pa.Table.from_pydict(cols, schema=schema)
    seeded = seed_rows.cast(schema).set_column(0, "segment", pa.array([name] * seed_rows.num_rows))
    return pa.concat_tables([seeded, predicted])


def _parse_force(s: str) -> Force:
    parts = s.rsplit(":", 3)
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(f"--force {s!r}: expected ENTITY:START:END:TOKEN")
    return parts[0], int(parts[1]), int(parts[2]), int(parts[3])


def _parse_script(s: str) -> tuple[str, Any]:
    """``ENTITY:START:END:VX,VY,VZ`` (a constant root velocity in the entity's own frame, m/s; END
    exclusive) or ``ENTITY:FILE.npy`` (a (horizon, 9) array of E.root then E.rot6d, NaN = the model's)."""
    name, _, rest = s.partition(":")
    if rest.endswith(".npy"):
        return name, Path(rest)
    parts = rest.split(":")
    if len(parts) != 3 or len(parts[2].split(",")) != 3:
        raise argparse.ArgumentTypeError(f"--script-root {s!r}: expected ENTITY:START:END:VX,VY,VZ or ENTITY:FILE.npy")
    return name, (int(parts[0]), int(parts[1]), tuple(float(v) for v in parts[2].split(",")))


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
            if not 0 <= start < end:
                raise ValueError(f"--script-root {name}: frames [{start}, {end}) are empty or negative")
            arr[start : min(end, horizon), 0:3] = np.asarray(velocity) / fps  # metres per model frame
    return out


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The rollout command's arguments (shared by ``marionette rollout`` and ``python -m``)."""
    ap.add_argument("ckpt", type=Path, help="a checkpoint directory or a training output directory")
    ap.add_argument("corpus", type=Path)
    ap.add_argument("--segment", required=True, help="the recorded segment whose first frames seed the rollout")
    ap.add_argument("--seed-frames", type=int, default=64)
    ap.add_argument("--horizon", type=int, required=True, help="predicted frames")
    ap.add_argument("--temperature", type=float, default=0.0, help="0: argmax, deterministic")
    ap.add_argument("--seed", type=int, default=0, help="the sampler's seed")
    ap.add_argument("--force", type=_parse_force, nargs="*", default=[], help="ENTITY:START:END:TOKEN (predicted frames, END exclusive)")
    ap.add_argument("--script-root", type=_parse_script, nargs="*", default=[],
                    help="ENTITY:START:END:VX,VY,VZ (m/s in the entity's frame) or ENTITY:FILE.npy ((horizon, 9) root channels)")  # fmt: skip
    ap.add_argument("--rules", default="auto", help=f"auto, none, or a comma list of {','.join(RULES)}")
    ap.add_argument("--out", type=Path, required=True, help="STATES.arrow (the corpus state schema)")
    ap.add_argument("--render", type=Path, default=None, help="also render the rollout (follow camera) to this .mkv")
    ap.add_argument("--size", type=lambda v: tuple(int(x) for x in v.lower().split("x")), default=(352, 640), help="render HxW")


def run(args: argparse.Namespace, log=print) -> pa.Table:
    """Run a parsed rollout command: the rollout, its table, and the optional render."""
    rules = args.rules if args.rules in ("auto", "none") else tuple(r for r in args.rules.split(",") if r)
    c = _as_corpus(args.corpus)
    fps = float(read_meta(_checkpoint_dir(args.ckpt))["train_config"].get("fps", 20.0))
    script = script_from_args(args.script_root, args.horizon, fps, c.layout)
    started = time.perf_counter()
    table = rollout(args.ckpt, c, args.segment, args.seed_frames, args.horizon, args.temperature, args.seed, args.force,
                    script_root=script, rules=rules)  # fmt: skip
    took = time.perf_counter() - started
    write_ipc(args.out, table)
    log(f"{args.out}: {table.num_rows} rows ({args.horizon} predicted, {args.horizon / took:.0f} frames/s incl. loading)")
    if args.render is not None:
        from marionette.bridge.targets import TerrainScene, render_rows
        from terrain_scan.scan import stage_dir

        d = stage_dir(c.path, c.segment_row(args.segment)["stage"])
        terrain = TerrainScene.of_stage(d) if (d / "manifest.json").exists() else TerrainScene.empty()
        meta = render_rows(c.layout, table, args.render, terrain, camera="follow", size=args.size)
        log(f"{args.render}: {meta.width}×{meta.height} at {meta.fps:g} fps (follow camera)")
    return table


def main(argv: list[str] | None = None) -> pa.Table:
    """``python -m marionette.dynamics.rollout DIR CORPUS --segment ID --horizon N --out STATES.arrow [...]``."""
    ap = argparse.ArgumentParser(prog="python -m marionette.dynamics.rollout", description=__doc__.splitlines()[0])
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    main()
