"""Reading a corpus: metadata, state shards (layout-checked), segments, and derived views."""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from marionette import geometry as geo
from marionette.corpus import paths
from marionette.io import read_ipc, text_sha256, write_ipc
from marionette.schema import Layout, SchemaError, check_layout, layout_from_json, load_scene, state_schema

RESAMPLE_VERSION = "1"


class Corpus:
    """A built corpus directory. ``expect`` (a Layout or scene name) makes every read check the layout."""

    def __init__(self, path: Path, expect: Layout | str | None = None):
        self.path = Path(path)
        info = self.path / "meta" / "info.json"
        if not info.exists():
            raise FileNotFoundError(f"{info}: not a corpus (run `marionette ingest` first)")
        self.info = json.loads(info.read_text())
        self.layout = layout_from_json({k: v for k, v in self.info["layout"].items() if k != "hash"})
        self._shard_cache: dict[int, pa.Table] = {}
        if expect is not None:
            want = load_scene(expect) if isinstance(expect, str) else expect
            if want.hash != self.layout.hash:
                raise SchemaError(
                    f"{self.path}: corpus layout {self.layout.scene!r} (dim {self.layout.dim}, hash {self.layout.hash}) "
                    f"does not match the expected layout {want.scene!r} (dim {want.dim}, hash {want.hash})"
                )

    @cached_property
    def segments(self) -> pa.Table:
        return pq.read_table(self.path / "meta" / "segments.parquet")

    @cached_property
    def samples(self) -> pa.Table:
        return pq.read_table(self.path / "meta" / "samples.parquet")

    @cached_property
    def quarantine(self) -> pa.Table:
        return pq.read_table(self.path / "meta" / "quarantine.parquet")

    @cached_property
    def vocab(self) -> dict:
        return json.loads((self.path / "meta" / "vocab.json").read_text())

    @cached_property
    def stats(self) -> dict:
        return json.loads((self.path / "meta" / "stats.json").read_text())

    @property
    def fps(self) -> float:
        return float(self.info["fps"] if not isinstance(self.info["fps"], list) else self.info["fps"][0])

    def state_path(self, shard: int) -> Path:
        return paths.state_shard(self.path, shard)

    def video_path(self, shard: int) -> Path:
        return paths.video_shard(self.path, shard)

    def shard_ids(self) -> list[int]:
        where = str(self.path / "meta" / "info.json")
        return sorted(paths.check_shard(n, where) for n in self.info["shards"])

    def read_shard(self, shard: int) -> pa.Table:
        """A state shard, its layout checked against the corpus layout (the last two read are kept,
        so reading a shard's segments one by one decompresses it once)."""
        if shard in self._shard_cache:
            return self._shard_cache[shard]
        path = self.state_path(shard)
        table = read_ipc(path)
        check_layout(table.schema, self.layout, str(path))
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

    def dynamics_dir(self, fps: float = 20.0, method: str = "linear") -> Path:
        return self.path / "derived" / f"dynamics-{fps:g}fps-{method}"

    def dynamics_shard(self, shard: int, fps: float = 20.0, method: str = "linear") -> pa.Table:
        """The shard resampled to ``fps`` (cached under derived/, recomputed when its source changes)."""
        key = text_sha256(self.shard_hash(shard), f"{fps:g}", method, RESAMPLE_VERSION, self.layout.hash)[:16]
        path = self.dynamics_dir(fps, method) / f"shard-{shard:06d}-{key}.arrow"
        if path.exists():
            table = read_ipc(path)
            check_layout(table.schema, self.layout, str(path))
            return table
        src = self.read_shard(shard)
        parts = [
            resample_segment(self.layout, src.filter(pc.equal(src["segment"], s)), fps, method)
            for s in pc.unique(src["segment"]).to_pylist()
        ]
        table = pa.concat_tables(parts) if parts else state_schema(self.layout).empty_table()
        write_ipc(path, table, self.info["ingest"].get("compression", "zstd"))
        for old in path.parent.glob(f"shard-{shard:06d}-*.arrow"):  # views of an older version of the shard
            if old != path:
                old.unlink(missing_ok=True)
        return table

    def dynamics_segment(self, segment: str, fps: float = 20.0, method: str = "linear") -> pa.Table:
        t = self.dynamics_shard(self.segment_row(segment)["shard"], fps, method)
        return t.filter(pc.equal(t["segment"], segment))


def _fixed(col: pa.ChunkedArray, width: int) -> np.ndarray:
    arr = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    return arr.values.to_numpy(zero_copy_only=False).reshape(-1, width)


def world_of_rows(layout: Layout, table: pa.Table) -> dict[str, np.ndarray]:
    """World kept joints per entity of state rows, from the recorded roots and rotations (float64)."""
    n = table.num_rows
    state = _fixed(table["state"], layout.dim).astype(np.float64)
    out: dict[str, np.ndarray] = {}
    frames = {}
    for e in layout.articulated:
        x = _fixed(table[f"{e.name}.root_world"], 3)
        R = geo.quat_to_matrix(_fixed(table[f"{e.name}.rot_world"], 4))
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
        rots[e.name] = geo.resample_quats(t_src, _fixed(seg[f"{e.name}.rot_world"], 4), t_dst, method)
    state = geo.world_to_state(layout, joints, rots)
    idx = geo.index_at_or_before(t_src, t_dst)
    out = seg.take(pa.array(idx))
    cols = {name: out[name] for name in out.column_names}
    cols["t"] = pa.array(t_dst)
    cols["state"] = pa.FixedSizeListArray.from_arrays(pa.array(state.reshape(-1), pa.float32()), layout.dim)

    def fixed(x: np.ndarray, w: int) -> pa.Array:
        return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(x, np.float64).reshape(-1)), w)

    for e in layout.articulated:
        cols[f"{e.name}.root_world"] = fixed(joints[e.name][:, 0], 3)
        cols[f"{e.name}.rot_world"] = fixed(rots[e.name], 4)
    cam_pos = geo.resample_positions(t_src, _fixed(seg["camera.pos"], 3), t_dst, method)
    cam_rot = geo.resample_quats(t_src, _fixed(seg["camera.rot"], 4), t_dst, method)
    cols["camera.pos"] = fixed(cam_pos, 3)
    cols["camera.rot"] = fixed(cam_rot, 4)
    return pa.Table.from_pydict(cols, schema=seg.schema)
