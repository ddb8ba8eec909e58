"""Reading a corpus: metadata, state shards (layout-checked), segments, and derived views."""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from marionette import geometry as geo
from marionette.corpus import paths
from marionette.corpus.info import CorpusInfo
from marionette.io import read_ipc, read_json, text_sha256, write_ipc
from marionette.schema import Layout, SchemaError, check_layout, layout_from_json, load_scene, state_schema

RESAMPLE_VERSION = "1"

MODEL_FPS = 20.0  # the rate the dynamics models step at: the dynamics view's default rate


class Corpus:
    """A built corpus directory. ``expect`` (a Layout or scene name) makes every read check the layout.

    A corpus may hold several scenes (``marionette ingest --scene auto``: each recording the layout of what it
    holds). ``scene`` picks one: the corpus then reads as that scene's alone (its segments, shards, layout, vocab
    and stats), which is what the dynamics model and the evaluation need. Without one, a corpus of one scene is
    that scene; a corpus of several reads every segment and shard (``layout_of_shard`` gives each its layout,
    which the terrain scan, the pose pass and the observation model use) and ``layout`` is an error naming them."""

    def __init__(self, path: Path, expect: Layout | str | None = None, scene: str | None = None):
        self.path = Path(path)
        info = paths.meta(self.path, paths.INFO)
        if not info.exists():
            raise FileNotFoundError(f"{info}: not a corpus (run `marionette ingest` first)")
        self.info = CorpusInfo.read(info)
        if self.info.layouts:
            self.layouts = {
                name: layout_from_json({k: v for k, v in d.items() if k != "hash"})
                for name, d in sorted(self.info.layouts.items())
            }
        elif self.info.layout:
            one = layout_from_json({k: v for k, v in self.info.layout.items() if k != "hash"})
            self.layouts = {one.scene: one}
        else:  # ingested with scene auto, nothing in it yet
            self.layouts = {}
        if scene is not None and scene not in self.layouts:
            raise SchemaError(f"{self.path}: no scene {scene!r}; it holds {', '.join(self.layouts)}")
        self.scene = scene if scene is not None else (next(iter(self.layouts)) if len(self.layouts) == 1 else None)
        self._shard_cache: dict[int, pa.Table] = {}
        if expect is not None:
            want = load_scene(expect) if isinstance(expect, str) else expect
            if want.hash != self.layout.hash:
                raise SchemaError(
                    f"{self.path}: corpus layout {self.layout.scene!r} (dim {self.layout.dim}, hash {self.layout.hash}) "
                    f"does not match the expected layout {want.scene!r} (dim {want.dim}, hash {want.hash})"
                )

    @property
    def layout(self) -> Layout:
        """The layout of the corpus's scene (or of the one chosen)."""
        if self.scene is None:
            if not self.layouts:
                raise SchemaError(f"{self.path}: the corpus holds no recording yet, so no scene")
            raise SchemaError(
                f"{self.path}: the corpus holds {len(self.layouts)} scenes ({', '.join(self.layouts)}): choose one (--scene)"
            )
        return self.layouts[self.scene]

    @property
    def many(self) -> bool:
        """Whether the corpus holds more than one scene."""
        return len(self.layouts) > 1

    @cached_property
    def all_segments(self) -> pa.Table:
        """Every segment of every scene."""
        return pq.read_table(paths.meta(self.path, paths.SEGMENTS))

    @cached_property
    def segments(self) -> pa.Table:
        """The segments (of the chosen scene, in a corpus of several)."""
        t = self.all_segments
        if self.many and self.scene is not None:
            t = t.filter(pc.equal(t["scene"], self.scene))
        return t

    def layout_of_shard(self, shard: int) -> Layout:
        """The layout of one state shard: its recording's scene."""
        if not self.many:
            return next(iter(self.layouts.values()))
        t = self.all_segments
        rows = t.filter(pc.equal(t["shard"], int(shard)))
        if rows.num_rows == 0:
            raise KeyError(f"{self.path}: no segment in shard {shard}")
        return self.layouts[rows["scene"][0].as_py()]

    @cached_property
    def samples(self) -> pa.Table:
        return pq.read_table(paths.meta(self.path, paths.SAMPLES))

    @cached_property
    def quarantine(self) -> pa.Table:
        return pq.read_table(paths.meta(self.path, paths.QUARANTINE))

    def _per_scene(self, name: str) -> dict:
        d = read_json(paths.meta(self.path, name))
        if self.many:
            return d["scenes"][self.layout.scene]  # a corpus of several scenes keeps one per scene
        return d

    @cached_property
    def vocab(self) -> dict:
        return self._per_scene(paths.VOCAB)

    @cached_property
    def stats(self) -> dict:
        return self._per_scene(paths.STATS)

    @property
    def fps(self) -> float:
        return self.info.source_fps

    def state_path(self, shard: int) -> Path:
        return paths.state_shard(self.path, shard)

    def video_path(self, shard: int) -> Path:
        return paths.video_shard(self.path, shard)

    def pose_path(self, shard: int, jitter: str | None = None) -> Path:
        return paths.pose_shard(self.path, shard, jitter)

    def shard_ids(self) -> list[int]:
        if self.many and self.scene is not None:
            return sorted(set(self.segments["shard"].to_pylist()))
        return sorted(self.info.shards)

    def read_shard(self, shard: int) -> pa.Table:
        """A state shard, its layout checked against the corpus layout (the last two read are kept,
        so reading a shard's segments one by one decompresses it once)."""
        if shard in self._shard_cache:
            return self._shard_cache[shard]
        path = self.state_path(shard)
        layout = self.layout_of_shard(shard)
        segs = self.all_segments
        rows = int(pc.sum(segs.filter(pc.equal(segs["shard"], shard))["frames"]).as_py() or 0)
        table = read_ipc(path, rows, lambda schema: check_layout(schema, layout, str(path)))
        self._shard_cache[shard] = table
        while len(self._shard_cache) > 2:
            self._shard_cache.pop(next(iter(self._shard_cache)))
        return table

    def segment_ids(self, split: str | None = None) -> list[str]:
        seg = self.segments
        if split is not None:
            seg = seg.filter(pc.equal(seg["split"], split))
        return seg["segment"].to_pylist()

    def segment_row(self, segment: str) -> dict:
        rows = self.segments.filter(pc.equal(self.segments["segment"], segment)).to_pylist()
        if not rows:
            raise KeyError(f"{self.path}: no segment {segment!r}")
        return rows[0]

    def stage_of(self, segment: str) -> str:
        """The stage a segment was recorded on."""
        return self.segment_row(segment)["stage"]

    def read_segment(self, segment: str) -> pa.Table:
        """All source-rate rows of one segment."""
        row = self.segment_row(segment)
        t = self.read_shard(row["shard"])
        return t.filter(pc.equal(t["segment"], segment))

    def shard_hash(self, shard: int) -> str:
        """Content hash of a state shard as recorded when it was ingested."""
        rows = self.samples.filter(pc.equal(self.samples["shard"], shard)).to_pylist()
        if not rows or not rows[0]["state_hash"]:
            raise KeyError(f"{self.path}: no ingested sample holds shard {shard}")
        return rows[0]["state_hash"]

    # -- derived: the dynamics view ----------------------------------------------------------------

    def dynamics_dir(self, fps: float = MODEL_FPS, method: str = "linear") -> Path:
        return paths.derived(self.path, f"dynamics-{fps:g}fps-{method}")

    def dynamics_shard(self, shard: int, fps: float = MODEL_FPS, method: str = "linear") -> pa.Table:
        """The shard resampled to ``fps`` (cached under derived/, recomputed when its source changes)."""
        key = text_sha256(self.shard_hash(shard), f"{fps:g}", method, RESAMPLE_VERSION, self.layout.hash)[:16]
        path = self.dynamics_dir(fps, method) / f"shard-{shard:06d}-{key}.arrow"
        if path.exists():
            return read_ipc(path, check_schema=lambda schema: check_layout(schema, self.layout, str(path)))
        src = self.read_shard(shard)
        parts = [
            resample_segment(self.layout, src.filter(pc.equal(src["segment"], s)), fps, method)
            for s in pc.unique(src["segment"]).to_pylist()
        ]
        table = pa.concat_tables(parts) if parts else state_schema(self.layout).empty_table()
        write_ipc(path, table, self.info.compression)
        for old in path.parent.glob(f"shard-{shard:06d}-*.arrow"):  # views of an older version of the shard
            if old != path:
                old.unlink(missing_ok=True)
        return table

    def dynamics_segment(self, segment: str, fps: float = MODEL_FPS, method: str = "linear") -> pa.Table:
        t = self.dynamics_shard(self.segment_row(segment)["shard"], fps, method)
        return t.filter(pc.equal(t["segment"], segment))


def state_table(layout: Layout, columns: dict, n: int | None = None) -> pa.Table:
    """A state-shard table built from ``state_schema(layout)``: every field from ``columns`` (numpy arrays, lists or
    Arrow arrays; a fixed-size-list field from an (n, width) array, a scalar broadcast to ``n`` rows). A missing or
    unknown column is an error naming it."""
    schema = state_schema(layout)
    missing = [f.name for f in schema if f.name not in columns]
    extra = sorted(set(columns) - set(schema.names))
    if missing or extra:
        raise SchemaError(f"state table for layout {layout.scene!r}: missing columns {missing}, unknown columns {extra}")
    arrays = []
    for f in schema:
        v = columns[f.name]
        if n is not None and np.ndim(v) == 0 and not isinstance(v, pa.Array):
            v = [v] * n
        if isinstance(v, pa.Array | pa.ChunkedArray):
            arrays.append(v.cast(f.type) if v.type != f.type else v)
        elif pa.types.is_fixed_size_list(f.type):
            flat = np.ascontiguousarray(v, f.type.value_type.to_pandas_dtype()).reshape(-1)
            arrays.append(pa.FixedSizeListArray.from_arrays(pa.array(flat, f.type.value_type), f.type.list_size))
        else:
            arrays.append(pa.array(v, f.type))
    return pa.Table.from_arrays(arrays, schema=schema)


def fixed_rows(col: pa.ChunkedArray, width: int) -> np.ndarray:
    """A fixed-size-list column as an (n, width) array (zero-copy where Arrow allows)."""
    arr = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    return arr.values.to_numpy(zero_copy_only=False).reshape(-1, width)


def world_of_rows(layout: Layout, table: pa.Table) -> dict[str, np.ndarray]:
    """World kept joints per entity of state rows, from the recorded roots and rotations (float64)."""
    n = table.num_rows
    state = fixed_rows(table["state"], layout.dim).astype(np.float64)
    out: dict[str, np.ndarray] = {}
    frames = {}
    for e in layout.articulated:
        x = fixed_rows(table[f"{e.name}.root_world"], 3)
        R = geo.quat_to_matrix(fixed_rows(table[f"{e.name}.rot_world"], 4))
        frames[e.name] = (x, R)
        local = state[:, layout.slice(f"{e.name}.joints")].reshape(n, -1, 3)
        out[e.name] = np.concatenate([x[:, None], geo.to_world(local, x, R)], axis=1)
    for e in layout.attachments:
        x, R = frames[e.owner]
        out[e.name] = geo.to_world(state[:, layout.slice(f"{e.name}.points")].reshape(n, -1, 3), x, R)
    return out


def resample_segment(layout: Layout, seg: pa.Table, fps: float, method: str = "linear") -> pa.Table:
    """One segment's rows resampled to ``fps``: world positions interpolated in time, root rotations
    by slerp with sign continuity, discrete fields from the source frame at or before t; the state is
    then re-derived from the resampled world skeletons."""
    if seg.num_rows == 0:
        return seg
    t_src = seg["t"].to_numpy()
    n_out = int(np.floor((t_src[-1] - t_src[0]) * fps + 1e-6)) + 1
    t_dst = t_src[0] + np.arange(n_out) / fps
    world = world_of_rows(layout, seg)
    joints, rots = {}, {}
    for e in layout.entities:
        joints[e.name] = geo.resample_positions(t_src, world[e.name], t_dst, method)
    for e in layout.articulated:
        rots[e.name] = geo.resample_quats(t_src, fixed_rows(seg[f"{e.name}.rot_world"], 4), t_dst, method)
    state = geo.world_to_state(layout, joints, rots)
    idx = geo.index_at_or_before(t_src, t_dst)
    out = seg.take(pa.array(idx))
    cols = {name: out[name].combine_chunks() for name in out.column_names}
    cols["t"] = t_dst
    cols["state"] = state
    for e in layout.articulated:
        cols[f"{e.name}.root_world"] = joints[e.name][:, 0]
        cols[f"{e.name}.rot_world"] = rots[e.name]
    cols["camera.pos"] = geo.resample_positions(t_src, fixed_rows(seg["camera.pos"], 3), t_dst, method)
    cols["camera.rot"] = geo.resample_quats(t_src, fixed_rows(seg["camera.rot"], 4), t_dst, method)
    return state_table(layout, cols)


def as_corpus(corpus: Corpus | Path | str, scene: str | None = None) -> Corpus:
    """``corpus`` itself, or the Corpus at that path (its scene ``scene``, in a corpus of several)."""
    return corpus if isinstance(corpus, Corpus) else Corpus(Path(corpus), scene=scene)
