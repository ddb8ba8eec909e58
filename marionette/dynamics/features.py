"""The dynamics models' per-frame features beyond the state: the relative position and the terrain.

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
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from marionette import geometry as geo
from marionette.corpus import MODEL_FPS, RESAMPLE_VERSION, Corpus, as_corpus, fixed_rows, paths, world_of_rows
from marionette.corpus.vocab import ActionTokens, entity_type_key  # noqa: F401 — the models' token tables
from marionette.dynamics.config import N_CLEARANCES, PATCH_SIZE, TERRAIN_FEATURES
from marionette.io import read_ipc, text_sha256, write_ipc
from marionette.schema import Layout, SchemaError
from terrain_scan.field import LayeredField, egocentric_patch, joint_clearances, open_stage
from terrain_scan.store import stage_terrain

FEATURE_VERSION = "1"


PATCH_CELL_M = 0.4


PATCH_AHEAD_M = 1.0


RELATIVE_SCALE_M = 5.0  # the relative feature's unit: fighters stand a few metres apart


TERRAIN_DIR = "terrain-features"


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


def terrain_feature_path(corpus: Corpus | Path | str, shard: int, fps: float = MODEL_FPS, method: str = "linear") -> Path:
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
    corpus: Corpus | Path | str, shard: int, fps: float = MODEL_FPS, method: str = "linear"
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
