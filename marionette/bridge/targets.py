"""Pose-control targets: every video chunk's ``pose.gbz``, rendered from recorded state with the recorded
camera, cached as a derived product and gathered into the pose shards beside the video shards.

A chunk's target is keyed by what it is computed from (DESIGN "The corpus"): the chunk's state rows
(their content hash), the sha256 of every terrain chunk its cameras can see (frustum against the
chunk's bounding box, over all the chunk's frames), the stage's height range, ``BRIDGE_VERSION`` and
the render settings. The pose shards (``pose/shard-NNNNNN.tar``, ``video_shards``: ``<key>.pose.json`` and
``<key>.pose.gbz`` per chunk, in the video shard's order) are the one copy of the targets and their cache: a pass
takes a chunk's target from its pose shard when the shard's record of it has the same key, renders the others
into ``<corpus>/derived/pose/<segment>__c<chunk>-<key>.gbz`` (files a pass killed before its shard was written
are taken up by the next), rewrites (atomically) only the pose shards whose members change, and then deletes the
rendered files its shards now hold. A pass reads the video shards' ``json`` members only and never writes a video
shard: a terrain re-scan that changes one chunk re-renders only the video chunks that see it, rewrites only their
pose shards, and leaves every RGB byte where it was; a pass with nothing new writes nothing and reads no target.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import pyarrow as pa

from marionette.corpus import Corpus, fixed_rows, paths, video_shards
from marionette.corpus.lock import corpus_lock
from marionette.fanout import pool_mapper, threads_per_worker, worker_identity
from marionette.geometry import resample_positions, resample_quats
from marionette.io import file_sha256, text_sha256
from marionette.recordings.wildworld import RGB_FILE
from marionette.schema import Entity, Layout
from marionette.video import CropResize
from terrain_scan.layers import Observations
from terrain_scan.mesh import tessellate
from terrain_scan.store import Stage, chunk_observations, parse_chunk_name, stage_terrain
from terrain_scan.trn2 import CELLS, find_chunks, read_chunk

from .camera import Cameras, follow_cameras, recorded_cameras
from .gbuffer import GBufferMeta, write_gbuffer
from .jitter import Jitter
from .kinematics import bone_capsules, world_skeletons
from .render import TERRAIN_CULL_M, Rasterizer, llvmpipe_threads

BRIDGE_VERSION = "4"  # what the renderer draws: a change of it re-renders every target
PLAYER_EDGES_KEY = "npc"  # WildWorld's skeleton key of the player character (the hunter rig)


@dataclass(frozen=True)
class RenderSettings:
    """Depth range (m) of the render and its terrain culling; heights span the stage's terrain range
    widened by the margins (m) below and above (characters stand, and jump, above the ground)."""

    z_near: float = 0.3
    z_far: float = 100.0
    cull_m: float = TERRAIN_CULL_M
    margin_below_m: float = 2.0
    margin_above_m: float = 10.0

    def key(self) -> str:
        return text_sha256(json.dumps(asdict(self), sort_keys=True))[:16]


@dataclass
class TerrainScene:
    """A stage's terrain as the bridge uses it: its mesh, its chunks' boxes and hashes, its height range."""

    vertices: np.ndarray  # (V, 3) float64 world
    faces: np.ndarray  # (F, 3)
    boxes: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # "cx_cz" → (lo (3,), hi (3,))
    hashes: dict[str, str] = field(default_factory=dict)  # "cx_cz" → sha256 of the chunk file
    h_range: tuple[float, float] | None = None  # (lowest, highest) layer height, None without terrain

    @staticmethod
    def empty() -> TerrainScene:
        return TerrainScene(np.zeros((0, 3)), np.zeros((0, 3), np.int64))

    @staticmethod
    def of_stage(stage) -> TerrainScene:
        """A stage's TRN2 chunks (as its checked manifest lists them) as a mesh, boxes and hashes; ``stage`` is a
        ``terrain_scan.store.Stage`` (``Corpus.terrain``), a stage directory (with a manifest, or the upstream
        release's ``c_<cx>_<cz>.bin`` chunks: ``trn2.find_chunks``, which names a directory holding neither), or
        None (no terrain)."""

        if stage is None:
            return TerrainScene.empty()
        if isinstance(stage, Stage) or (Path(stage) / "manifest.json").exists():
            files = (stage if isinstance(stage, Stage) else Stage(stage)).chunk_files()
        else:
            found = find_chunks(Path(stage))
            files = {f"{cx}_{cz}": (p, file_sha256(p)) for (cx, cz), p in found.items()}
            files = dict(sorted(files.items()))
        parts, boxes, hashes = [], {}, {}
        for name, (file, digest) in files.items():
            ch = read_chunk(file, at=parse_chunk_name(name, str(file)))
            layers = chunk_observations(ch, filled=True)
            if not len(layers):
                continue
            parts.append(layers)
            h = layers.h
            boxes[name] = (
                np.array([ch.cx * CELLS, h.min(), ch.cz * CELLS]),
                np.array([(ch.cx + 1) * CELLS, h.max(), (ch.cz + 1) * CELLS]),
            )
            hashes[name] = digest
        if not parts:
            return TerrainScene.empty()
        layers = Observations.concat(parts)
        order = np.lexsort((layers.h, layers.gz, layers.gx))
        V, F = tessellate(layers.take(order))
        return TerrainScene(V, F, boxes, hashes, (float(layers.h.min()), float(layers.h.max())))

    def seen_chunks(self, cams: Cameras, z_near: float, z_far: float) -> list[str]:
        """Terrain chunks whose bounding box meets some valid camera's view frustum (a conservative test)."""
        if not self.boxes:
            return []
        names = sorted(self.boxes)
        lo = np.array([self.boxes[n][0] for n in names])
        hi = np.array([self.boxes[n][1] for n in names])
        seen = np.zeros(len(names), bool)
        for i in np.flatnonzero(cams.valid):
            seen |= cams.boxes_in_view(i, lo, hi, z_near, z_far)
            if seen.all():
                break
        return [n for n, s in zip(names, seen) if s]


def height_range(terrain: TerrainScene, roots_y: np.ndarray, settings: RenderSettings) -> tuple[float, float]:
    """(h_min, h_max) of the render: the terrain's range (else the roots'), widened by the margins."""
    lo, hi = terrain.h_range if terrain.h_range is not None else (float(np.nanmin(roots_y)), float(np.nanmax(roots_y)))
    return float(np.floor(lo - settings.margin_below_m)), float(np.ceil(hi + settings.margin_above_m))


def chunk_inputs(layout: Layout, rows: pa.Table) -> tuple[np.ndarray, dict, dict, np.ndarray]:
    """State (n, D) float64, anchors (row 0's recorded roots), validity, times (s) of a chunk's rows."""
    state = fixed_rows(rows["state"], layout.dim).astype(np.float64)
    valid = rows["valid"].to_numpy(zero_copy_only=False).astype(bool)
    anchors = {e.name: fixed_rows(rows[f"{e.name}.root_world"], 3)[0] for e in layout.articulated}
    return state, anchors, {e.name: valid for e in layout.articulated}, rows["t"].to_numpy().astype(np.float64)


def followed_entities(layout: Layout) -> tuple[Entity, ...]:
    """The articulated entities in the follow camera's order: the player first (the first whose rig's
    ``edges_key`` is ``PLAYER_EDGES_KEY``, else the first articulated entity), then the others in layout order."""
    ents = layout.articulated
    player = next((e for e in ents if e.rig.edges_key == PLAYER_EDGES_KEY), ents[0])
    return (player, *(e for e in ents if e is not player))


def follow_view(layout: Layout, skel, fps: float, width: int, height: int, start: Cameras | None = None) -> Cameras:
    """The follow camera (``camera.follow_cameras``) behind a ``Skeletons``' player, framing the other entity
    (``followed_entities``), optionally seeded."""
    ents = followed_entities(layout)
    fwd = skel.rot[ents[0].name] @ np.asarray(ents[0].rig.forward_axis, np.float64)
    return follow_cameras(
        [skel.joints[e.name][:, 0] for e in ents], fwd, [skel.valid[e.name] for e in ents], fps, width, height, start=start
    )


def render_frames(rast: Rasterizer, layout: Layout, skel, cams: Cameras, h: tuple[float, float], settings: RenderSettings):
    """Yield the G-buffer's packed codes (H, W) uint32 (``Rasterizer.render_packed``) of every frame of ``skel`` seen
    through ``cams``."""
    for i, bones in enumerate(bone_capsules(layout, skel)):
        yield rast.render_packed(cams, i, bones, h[0], h[1], settings.z_near, settings.z_far, settings.cull_m)


@dataclass
class TargetsReport:
    chunks: int = 0
    rendered: list[str] = field(default_factory=list)  # chunk names rendered in this pass
    shards_rewritten: list[int] = field(default_factory=list)  # pose shards written (video shards are never written)
    frames_rendered: int = 0
    failed: dict[str, str] = field(default_factory=dict)  # chunk key or shard → why it has no target
    workers: list[str] = field(default_factory=list)  # where the shards were rendered (``marionette.fanout``)


class _Pass:
    """One pose-target pass's caches: terrain per stage, a rasterizer per size, rows per segment."""

    def __init__(self, corpus: Corpus, settings: RenderSettings, report: TargetsReport, jitter: Jitter | None = None):
        self.corpus, self.settings, self.report = corpus, settings, report
        self.jitter = jitter if jitter is not None and jitter.active else None
        self.jitter_key = None if self.jitter is None else self.jitter.key()
        self.segments = {r["segment"]: r for r in corpus.segments.to_pylist()}
        self.terrains: dict[str, TerrainScene] = {}
        self.rasts: dict[tuple[int, int], Rasterizer] = {}
        self.uploaded: dict[tuple[int, int], str] = {}
        self.rows: dict[str, pa.Table] = {}
        self.keep: set[str] = set()  # rendered files no pose shard holds yet

    def terrain(self, stage: str) -> TerrainScene:
        if stage not in self.terrains:
            self.terrains[stage] = TerrainScene.of_stage(stage_terrain(self.corpus.path, stage))
        return self.terrains[stage]

    def target(self, vpath: Path, key: str, rec: dict, held: dict | None) -> tuple[Path | None, str, list[str]]:
        """The chunk's pose target: (the file it was rendered to, its render key, the terrain chunks seen); the file
        is None where ``held`` (the chunk's current record in its pose shard) has the same key: the shard's copy
        stands."""
        settings = self.settings
        segment = paths.parse_chunk_key(key, str(vpath))[0]
        if segment not in self.segments:
            raise ValueError(f"{vpath}: chunk {key} belongs to no segment of the corpus")
        layout = self.corpus.layout_of_shard(self.segments[segment]["shard"])  # each recording its scene's
        stage = self.segments[segment]["stage"]
        terrain = self.terrain(stage)
        if segment not in self.rows:
            self.rows = {segment: self.corpus.read_segment(segment)}  # chunks of a segment are consecutive
        rows = self.rows[segment]
        frames = rows["frame"].to_numpy()
        a, b = rec["frames"]
        rows = rows.take(np.flatnonzero((frames >= a) & (frames < b)))
        if rows.num_rows != b - a:
            raise ValueError(f"{vpath}: chunk {key} spans frames [{a}, {b}) but its segment has {rows.num_rows} of them")
        out_h, out_w = rec["resize"]
        cams = recorded_cameras(
            np.asarray(rec["K"], np.float64),
            fixed_rows(rows["camera.pos"], 3),
            fixed_rows(rows["camera.rot"], 4),
            rows["valid"].to_numpy(zero_copy_only=False),
            out_w,
            out_h,
        )
        roots_y = np.concatenate([fixed_rows(rows[f"{e.name}.root_world"], 3)[:, 1] for e in layout.articulated])
        h = height_range(terrain, roots_y, settings)
        seen = terrain.seen_chunks(cams, settings.z_near, settings.z_far)
        digest = text_sha256(
            _rows_hash(layout, rows),
            json.dumps([[s, terrain.hashes[s]] for s in seen]),
            json.dumps(h),
            json.dumps(rec["K"]),
            f"{out_h}x{out_w}",
            BRIDGE_VERSION,
            settings.key(),
            *([] if self.jitter is None else [json.dumps(asdict(self.jitter), sort_keys=True)]),
        )[:16]
        if held is not None and held.get("key") == digest:
            return None, digest, seen
        path = paths.pose_target(self.corpus.path, key, digest, self.jitter_key)
        self.keep.add(path.name)
        if not path.exists():  # else a pass killed before writing this shard rendered it
            size = (out_w, out_h)
            if size not in self.rasts:
                self.rasts[size] = Rasterizer(out_w, out_h)
            rast = self.rasts[size]
            if self.uploaded.get(size) != stage:
                rast.set_terrain(terrain.vertices, terrain.faces)
                self.uploaded[size] = stage
            state, anchors, valid, t = chunk_inputs(layout, rows)
            if self.jitter is None:
                skel = world_skeletons(layout, state, anchors, valid, t)
            else:  # the state moved before it is rendered (bridge.jitter), drawn for this chunk
                skel = self.jitter.apply(
                    layout, world_skeletons(layout, state, anchors, valid, t, self.jitter.times(t, key)), key
                )
            meta = GBufferMeta(h[0], h[1], settings.z_near, settings.z_far, out_w, out_h, float(rec["fps"]))
            self.report.frames_rendered += write_gbuffer(path, render_frames(rast, layout, skel, cams, h, settings), meta)
            self.report.rendered.append(key)
        return path, digest, seen

    def shard(
        self, vpath: Path, chunks: dict[str, dict[str, bytes]], state_hash: str, held: video_shards.PoseShard, progress
    ) -> tuple[list[tuple[str, bytes | Path | Callable[[], bytes]]], list[Path], bool]:
        """The pose shard's members for a video shard's chunks (key → {"json": bytes}), every target brought up to
        date (a target ``held`` already holds under its key is read from it when the shard is written), the files
        rendered for it, and whether the members are ``held``'s own; a chunk whose target cannot be rendered gets no
        members and is listed in ``report.failed``."""
        out: list[tuple[str, bytes | Path | Callable[[], bytes]]] = []
        rendered: list[Path] = []
        same = True
        for key, m in chunks.items():
            rec = video_shards.chunk_record(m["json"], key, str(vpath))
            self.report.chunks += 1
            try:
                current = held.member(key, m["json"], state_hash)
            except ValueError:  # a damaged record: its target is rendered again
                current = None
            try:
                target, digest, seen = self.target(vpath, key, rec, None if current is None else current[0])
            except Exception as exc:  # one chunk's failure is recorded; the pass goes on
                self.report.failed[key] = f"{type(exc).__name__}: {exc}"
            else:
                pose = video_shards.pose_record(key, digest, seen, rec["frames"][1] - rec["frames"][0], m["json"], state_hash)
                out.append(
                    (video_shards.member_name(key, video_shards.POSE_RECORD_KIND), json.dumps(pose, sort_keys=True).encode())
                )
                if target is None:  # the shard's copy, read when the new shard is written
                    out.append((video_shards.member_name(key, video_shards.POSE_KIND), partial(held.read, current[1])))
                    same = same and current[0] == pose
                else:
                    out.append((video_shards.member_name(key, video_shards.POSE_KIND), target))
                    rendered.append(target)
                    same = False
            progress(1)
        return out, rendered, same and held.names() == [name for name, _ in out]

    def release(self) -> None:
        for r in self.rasts.values():
            r.release()


@dataclass(frozen=True)
class RenderJob:
    """One video shard's pose targets, for a worker: the corpus and the shard number."""

    corpus: str
    shard: int

    @property
    def name(self) -> str:
        return f"pose-{paths.shard_name(self.shard)}"


@dataclass
class ShardOutcome:
    """What a worker did to one shard: its pass's report, the derived files its chunks use, and where it ran."""

    job: RenderJob
    report: TargetsReport
    keep: set[str]
    worker: str


def render_shard(
    job: RenderJob, settings: RenderSettings, gl_threads: int | None = None, jitter: Jitter | None = None
) -> ShardOutcome:
    """Bring one shard's pose targets up to date in a pass of its own (its own rasterizer and terrain). With
    ``gl_threads``, a worker that has no ``LP_NUM_THREADS`` of its own gives Mesa's llvmpipe that many threads
    (read when the process's first GL context is made: k workers on one machine share its cores)."""

    if gl_threads is not None:
        os.environ.setdefault("LP_NUM_THREADS", llvmpipe_threads(gl_threads))
    corpus = Corpus(Path(job.corpus))
    report = TargetsReport()
    run = _Pass(corpus, settings, report, jitter)
    try:
        _render_shard(run, corpus, job.shard, lambda n: None)
    finally:
        run.release()
    return ShardOutcome(job, report, run.keep, worker_identity())


def _render_shard(run: _Pass, corpus: Corpus, shard: int, progress) -> None:
    """One shard's pose targets through ``run``; its pose shard is rewritten (atomically) when its members change
    (``report.shards_rewritten``). The video shard is only read."""
    vpath, ppath = corpus.video_path(shard), corpus.pose_path(shard, run.jitter_key)
    if not vpath.exists():
        return
    try:
        held = video_shards.PoseShard(ppath)
    except (ValueError, OSError):  # a damaged pose shard is written again
        held = video_shards.PoseShard(ppath, read=False)
    with held:
        try:
            chunks = video_shards.read_chunks(vpath, kinds=("json",))
            members, rendered, same = run.shard(vpath, chunks, corpus.shard_hash(shard), held, progress)
        except (ValueError, OSError, KeyError) as exc:  # an unreadable or untrusted shard: named, left untouched
            run.report.failed[paths.shard_name(shard)] = str(exc)
            return
        if not same:
            video_shards.write_members(ppath, members)
            run.report.shards_rewritten.append(shard)
    for f in rendered:  # now in the pose shard: its one copy
        run.keep.discard(f.name)
        f.unlink(missing_ok=True)


def render_pose_targets(
    corpus_path: Path,
    settings: RenderSettings | None = None,
    progress: bool = False,
    workers: int = 1,
    mapper=None,
    gl_threads: int | None = None,
    jitter: Jitter | None = None,
) -> TargetsReport:
    """Bring every video chunk's pose target up to date (module docstring), holding the corpus lock; a chunk
    or shard that fails is recorded in ``failed`` and the pass goes on. ``progress`` shows a bar over chunks.

    One worker renders every shard in this process, in one pass (one rasterizer, each stage's terrain loaded
    once). Otherwise each shard is a job (``render_shard``) for ``mapper`` (``marionette.fanout``; default: a
    pool of ``workers`` fresh processes, none inheriting this one's GL context; the flows pass one that runs
    on Dask) and the outcomes are merged in shard order: a shard's bytes depend only on its own chunks, so
    every worker count writes the same files and the same report. ``gl_threads``: llvmpipe's threads in each
    worker (``render_shard``); by default the local pool's workers split this machine's cores between them.
    ``jitter`` (active): the targets of jittered state instead (``bridge.jitter``; each chunk's drawn for its
    key), a product of their own under ``corpus.paths.jitter_dir``; the corpus's own targets are not touched.
    """

    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    corpus = Corpus(Path(corpus_path))
    settings = settings or RenderSettings()
    report = TargetsReport()
    jitter = jitter if jitter is not None and jitter.active else None
    jitter_key = None if jitter is None else jitter.key()
    out_dir = paths.pose_targets_dir(corpus.path, jitter_key)
    with corpus_lock(corpus.path, "pose targets"):
        if out_dir.is_dir():  # no other pass writes here while this one holds the lock: a temp file is a killed pass's
            for stale in out_dir.glob(".*.tmp"):
                stale.unlink(missing_ok=True)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=corpus.info.total_chunks, desc="pose targets", unit="chunk")
        try:
            if mapper is None and workers == 1:
                keep = _render_serial(corpus, settings, report, bar, jitter)
            else:
                if mapper is None and gl_threads is None:
                    gl_threads = threads_per_worker(workers)
                mapper = mapper or pool_mapper(workers, start_method="spawn")
                keep = _render_fanned_out(corpus, settings, report, bar, mapper, gl_threads, jitter)
        finally:
            if bar:
                bar.close()
        if out_dir.exists():
            for old in out_dir.glob("*.*"):
                if old.suffix in (".gbz", ".mkv") and old.name not in keep:  # .mkv: an earlier bridge's
                    old.unlink(missing_ok=True)
        _remove_orphan_pose_shards(corpus, jitter_key)
    return report


def _remove_orphan_pose_shards(corpus: Corpus, jitter_key: str | None = None) -> None:
    """Delete the pose shards of shard numbers the corpus no longer holds (a retired recording's)."""
    held = {paths.shard_name(s) for s in corpus.shard_ids()}
    where = corpus.pose_path(0, jitter_key).parent
    for p in where.glob("shard-*.tar") if where.is_dir() else []:
        if paths.SHARD_NAME.fullmatch(p.stem) and p.stem not in held:
            p.unlink(missing_ok=True)


def _render_serial(corpus: Corpus, settings: RenderSettings, report: TargetsReport, bar, jitter: Jitter | None) -> set[str]:

    report.workers = [worker_identity()]
    run = _Pass(corpus, settings, report, jitter)
    try:
        for shard in corpus.shard_ids():
            _render_shard(run, corpus, shard, bar.update if bar else lambda n: None)
    finally:
        run.release()
    return run.keep


def _render_fanned_out(
    corpus: Corpus, settings: RenderSettings, report: TargetsReport, bar, mapper, gl_threads: int | None, jitter: Jitter | None
) -> set[str]:
    jobs = [RenderJob(str(corpus.path), s) for s in corpus.shard_ids()]
    outcomes: dict[int, ShardOutcome] = {}
    for out in mapper(render_shard, jobs, {"settings": settings, "gl_threads": gl_threads, "jitter": jitter}):
        outcomes[out.job.shard] = out
        if bar:
            bar.update(out.report.chunks)
    missing = [j.shard for j in jobs if j.shard not in outcomes]
    if missing:
        raise RuntimeError(f"{corpus.path}: the pose pass's workers returned no outcome for shards {missing}")
    keep: set[str] = set()
    for j in jobs:  # in shard order, as one pass would have listed them
        r = outcomes[j.shard].report
        report.chunks += r.chunks
        report.rendered += r.rendered
        report.shards_rewritten += r.shards_rewritten
        report.frames_rendered += r.frames_rendered
        report.failed.update(r.failed)
        keep |= outcomes[j.shard].keep
    report.workers = sorted({o.worker for o in outcomes.values()})
    return keep


def _rows_hash(layout: Layout, rows: pa.Table) -> str:
    """Content hash of a chunk's state rows: state vectors, recorded roots and rotations, validity, times, cameras."""
    h = hashlib.sha256()
    cols = [("state", layout.dim), ("camera.pos", 3), ("camera.rot", 4)]
    cols += [(f"{e.name}.root_world", 3) for e in layout.articulated] + [(f"{e.name}.rot_world", 4) for e in layout.articulated]
    for name, width in cols:
        h.update(name.encode())
        h.update(np.ascontiguousarray(fixed_rows(rows[name], width)).tobytes())
    for name in ("valid", "t", "frame"):
        h.update(name.encode())
        h.update(np.ascontiguousarray(rows[name].to_numpy(zero_copy_only=False)).tobytes())
    return h.hexdigest()


# ------------------------------------------------------------------------------------------------
# one segment or one rollout, at any size, rate and camera (`marionette render`)


def source_size(corpus: Corpus, segment: str) -> tuple[int, int]:
    """(height, width) of a segment's source video: from its video chunks' records, else the source's header."""
    row = corpus.segment_row(segment)
    vpath = corpus.video_path(row["shard"])
    if vpath.exists():
        for key, m in video_shards.read_chunks(vpath, segment, kinds=("json",)).items():
            h, w = video_shards.chunk_record(m["json"], key, str(vpath))["source_size"]
            return int(h), int(w)
    sample = corpus.samples.filter(pa.compute.equal(corpus.samples["sample"], row["sample"])).to_pylist()
    if sample and sample[0]["source"]:
        import av

        with av.open(str(Path(sample[0]["source"]) / RGB_FILE)) as c:
            cc = c.streams.video[0].codec_context
            return int(cc.height), int(cc.width)
    raise ValueError(f"{corpus.path}: cannot tell the source video size of segment {segment!r}")


def render_rows(
    layout: Layout,
    rows: pa.Table,
    out: Path,
    terrain: TerrainScene,
    camera: str = "recorded",
    size: tuple[int, int] = (704, 1280),
    fps: float | None = None,
    src_size: tuple[int, int] | None = None,
    settings: RenderSettings | None = None,
    jitter: Jitter | None = None,
    key: str = "",
) -> GBufferMeta:
    """Render state rows (one segment or rollout, corpus state schema) to a G-buffer video ``out``.

    ``camera``: "recorded" (the rows' camera, its intrinsics mapped by the centred crop + resize from
    ``src_size`` to ``size``) or "follow" (``camera.follow_cameras``). ``fps`` defaults to the rows' rate;
    skeletons and the recorded camera are interpolated in time (slerp for rotations). ``jitter`` moves the
    skeletons (``bridge.jitter``; drawn for the clip ``key``) before they are rendered; the camera stays.
    """

    settings = settings or RenderSettings()
    if rows.num_rows == 0:
        raise ValueError(f"{out}: no rows to render")
    H, W = size
    state, anchors, valid, t = chunk_inputs(layout, rows)
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        raise ValueError(f"{out}: the rows' times are not increasing")
    src_fps = 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else 30.0
    fps = float(fps or round(src_fps, 6))
    n_out = max(1, int(np.floor((t[-1] - t[0]) * fps + 1e-6)) + 1)
    t_out = t[0] + np.arange(n_out) / fps
    jitter = jitter or Jitter()
    skel = jitter.apply(layout, world_skeletons(layout, state, anchors, valid, t, jitter.times(t_out, key)), key)
    if camera == "recorded":
        if src_size is None:
            raise ValueError("the recorded camera needs the source video size")
        cr = CropResize.fit(src_size[0], src_size[1], H, W)
        K = resample_positions(t, fixed_rows(rows["camera.K"], 4), t_out, "nearest")
        pos = resample_positions(t, fixed_rows(rows["camera.pos"], 3), t_out)
        rot = resample_quats(t, np.nan_to_num(fixed_rows(rows["camera.rot"], 4)), t_out)
        # a frame with an invalid recorded camera (NaN position) makes the frames interpolated from it invalid: black
        cams = recorded_cameras(K, pos, rot, np.ones(n_out, bool), W, H, crop=cr)
    elif camera == "follow":
        cams = follow_view(layout, skel, fps, W, H)
    else:
        raise ValueError(f"camera must be 'recorded' or 'follow', not {camera!r}")
    roots_y = np.concatenate([skel.joints[e.name][:, 0, 1] for e in layout.articulated])
    h = height_range(terrain, roots_y, settings)
    meta = GBufferMeta(h[0], h[1], settings.z_near, settings.z_far, W, H, fps)
    with Rasterizer(W, H) as rast:
        rast.set_terrain(terrain.vertices, terrain.faces)
        write_gbuffer(out, render_frames(rast, layout, skel, cams, h, settings), meta)
    return meta
