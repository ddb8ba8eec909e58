"""Training windows for the dynamics model, read from the corpus's dynamics view (20 fps by default).

Everything here is derived from the corpus alone; the definitions, exactly:

**Normalisation** (``Normaliser``). The root stream and the body state are z-scored per dimension,
z = (x − mean) / max(std, std_floor), with mean and std the ``state`` entry of ``meta/stats.json``
(population statistics over the train split's source-rate rows; over all rows when the corpus has no
train split, which ``stats.json`` records as ``"split": "all"``), mapped through the same index lists as
``state.split_state``. ``std_floor`` (default 1e-3, in the dimension's own unit: metres or 6D
entries) keeps dimensions that barely vary from blowing up: a joint rigidly attached to its root
(the synthetic drake's spine, or any 6D entry of a yaw-only rotation) has a std of float32 rounding
noise (~1e-5 m) or exactly 0, and dividing by that would turn rounding noise into unit-scale signal
or divide by zero. The arithmetic runs in float64 and returns the input's dtype.
The statistics are those of the source rate (30 fps): the joints and 6D rotations do not depend on
the rate, but a root displacement δ is per frame, so at 20 fps it is ~1.5× the 30 fps one and its
normalised values have a std of ~1.5 rather than 1 (harmless for training; stated so nobody is
surprised).

**Tokens** (``ActionTokens``). vocab.json numbers the composite action ids densely per entity type
``<rig>:<type_id>`` (the row's ``<entity>.type_id`` column names the type; ``ingest.sample`` keys the
vocab the same way), token 0 = composite 0 = "no valid action". The model has one embedding table
per articulated entity, so an entity's tokens are the concatenation of the vocabularies of every
type of its rig, in increasing type id: entity token 0 = no valid action; type k's vocab token
v ≥ 1 becomes offset_k + v with offset_k = Σ_{types j before k} (size_j − 1). With one type per rig
(the usual case) entity tokens are the vocab tokens. A composite id (or type) the vocab does not
hold is an error naming the segment, the row and the source frame.

**Progress** = motion_frame / clip_length of the row's action (clip length = the largest motion_frame
the corpus saw + 1, from vocab.json), clipped to [0, 1]; 0 for token 0 and for an invalid
motion_frame (−1). It is in source frames: at the source rate it grows by 1/clip_length per frame.
The dynamics view takes discrete fields from the source frame at or before each 20 fps time, i.e.
source frame ⌊1.5·k⌋ of a 30 fps segment, so along a 20 fps clip progress grows by 1 and 2
source frames in turn, 1.5/clip_length per model frame on average (a rollout that advances an
unchanged token should add (source fps / model fps) / clip_length to match what training saw).

**Relative feature** (``relative_roots``, read only by models with ``relative_position`` on), per row
and articulated entity: the nearest other articulated entity's root in the entity's own root frame,
Rᵀ(r_other − r_me), in units of 5 m (``RELATIVE_SCALE_M``), from the view's ``root_world`` and
``rot_world``; zeros in a one-entity scene. A rollout re-derives it each frame from the corrected roots.

**Terrain features** (``terrain_feature_shard``), per row and articulated entity, 132 float32 = the
11 × 11 ``terrain_scan.field.egocentric_patch`` at the entity's recorded root and rotation (the
dynamics view's ``root_world``/``rot_world``, the rig's forward axis; 0.4 m cells, centred 1 m ahead;
heights relative to the root, flattened row-major: index = 11·row + column, row 0 nearest the body),
then the 11 ``joint_clearances`` of the rig's key contact joints (``rig.contact_joints`` order; world
joints from ``corpus.world_of_rows``; ref_y = root height). Unknown values (no terrain there, or a
stage that was never scanned) are stored as 0 with ``known`` False beside them (same shape), so
features are finite everywhere and the model reads zeros for unknown terrain; ``known`` travels in
``Batch.terrain_known``, frame-aligned with ``Frames.terrain``, for losses that need the surface (a rig with fewer than 11 contact joints has
its tail unknown). Features are computed for every articulated entity (the config's per-entity
switch only chooses which ones a model reads), so one cache serves every config.

**Cache key** of a shard's terrain features: sha256 over (the dynamics-view key of the shard = its
content hash, the rate, the resampling method, ``corpus.RESAMPLE_VERSION`` and the layout hash;
every stage its segments lie on with the sha256 of each of its chunks from the stage's
``manifest.json`` — none when it has no terrain; ``FEATURE_VERSION``; the patch geometry). File:
``<corpus>/derived/terrain-features/shard-NNNNNN-<fps>fps-<method>-<key>.arrow``, written atomically;
files of the same shard and rate with another key are removed after a write.

**Windows.** A window is W = ``length`` + 1 consecutive dynamics frames of one segment (``length``
model steps plus the next-frame target). Segments shorter than W are skipped (``WindowData.usable``
says which are kept; no padding, so no time mask). Training (``WindowSampler``, train split only):
each epoch draws, from ``numpy.random.default_rng([seed, epoch])``, one phase per usable segment,
uniform in [0, min(W − 1, n − W)], and tiles the segment with non-overlapping windows starting at
phase + k·W; the corpus-wide list of windows is shuffled with the same generator, cut to a multiple
of world_size, and rank r takes every world_size-th window from position r, then full batches of
``batch_size`` (a partial last batch is dropped, so every rank runs the same number of steps).
Ranks therefore see disjoint windows (no frame of one epoch is read by two ranks), and the batches
are a function of (seed, rank, world_size, epoch) alone. Held-out evaluation (``HeldOutWindows``):
every usable segment of the split tiled from frame 0 with stride W, in segment order, rank r taking
every world_size-th window; batches of up to ``batch_size`` (the last may be smaller); frames after a
segment's last whole window are not evaluated.
What "every window of the epoch" means for training: the epoch's windows are the tiles above, and
exactly the first world_size · ⌊⌊E / world_size⌋ / batch_size⌋ · batch_size of the shuffled E are
trained on, each by one rank once; the rest, fewer than world_size · batch_size (E mod world_size
cut for equal shares, then each rank's partial batch), wait for another epoch's draw
(``WindowSampler.epoch_windows`` lists all E in shuffled order).

**Loader workers** (``TrainBatches``, ``train_batches``). A rank's batches from global step s on,
epoch after epoch, numbered j = 0, 1, … from s: in-process (no workers) they are stacked in turn; with
k DataLoader workers, worker w stacks only the batches with j ≡ w (mod k), and the DataLoader, which
asks its workers for batches in turn and returns them in that order (``in_order``), yields the
in-process sequence exactly, so training reads the same batches in the same order (same losses) with
any number of workers. A worker computes the epoch's window list itself from (seed, rank,
world_size, epoch) and reads windows from the memory-mapped cache: what reaches it is the sampler's
recipe (``WindowData`` pickles as its corpus path, split, flags, normaliser and token tables, and
re-opens the arrays when unpickled, under a ``spawn`` start method; ``fork`` shares the open maps),
never the arrays, so k workers add k processes' fixed overhead and no copy of the split.

**Window arrays on disk** (``shard_windows``). What a window reads — normalised root and body
(float32), tokens (int64), progress (float32), and when asked terrain features and ``known`` and the
relative feature — is computed one shard at a time and stored as one ``.npy`` file per array under
``<corpus>/derived/windows/shard-NNNNNN-<fps>fps-<method>-t<0|1>r<0|1>-<key>/`` (t, r: terrain
and relative arrays held) with ``segments.json`` (each
segment's [first, end) rows, contiguous in the view), written to a temporary directory and renamed
into place. ``WindowData`` opens them memory-mapped (``allow_pickle=False``; every array's dtype and
shape checked against the layout before use, a mismatch recomputed), so a process's memory holds the
pages its windows touch — the page cache, shared by the ranks and workers of one machine — and not
the split: its anonymous memory does not grow with the corpus. The key: sha256 over the shard's
dynamics-view key, the normaliser, the token tables' vocab hash and sizes, the terrain features' key
when they are read, the relative flag and ``WINDOWS_VERSION``; directories of the same shard, rate and
arrays under another key are removed after a write.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import torch
from torch import Tensor
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from marionette import geometry as geo
from marionette.corpus import RESAMPLE_VERSION, Corpus, fixed_rows, paths, world_of_rows
from marionette.corpus.vocab import ActionTokens, entity_type_key  # noqa: F401 — the models' token tables
from marionette.dynamics.config import N_CLEARANCES, PATCH_SIZE, TERRAIN_FEATURES
from marionette.dynamics.model import PLAYED_OUT_SLACK, Frames
from marionette.dynamics.state import body_index, root_index
from marionette.io import read_ipc, text_sha256, write_ipc, write_json
from marionette.schema import Layout, SchemaError
from terrain_scan.field import LayeredField, egocentric_patch, joint_clearances, open_stage
from terrain_scan.store import stage_terrain

DEFAULT_FPS = 20.0
DEFAULT_STD_FLOOR = 1e-3
NORMALISER_VERSION = 1
FEATURE_VERSION = "1"
PATCH_CELL_M = 0.4
PATCH_AHEAD_M = 1.0
RELATIVE_SCALE_M = 5.0  # the relative feature's unit: fighters stand a few metres apart
TERRAIN_DIR = "terrain-features"
WINDOWS_DIR = "windows"
WINDOWS_VERSION = "2"  # 2: progress counts the time past the source frame


def as_corpus(corpus: Corpus | Path | str, scene: str | None = None) -> Corpus:
    """``corpus`` itself, or the Corpus at that path (its scene ``scene``, in a corpus of several)."""
    return corpus if isinstance(corpus, Corpus) else Corpus(Path(corpus), scene=scene)


# -- normalisation -----------------------------------------------------------------------------------


def _affine(x: Any, mean: np.ndarray, std: np.ndarray, inverse: bool) -> Any:
    """(x − mean)/std, or x·std + mean when ``inverse``, over the last axis; float64 inside, x's dtype out."""
    if isinstance(x, torch.Tensor):
        m = torch.as_tensor(mean, dtype=torch.float64, device=x.device)
        s = torch.as_tensor(std, dtype=torch.float64, device=x.device)
        y = x.to(torch.float64)
        out = y * s + m if inverse else (y - m) / s
        return out.to(x.dtype if x.is_floating_point() else torch.float32)
    a = np.asarray(x)
    out = a.astype(np.float64) * std + mean if inverse else (a.astype(np.float64) - mean) / std
    return out.astype(a.dtype if np.issubdtype(a.dtype, np.floating) else np.float32)


@dataclass(frozen=True, eq=False)
class Normaliser:
    """Per-dimension z-score of the root stream and the body state (module doc: the definition)."""

    root_mean: np.ndarray  # (root_dim,) float64
    root_std: np.ndarray  # (root_dim,) float64, already floored
    body_mean: np.ndarray  # (body_dim,)
    body_std: np.ndarray  # (body_dim,), already floored
    std_floor: float
    layout_hash: str
    stats_split: str  # "train", or "all" when the corpus had no train split

    @classmethod
    def from_corpus(
        cls, corpus: Corpus | Path | str, layout: Layout | None = None, std_floor: float = DEFAULT_STD_FLOOR
    ) -> Normaliser:
        """The normaliser of a corpus's ``stats.json`` state statistics (train split), std floored at ``std_floor``."""
        c = as_corpus(corpus)
        layout = layout or c.layout
        if layout.hash != c.layout.hash:
            raise SchemaError(
                f"{c.path}: corpus layout {c.layout.scene!r} ({c.layout.hash}) is not {layout.scene!r} ({layout.hash})"
            )
        if std_floor <= 0:
            raise ValueError(f"std_floor {std_floor} must be > 0")
        st = c.stats.get("state")
        where = paths.meta(c.path, paths.STATS)
        if st is None:
            raise KeyError(f"{where}: no 'state' entry")
        mean, std = np.asarray(st["mean"], np.float64), np.asarray(st["std"], np.float64)
        if mean.shape != (layout.dim,) or std.shape != (layout.dim,):
            raise SchemaError(
                f"{where}: state stats have {mean.shape[0]} means and {std.shape[0]} stds; the layout has dim {layout.dim}"
            )
        std = np.maximum(std, std_floor)
        ri, bi = root_index(layout), body_index(layout)
        return cls(mean[ri], std[ri], mean[bi], std[bi], float(std_floor), layout.hash, str(c.stats.get("split", "train")))

    def normalise_root(self, root: Any) -> Any:
        """Root stream (..., root_dim) → z-scores; numpy or torch, dtype kept."""
        return _affine(root, self.root_mean, self.root_std, inverse=False)

    def normalise_body(self, body: Any) -> Any:
        """Body state (..., body_dim) → z-scores; numpy or torch, dtype kept."""
        return _affine(body, self.body_mean, self.body_std, inverse=False)

    def denormalise_root(self, root: Any) -> Any:
        """Z-scored root stream (..., root_dim) → metres and 6D entries."""
        return _affine(root, self.root_mean, self.root_std, inverse=True)

    def denormalise_body(self, body: Any) -> Any:
        """Z-scored body state (..., body_dim) → metres."""
        return _affine(body, self.body_mean, self.body_std, inverse=True)

    def normalise(self, root: Any, body: Any) -> tuple[Any, Any]:
        """(root, body) → their z-scores."""
        return self.normalise_root(root), self.normalise_body(body)

    def denormalise(self, root: Any, body: Any) -> tuple[Any, Any]:
        """Z-scored (root, body) → state units."""
        return self.denormalise_root(root), self.denormalise_body(body)

    def to_json(self) -> dict:
        """A JSON-ready dict (saved beside checkpoints); the stds are the floored ones in use."""
        return {
            "version": NORMALISER_VERSION,
            "layout_hash": self.layout_hash,
            "stats_split": self.stats_split,
            "std_floor": self.std_floor,
            "root_mean": self.root_mean.tolist(),
            "root_std": self.root_std.tolist(),
            "body_mean": self.body_mean.tolist(),
            "body_std": self.body_std.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict) -> Normaliser:
        """Rebuild from ``to_json()``."""
        if d.get("version") != NORMALISER_VERSION:
            raise ValueError(f"normaliser JSON version {d.get('version')!r}; this code reads {NORMALISER_VERSION}")
        arr = {k: np.asarray(d[k], np.float64) for k in ("root_mean", "root_std", "body_mean", "body_std")}
        return cls(**arr, std_floor=float(d["std_floor"]), layout_hash=d["layout_hash"], stats_split=d["stats_split"])


# -- action tokens and progress ----------------------------------------------------------------------


def vocab_sizes(corpus: Corpus | Path | str) -> tuple[int, ...]:
    """Entity vocabulary sizes per articulated entity in layout order (token 0 included), for ``DynamicsConfig``."""
    return ActionTokens.from_corpus(corpus).sizes


# -- the relative feature ----------------------------------------------------------------------------


def relative_roots(roots_world: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(..., N, 3) world roots and (..., N, 3, 3) root rotations → (..., N, 3): for each entity, the nearest
    other entity's root in its own root frame, Rᵢᵀ (r_j − r_i), divided by ``RELATIVE_SCALE_M``; zeros
    when the scene has one entity. float64 differences, so roots far from the origin lose nothing."""
    r = np.asarray(roots_world, np.float64)
    R = np.asarray(rotations, np.float64)
    n = r.shape[-2]
    out = np.zeros(r.shape, np.float64)
    if n < 2:
        return out
    d = r[..., None, :, :] - r[..., :, None, :]  # (..., N, N, 3): d[i, j] = r_j − r_i
    dist = np.linalg.norm(d, axis=-1) + np.where(np.eye(n, dtype=bool), np.inf, 0.0)
    nearest = np.nan_to_num(dist, nan=np.inf).argmin(-1)  # (..., N)
    other = np.take_along_axis(d, nearest[..., None, None], axis=-2)[..., 0, :]  # (..., N, 3)
    return np.einsum("...ji,...j->...i", R, other) / RELATIVE_SCALE_M


def relative_of_rows(layout: Layout, table: pa.Table) -> np.ndarray:
    """``relative_roots`` (n, N, 3) float32 of state rows, from their ``root_world`` and ``rot_world`` columns."""
    ents = layout.articulated
    roots = np.stack([fixed_rows(table[f"{e.name}.root_world"], 3) for e in ents], axis=1)
    R = np.stack([geo.quat_to_matrix(fixed_rows(table[f"{e.name}.rot_world"], 4)) for e in ents], axis=1)
    return relative_roots(roots, R).astype(np.float32)


# -- terrain features --------------------------------------------------------------------------------


def stage_chunk_hashes(c: Corpus, stage: str) -> dict[str, str]:
    """Chunk name "cx_cz" → sha256 of each chunk of a stage, from its manifest.json; empty when it was never scanned."""
    scanned = stage_terrain(c.path, stage)
    return {name: digest for name, (_, digest) in scanned.chunk_files().items()} if scanned is not None else {}


def compute_terrain_features(layout: Layout, table: pa.Table, field: LayeredField | None) -> tuple[np.ndarray, np.ndarray]:
    """Features (n, N, 132) float32 (unknown → 0) and ``known`` (n, N, 132) bool of rows, N articulated
    entities in layout order: the 11×11 egocentric patch (m, relative to the root), then 11 clearances (m)."""
    if field is None or table.num_rows == 0:
        return terrain_features_of(layout, {}, np.zeros((table.num_rows, 0, 3, 3)), None)
    R = np.stack([geo.quat_to_matrix(fixed_rows(table[f"{e.name}.rot_world"], 4)) for e in layout.articulated], axis=1)
    return terrain_features_of(layout, world_of_rows(layout, table), R, field)


def terrain_features_of(
    layout: Layout, joints_world: dict[str, np.ndarray], R: np.ndarray, field: LayeredField | None
) -> tuple[np.ndarray, np.ndarray]:
    """``compute_terrain_features`` from world skeletons: ``joints_world[name]`` (n, K, 3), root first, and
    root rotations ``R`` (n, N, 3, 3) of the articulated entities (what a rollout already holds)."""
    n, ents = R.shape[0], layout.articulated
    feats = np.zeros((n, len(ents), TERRAIN_FEATURES), np.float32)
    known = np.zeros((n, len(ents), TERRAIN_FEATURES), bool)
    if field is None or n == 0:
        return feats, known
    for i, e in enumerate(ents):
        contacts = list(e.rig.contact_index)
        if len(contacts) > N_CLEARANCES:
            raise SchemaError(
                f"rig {e.rig.name!r} declares {len(contacts)} key contact joints; terrain features hold {N_CLEARANCES}"
            )
        joints = np.asarray(joints_world[e.name], np.float64)
        root = joints[:, 0]
        patch, _ = egocentric_patch(
            field, root, R[:, i], np.asarray(e.rig.forward_axis, np.float64), PATCH_SIZE, PATCH_CELL_M, PATCH_AHEAD_M
        )
        clear = joint_clearances(field, joints[:, contacts], root[:, 1])
        values = np.concatenate([patch.reshape(n, -1), clear], axis=1)  # (n, 121 + contacts)
        ok = np.isfinite(values)
        feats[:, i, : values.shape[1]] = np.where(ok, values, 0.0)
        known[:, i, : values.shape[1]] = ok
    return feats, known


def _dynamics_key(c: Corpus, shard: int, fps: float, method: str) -> str:
    """The dynamics view's cache key of a shard (what ``Corpus.dynamics_shard`` computes it from)."""
    return text_sha256(c.shard_hash(shard), f"{fps:g}", method, RESAMPLE_VERSION, c.layout.hash)[:16]


def _shard_stages(c: Corpus, shard: int) -> dict[str, str]:
    seg = c.segments.filter(pc.equal(c.segments["shard"], shard))
    return dict(zip(seg["segment"].to_pylist(), seg["stage"].to_pylist()))


def terrain_feature_path(corpus: Corpus | Path | str, shard: int, fps: float = DEFAULT_FPS, method: str = "linear") -> Path:
    """Where a shard's terrain features live under its current key (module doc: the key)."""
    c = as_corpus(corpus)
    stages = sorted(set(_shard_stages(c, shard).values()))
    geometry = json.dumps([PATCH_SIZE, PATCH_CELL_M, PATCH_AHEAD_M, N_CLEARANCES])
    terrain = json.dumps({st: stage_chunk_hashes(c, st) for st in stages}, sort_keys=True)
    key = text_sha256(_dynamics_key(c, shard, fps, method), terrain, FEATURE_VERSION, geometry)[:16]
    return paths.derived(c.path, TERRAIN_DIR) / f"shard-{shard:06d}-{fps:g}fps-{method}-{key}.arrow"


def _feature_schema(layout: Layout) -> pa.Schema:
    fields = [pa.field("segment", pa.string()), pa.field("frame", pa.int32())]
    for e in layout.articulated:
        fields += [
            pa.field(f"{e.name}.terrain", pa.list_(pa.float32(), TERRAIN_FEATURES)),
            pa.field(f"{e.name}.terrain_known", pa.list_(pa.bool_(), TERRAIN_FEATURES)),
        ]
    return pa.schema(
        fields, metadata={b"marionette.layout_hash": layout.hash.encode(), b"feature_version": FEATURE_VERSION.encode()}
    )


def terrain_feature_shard(
    corpus: Corpus | Path | str, shard: int, fps: float = DEFAULT_FPS, method: str = "linear"
) -> tuple[np.ndarray, np.ndarray]:
    """Terrain features (n, N, 132) float32 and ``known`` (n, N, 132) bool, row-aligned with
    ``corpus.dynamics_shard(shard, fps, method)``; cached, recomputed only when the key changes."""
    c = as_corpus(corpus)
    layout = c.layout
    view = c.dynamics_shard(shard, fps, method)
    path = terrain_feature_path(c, shard, fps, method)
    if path.exists():
        cached = read_ipc(path)
        if (
            cached.schema.equals(_feature_schema(layout))
            and cached["segment"].equals(view["segment"])
            and cached["frame"].equals(view["frame"])
        ):
            return _feature_arrays(layout, cached)
    stage_of = _shard_stages(c, shard)
    segs = view["segment"].to_numpy(zero_copy_only=False)
    feats = np.zeros((view.num_rows, len(layout.articulated), TERRAIN_FEATURES), np.float32)
    known = np.zeros(feats.shape, bool)
    for st in sorted(set(stage_of.values())):
        rows = np.flatnonzero(np.isin(segs, [s for s, v in stage_of.items() if v == st]))
        scanned = stage_terrain(c.path, st)
        field = open_stage(scanned.dir) if scanned is not None else None
        feats[rows], known[rows] = compute_terrain_features(layout, view.take(pa.array(rows)), field)
    cols: dict[str, pa.Array] = {"segment": view["segment"].combine_chunks(), "frame": view["frame"].combine_chunks()}
    for i, e in enumerate(layout.articulated):
        cols[f"{e.name}.terrain"] = pa.FixedSizeListArray.from_arrays(pa.array(feats[:, i].reshape(-1)), TERRAIN_FEATURES)
        cols[f"{e.name}.terrain_known"] = pa.FixedSizeListArray.from_arrays(pa.array(known[:, i].reshape(-1)), TERRAIN_FEATURES)
    write_ipc(path, pa.Table.from_pydict(cols, schema=_feature_schema(layout)), c.info.compression)
    for old in path.parent.glob(f"shard-{shard:06d}-{fps:g}fps-{method}-*.arrow"):  # features under an older key
        if old != path:
            old.unlink(missing_ok=True)
    return feats, known


def _feature_arrays(layout: Layout, table: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    feats = np.stack([fixed_rows(table[f"{e.name}.terrain"], TERRAIN_FEATURES) for e in layout.articulated], axis=1)
    known = np.stack([fixed_rows(table[f"{e.name}.terrain_known"], TERRAIN_FEATURES) for e in layout.articulated], axis=1)
    return feats.astype(np.float32), known.astype(bool)


# -- windows -----------------------------------------------------------------------------------------


WINDOW_ARRAYS = ("root", "body", "action", "progress", "features", "known", "rel")


def _window_dtypes(layout: Layout) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """Each window array's dtype and shape after its row axis."""
    N = len(layout.articulated)
    return {
        "root": (np.dtype(np.float32), (len(root_index(layout)),)),
        "body": (np.dtype(np.float32), (len(body_index(layout)),)),
        "action": (np.dtype(np.int64), (N,)),
        "progress": (np.dtype(np.float32), (N,)),
        "features": (np.dtype(np.float32), (N, TERRAIN_FEATURES)),
        "known": (np.dtype(bool), (N, TERRAIN_FEATURES)),
        "rel": (np.dtype(np.float32), (N, 3)),
    }


def shard_windows_dir(
    c: Corpus, shard: int, normaliser: Normaliser, tokens: ActionTokens, *, terrain: bool, relative: bool, fps: float, method: str
) -> Path:
    """Where a shard's window arrays live under their current key (module doc: window arrays on disk)."""
    parts = [
        _dynamics_key(c, shard, fps, method),
        json.dumps(normaliser.to_json(), sort_keys=True),
        tokens.vocab_hash,
        json.dumps([list(tokens.entities), list(tokens.sizes)]),
        terrain_feature_path(c, shard, fps, method).name if terrain else "no terrain",
        f"relative={relative}",
        WINDOWS_VERSION,
    ]
    reads = f"t{int(terrain)}r{int(relative)}"
    return paths.derived(c.path, WINDOWS_DIR) / f"shard-{shard:06d}-{fps:g}fps-{method}-{reads}-{text_sha256(*parts)[:16]}"


def shard_windows(
    c: Corpus,
    shard: int,
    normaliser: Normaliser,
    tokens: ActionTokens,
    *,
    terrain: bool = False,
    relative: bool = False,
    fps: float = DEFAULT_FPS,
    method: str = "linear",
) -> tuple[dict[str, np.ndarray | None], dict[str, tuple[int, int]]]:
    """A shard's window arrays, memory-mapped read-only (None for the ones not asked for), and each segment's
    [first, end) rows; computed and stored on first use (module doc: window arrays on disk)."""
    d = shard_windows_dir(c, shard, normaliser, tokens, terrain=terrain, relative=relative, fps=fps, method=method)
    names = [k for k in WINDOW_ARRAYS if (k not in ("features", "known") or terrain) and (k != "rel" or relative)]
    if d.is_dir():
        opened = _open_windows(c, d, names)
        if opened is not None:
            return opened
        shutil.rmtree(d, ignore_errors=True)  # a stale or damaged cache is recomputed
    _write_windows(c, shard, d, normaliser, tokens, terrain=terrain, relative=relative, fps=fps, method=method)
    opened = _open_windows(c, d, names)
    if opened is None:
        raise SchemaError(f"{d}: the window arrays just written do not read back")
    return opened


def _open_windows(c: Corpus, d: Path, names: list[str]):
    """The arrays of ``d`` memory-mapped and its segment spans, or None when anything disagrees with the layout."""
    expected = _window_dtypes(c.layout)
    try:
        spans = {str(k): (int(v[0]), int(v[1])) for k, v in json.loads((d / "segments.json").read_text()).items()}
        arrays: dict[str, np.ndarray | None] = dict.fromkeys(WINDOW_ARRAYS)
        n = None
        for k in names:
            a = np.load(d / f"{k}.npy", mmap_mode="r", allow_pickle=False)
            dtype, tail = expected[k]
            if a.dtype != dtype or a.shape[1:] != tail or (n is not None and len(a) != n):
                return None
            n, arrays[k] = len(a), a
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None
    if any(not 0 <= a <= b <= (n or 0) for a, b in spans.values()):
        return None
    return arrays, spans


def _write_windows(
    c: Corpus,
    shard: int,
    d: Path,
    normaliser: Normaliser,
    tokens: ActionTokens,
    *,
    terrain: bool,
    relative: bool,
    fps: float,
    method: str,
) -> None:
    layout = c.layout
    view = c.dynamics_shard(shard, fps, method)
    state = fixed_rows(view["state"], layout.dim)
    out: dict[str, np.ndarray] = {
        "root": normaliser.normalise_root(state[:, root_index(layout)]).astype(np.float32),
        "body": normaliser.normalise_body(state[:, body_index(layout)]).astype(np.float32),
    }
    out["action"], out["progress"] = tokens.encode(layout, view, where=str(c.dynamics_dir(fps, method)))
    out["action"], out["progress"] = out["action"].astype(np.int64), out["progress"].astype(np.float32)
    if terrain:
        out["features"], out["known"] = terrain_feature_shard(c, shard, fps, method)
    if relative:
        out["rel"] = relative_of_rows(layout, view).astype(np.float32)
    names = view["segment"].to_numpy(zero_copy_only=False)
    spans: dict[str, list[int]] = {}
    for s in dict.fromkeys(names.tolist()):
        idx = np.flatnonzero(names == s)
        if idx[-1] - idx[0] + 1 != len(idx):
            raise SchemaError(f"{c.dynamics_dir(fps, method)}: shard {shard}'s rows of segment {s} are not contiguous")
        spans[str(s)] = [int(idx[0]), int(idx[-1]) + 1]
    d.parent.mkdir(parents=True, exist_ok=True)
    # a fresh name: ranks on other machines sharing the corpus may have this process's pid
    tmp = Path(tempfile.mkdtemp(prefix=f".{d.name}.", suffix=".tmp", dir=d.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes 0700; the cache is read by every user of the corpus
    for k, a in out.items():
        np.save(tmp / f"{k}.npy", np.ascontiguousarray(a), allow_pickle=False)
    write_json(tmp / "segments.json", spans)
    try:
        os.replace(tmp, d)
    except OSError:  # another process (a DDP rank) put the same arrays there first
        shutil.rmtree(tmp, ignore_errors=True)
        if not d.is_dir():
            raise
    prefix = d.name[: -len(d.name.rsplit("-", 1)[1])]  # the same shard, rate and arrays
    for old in d.parent.glob(prefix + "*"):  # under an older key
        if old != d and old.is_dir():
            shutil.rmtree(old, ignore_errors=True)


@dataclass
class Batch:
    """A batch of windows: the model's inputs (normalised, float32, batch first, W = length + 1 frames),
    ``terrain_known`` (B, W, N, 132) bool when terrain was loaded, and which windows these are."""

    frames: Frames
    terrain_known: Tensor | None
    segments: tuple[str, ...]
    starts: tuple[int, ...]  # first dynamics frame of each window within its segment


def ended_events(data: WindowData, lengths: tuple[tuple[float, ...], ...], step: float) -> tuple[tuple[float, ...], ...]:
    """``lengths`` (per entity, per token: an event's clip length in source frames, 0 for a loop) with 0 for every
    token that the split's rows show running on where it has played out: a row of the token with at most ``step``
    source frames left, (1 − progress) · length ≤ step, followed by a row of the same token. By the vocab's
    definition an event's motion_frame never wraps, so on a consistent corpus none does; one that does (an action
    replayed back to back, or a motion_frame that stalls) keeps its copy-last odds (``DynamicsConfig.events_end``)."""
    out = [list(t) for t in lengths]
    for i, table in enumerate(lengths):
        L = np.asarray(table, np.float64)
        for tok, prog in zip(data.action, data.progress):
            if len(tok) < 2:
                continue
            cur, nxt = tok[:-1, i], tok[1:, i]
            ended = (L[cur] > 0) & ((1.0 - prog[:-1, i].astype(np.float64)) * L[cur] <= step + PLAYED_OUT_SLACK)
            for t in np.unique(cur[ended & (nxt == cur)]):
                out[i][int(t)] = 0.0
    return tuple(tuple(t) for t in out)


class WindowData:
    """One split's dynamics view, memory-mapped from the window cache: normalised root and body (float32), tokens,
    progress and, when asked, terrain features and the relative feature, per segment (segments in
    ``corpus.segment_ids(split)`` order). A pickle of it holds how to open it, not its arrays."""

    def __init__(
        self,
        corpus: Corpus | Path | str,
        split: str = "train",
        *,
        terrain: bool = False,
        relative: bool = False,
        normaliser: Normaliser | None = None,
        tokens: ActionTokens | None = None,
        fps: float = DEFAULT_FPS,
        method: str = "linear",
    ):
        c = as_corpus(corpus)
        self.corpus, self.split, self.terrain, self.fps, self.method = c, split, terrain, fps, method
        self.relative = relative
        self.layout = c.layout
        self.normaliser = normaliser or Normaliser.from_corpus(c)
        if self.normaliser.layout_hash != c.layout.hash:
            raise SchemaError(
                f"{c.path}: the normaliser was made for layout {self.normaliser.layout_hash}, the corpus is {c.layout.hash}"
            )
        self.tokens = tokens or ActionTokens.from_corpus(c)
        self.segments: list[str] = c.segment_ids(split)
        rows = {r["segment"]: r for r in c.segments.to_pylist()}
        self.root: list[np.ndarray] = []  # per segment (n, root_dim) float32, normalised
        self.body: list[np.ndarray] = []  # (n, body_dim)
        self.action: list[np.ndarray] = []  # (n, N) int64
        self.progress: list[np.ndarray] = []  # (n, N) float32
        self.features: list[np.ndarray | None] = []  # (n, N, 132) float32
        self.known: list[np.ndarray | None] = []  # (n, N, 132) bool
        self.rel: list[np.ndarray | None] = []  # (n, N, 3) float32, the relative feature
        by_shard: dict[int, list[str]] = {}
        for s in self.segments:
            by_shard.setdefault(int(rows[s]["shard"]), []).append(s)
        loaded: dict[str, tuple] = {}
        for shard, segs in sorted(by_shard.items()):
            arrays, spans = shard_windows(
                c, shard, self.normaliser, self.tokens, terrain=terrain, relative=relative, fps=fps, method=method
            )
            for s in segs:
                if s not in spans:
                    raise SchemaError(f"{c.path}: segment {s} has no rows in the dynamics view of shard {shard}")
                a, b = spans[s]
                loaded[s] = tuple(None if arrays.get(k) is None else arrays[k][a:b] for k in WINDOW_ARRAYS)
        for s in self.segments:
            r, b, t, p, f, k, rl = loaded[s]
            self.root.append(r)
            self.body.append(b)
            self.action.append(t)
            self.progress.append(p)
            self.features.append(f)
            self.known.append(k)
            self.rel.append(rl)
        self.lengths = np.asarray([len(r) for r in self.root], np.int64)

    def __getstate__(self) -> dict[str, Any]:
        """What a pickle holds (a DataLoader worker under ``spawn``): how to open the data, not its arrays."""
        return {
            "corpus": str(self.corpus.path),
            "split": self.split,
            "terrain": self.terrain,
            "relative": self.relative,
            "normaliser": self.normaliser,
            "tokens": self.tokens,
            "fps": self.fps,
            "method": self.method,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Re-open the pickled data's window arrays, memory-mapped from the cache (computed if it is gone)."""
        corpus, split = state.pop("corpus"), state.pop("split")
        self.__init__(corpus, split, **state)  # type: ignore[misc]

    def usable(self, frames: int) -> list[int]:
        """Indices of the segments holding at least ``frames`` dynamics frames."""
        return [i for i, n in enumerate(self.lengths) if n >= frames]

    def check_window(self, frames: int) -> list[int]:
        """``usable(frames)``, or a ValueError naming the longest segment when none is long enough."""
        if frames < 2:
            raise ValueError(f"a window needs at least 2 frames (length ≥ 1 step), not {frames}")
        ok = self.usable(frames)
        if not ok:
            if not self.segments:
                raise ValueError(f"{self.corpus.path}: split {self.split!r} has no segments")
            i = int(np.argmax(self.lengths))
            raise ValueError(
                f"{self.corpus.path}: a window of {frames} frames (length {frames - 1} + 1) at {self.fps:g} fps is longer "
                f"than every {self.split!r} segment; the longest, {self.segments[i]}, has {self.lengths[i]} frames"
            )
        return ok

    def batch(self, windows: Sequence[tuple[int, int]], frames: int) -> Batch:
        """Stack windows (segment index, first frame) of ``frames`` frames into a ``Batch``."""

        def stack(parts: list[np.ndarray | None]) -> Tensor:
            return torch.from_numpy(np.stack([p[s : s + frames] for p, (_, s) in zip(parts, windows)]))  # type: ignore[index]

        for i, s in windows:
            if s < 0 or s + frames > self.lengths[i]:
                raise IndexError(f"window [{s}, {s + frames}) outside segment {self.segments[i]} of {self.lengths[i]} frames")
        pick = [i for i, _ in windows]
        terrain = known = None
        if self.terrain:
            terrain = stack([self.features[i] for i in pick])  # (B, W, N, 132)
            known = stack([self.known[i] for i in pick])
        frames_ = Frames(
            root=stack([self.root[i] for i in pick]),  # (B, W, root_dim)
            body=stack([self.body[i] for i in pick]),  # (B, W, body_dim)
            tokens=stack([self.action[i] for i in pick]),  # (B, W, N) int64
            progress=stack([self.progress[i] for i in pick]),  # (B, W, N)
            terrain=terrain,
            relative=stack([self.rel[i] for i in pick]) if self.relative else None,  # (B, W, N, 3)
        )
        return Batch(frames_, known, tuple(self.segments[i] for i in pick), tuple(int(s) for _, s in windows))


class WindowSampler:
    """Random training windows of ``length`` steps (+1 frame) from the train split, per (seed, rank,
    world_size, epoch); ranks get disjoint windows and equal batch counts (module doc: the rule)."""

    def __init__(self, data: WindowData, length: int, batch_size: int, *, seed: int = 0, rank: int = 0, world_size: int = 1):
        if data.split != "train":
            raise ValueError(f"training windows come from the train split only; this data is split {data.split!r}")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world size {world_size}")
        if batch_size < 1:
            raise ValueError(f"batch_size {batch_size} must be ≥ 1")
        self.data, self.length, self.batch_size = data, int(length), int(batch_size)
        self.seed, self.rank, self.world_size = int(seed), int(rank), int(world_size)
        self.frames = self.length + 1
        self.usable = data.check_window(self.frames)
        self.skipped = [data.segments[i] for i in range(len(data.segments)) if i not in set(self.usable)]
        W = self.frames
        fewest = sum((int(n) - min(W - 1, int(n) - W)) // W for n in data.lengths[self.usable])  # every phase at its largest
        if fewest // world_size < batch_size:
            raise ValueError(
                f"{data.corpus.path}: an epoch may hold only {fewest} windows of {W} frames, fewer than "
                f"batch_size {batch_size} × world_size {world_size}; use shorter windows or smaller batches"
            )

    def epoch_windows(self, epoch: int) -> list[tuple[int, int]]:
        """Every window (segment index, first frame) of ``epoch`` over all ranks, in the shuffled order the
        ranks deal from (module doc: which of them are trained on)."""
        rng = np.random.default_rng([self.seed, int(epoch)])
        W, every = self.frames, []
        for i in self.usable:
            n = int(self.data.lengths[i])
            phase = int(rng.integers(0, min(W - 1, n - W) + 1))
            every += [(i, s) for s in range(phase, n - W + 1, W)]
        return [every[k] for k in rng.permutation(len(every))]

    def windows(self, epoch: int) -> list[tuple[int, int]]:
        """This rank's windows (segment index, first frame) of ``epoch``, in batch order."""
        every = self.epoch_windows(epoch)
        per_rank = len(every) // self.world_size
        mine = every[: per_rank * self.world_size][self.rank :: self.world_size]
        return mine[: (per_rank // self.batch_size) * self.batch_size]

    def batches(self, epoch: int) -> int:
        """Number of batches this rank (and every rank) gets in ``epoch``."""
        return len(self.windows(epoch)) // self.batch_size

    def epoch(self, epoch: int) -> Iterator[Batch]:
        """This rank's batches of ``epoch``."""
        wins = self.windows(epoch)
        for k in range(0, len(wins), self.batch_size):
            yield self.data.batch(wins[k : k + self.batch_size], self.frames)

    def stream(self, step: int = 0, part: int = 0, parts: int = 1) -> Iterator[Batch]:
        """This rank's batches from global step ``step`` on, epoch after epoch without end; with ``parts`` > 1
        only the j-th (j = 0, 1, … counted from ``step``) with j ≡ ``part`` (mod ``parts``), the share of
        DataLoader worker ``part`` of ``parts`` (module doc: loader workers)."""
        if not 0 <= part < parts:
            raise ValueError(f"part {part} outside {parts} parts")
        epoch, skip, j, bs = 0, int(step), 0, self.batch_size
        while True:
            wins = self.windows(epoch)
            n = len(wins) // bs
            for k in range(skip, n):
                if j % parts == part:
                    yield self.data.batch(wins[k * bs : (k + 1) * bs], self.frames)
                j += 1
            skip, epoch = max(0, skip - n), epoch + 1


class TrainBatches(IterableDataset):
    """A rank's training batches from global step ``step`` on (``WindowSampler.stream``), for a
    ``DataLoader(batch_size=None)``: in worker w of k only the batches j ≡ w (mod k), which the DataLoader
    interleaves back into the in-process order (module doc: loader workers)."""

    def __init__(self, sampler: WindowSampler, step: int = 0):
        super().__init__()
        self.sampler, self.step = sampler, int(step)

    def __iter__(self) -> Iterator[Batch]:
        info = get_worker_info()
        return self.sampler.stream(self.step) if info is None else self.sampler.stream(self.step, info.id, info.num_workers)


def train_batches(sampler: WindowSampler, step: int = 0, workers: int = 0) -> Generator[Batch, None, None]:
    """The sampler's batches from global step ``step`` on, stacked in this process (``workers`` 0) or by
    ``workers`` DataLoader worker processes; the same batches in the same order either way. Close the
    generator (or drop it) to stop the workers."""
    if workers < 0:
        raise ValueError(f"loader workers must be ≥ 0, not {workers}")
    return sampler.stream(step) if workers == 0 else _loader_batches(sampler, step, workers)


def _loader_batches(sampler: WindowSampler, step: int, workers: int) -> Generator[Batch, None, None]:
    # The loader's own generator: its seed draw leaves torch's global RNG (dropout's) as it was.
    loader = DataLoader(
        TrainBatches(sampler, step), batch_size=None, num_workers=workers, in_order=True, generator=torch.Generator()
    )
    it = iter(loader)
    try:
        yield from it
    finally:
        del it  # the last reference: its workers are shut down now, not at the next garbage collection


class HeldOutWindows:
    """Every whole window of ``length`` steps (+1 frame) of a held-out split, tiled from each segment's
    start, in a fixed order (no randomness); rank r of world_size gets every world_size-th window."""

    def __init__(self, data: WindowData, length: int, batch_size: int, *, rank: int = 0, world_size: int = 1):
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world size {world_size}")
        self.data, self.length, self.batch_size, self.frames = data, int(length), int(batch_size), int(length) + 1
        W = self.frames
        self.usable = data.usable(W) if data.segments else []
        self.skipped = [data.segments[i] for i in range(len(data.segments)) if i not in set(self.usable)]
        every = [(i, s) for i in self.usable for s in range(0, int(data.lengths[i]) - W + 1, W)]
        self._windows = every[rank::world_size]

    def windows(self) -> list[tuple[int, int]]:
        """This rank's windows (segment index, first frame), in order."""
        return list(self._windows)

    def __len__(self) -> int:
        return -(-len(self._windows) // self.batch_size)

    def __iter__(self) -> Iterator[Batch]:
        for k in range(0, len(self._windows), self.batch_size):
            yield self.data.batch(self._windows[k : k + self.batch_size], self.frames)
