"""One WildWorld sample → staged state rows (Arrow), video chunks (webdataset tar) and a summary.

A sample is staged under ``<corpus>/staging/<key>/`` and only becomes part of the corpus when
``finalize`` moves it into a numbered shard; ``record.json`` is written last and marks the staged
sample as complete, so a crash mid-sample leaves nothing a rerun would mistake for finished work.
"""

from __future__ import annotations

import hashlib
import json
import re
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from marionette import geometry as geo
from marionette.corpus import paths, state_table
from marionette.ingest.survey import recording_layout
from marionette.io import file_sha256, printable, read_json, text_sha256, write_ipc, write_json
from marionette.recordings.errors import SampleError, SampleSkipped
from marionette.recordings.skeleton_archive import MAX_MEMBER_BYTES
from marionette.recordings.wildworld import (
    DEPTH_FILE,
    MAX_FRAME_PIXELS,
    RGB_FILE,
    SKELETON_FILE,
    STATE_FILE,
    RecordedSample,
    SampleRef,
    check_in_tree,
    read_sample,
)
from marionette.schema import Layout, SchemaError, load_scene
from marionette.video import VideoSettings, write_video_shard

INGEST_VERSION = "2"  # in every cache key (IngestOptions.key): a change of what ingest writes for the same options bumps it
AUTO_SCENE = "auto"  # each recording ingested with the layout of what it holds


@dataclass(frozen=True)
class IngestOptions:
    """What a build ingests and how: scene, slice (species, weapon), segmenting, video, Arrow codec."""

    scene: str = "duel"
    rigs: str | None = None  # a directory of user rigs and scenes (schemas/'s layout) looked in before the built-in ones
    monster_species: int | None = None
    weapon: int | None = None
    min_segment_frames: int = 30
    video: VideoSettings = field(default_factory=VideoSettings)
    compression: str = "zstd"
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
    max_member_bytes: int = MAX_MEMBER_BYTES  # a skeleton.npz member declaring more (inflated) is quarantined unread
    max_frame_pixels: int = MAX_FRAME_PIXELS  # a sample whose video frames are larger is quarantined undecoded

    @property
    def auto(self) -> bool:
        """Whether each recording gets the layout of what it holds (``scene="auto"``) rather than one for all."""
        return self.scene == AUTO_SCENE

    @property
    def rigs_dir(self) -> Path | None:
        return None if self.rigs is None else Path(self.rigs)

    @property
    def layout(self) -> Layout:
        if self.auto:
            raise SchemaError("scene 'auto' has no one layout: each recording gets its own (layout_for)")
        return load_scene(self.scene, rigs=self.rigs_dir)

    def layout_for(self, ref: SampleRef) -> Layout:
        """The layout a recording is ingested with: the scene's, or with ``auto`` the one of what it holds."""
        if not self.auto:
            return self.layout

        return recording_layout(ref, self.rigs_dir)

    def type_filter(self, layout: Layout | None = None) -> dict[str, set[int]]:
        """Accepted type ids per entity name: the requested slice, else what the rigs declare."""
        out = {}
        for e in (layout or self.layout).entities:
            ids = set(e.rig.type_ids)
            if e.source_kind == "m" and self.monster_species is not None:
                ids = {self.monster_species}
            if e.source_kind == "w" and self.weapon is not None:
                ids = {self.weapon}
            out[e.name] = ids
        return out

    def key(self) -> str:
        """Hash of everything that changes what ingest writes."""
        d = asdict(self)
        if self.auto:  # what every rig says: a changed rig re-ingests
            from marionette.ingest.survey import rig_index

            index = rig_index(self.rigs_dir)
            d["layout_hash"] = text_sha256(json.dumps({k: r.to_json() for k, r in sorted(index.items())}, sort_keys=True))
        else:
            d["layout_hash"] = self.layout.hash  # what the rigs say, wherever they are
        d.pop("rigs")
        if d["max_frame_pixels"] == MAX_FRAME_PIXELS:  # left out at its default: a corpus's key names what differs from it
            d.pop("max_frame_pixels")
        d["ingest_version"] = INGEST_VERSION
        return text_sha256(json.dumps(d, sort_keys=True, default=str))[:16]

    def to_json(self) -> dict:
        d = asdict(self)
        d["split_fractions"] = list(self.split_fractions)
        if d["rigs"] is None:  # as corpora built before user rigs existed have it
            del d["rigs"]
        if d["max_frame_pixels"] == MAX_FRAME_PIXELS:
            del d["max_frame_pixels"]
        return d

    @staticmethod
    def from_json(d: dict) -> IngestOptions:
        d = dict(d)
        d["video"] = VideoSettings(**{"x264_options": "", **d["video"]})  # no x264_options: the preset alone
        d["split_fractions"] = tuple(d["split_fractions"])
        return IngestOptions(**d)


@dataclass
class SampleResult:
    """What happened to one sample: ingested, unchanged (no work), skipped or quarantined."""

    sample: str
    status: str
    input_hash: str
    reason: str = ""
    segments: int = 0
    frames: int = 0
    worker: str = ""


KEPT_NAME = re.compile(r"[A-Za-z0-9]+(?:_[A-Za-z0-9]+)*")  # a source name used as it is in keys and file names
MAX_KEPT_NAME = 64  # characters; a longer name is shortened and hashed
_CLEAN_CHARS = 48  # of a shortened or cleaned name, before its hash
_NAME_HASH = 12  # hex digits of sha256 appended to a name that had to change


def safe_name(s: str) -> str:
    """A source name (a part or sample directory: any characters, up to the file system's 255 bytes) as it appears in
    sample keys, segment ids and file names: the name itself when it is letters and digits joined by single
    underscores and at most ``MAX_KEPT_NAME`` long, else its cleaned first ``_CLEAN_CHARS`` characters, ``--`` and a
    hash of the whole name.

    The output never holds ``__``, never starts or ends with ``_``, and holds ``-`` only in the ``--`` before a hash,
    so joining two names with ``__`` (``sample_key``) or ``-`` (``segment_id``) is read back one way only: two
    different sources never share a key or a segment id (``check_keys`` refuses the impossible hash collision)."""
    if KEPT_NAME.fullmatch(s) and len(s) <= MAX_KEPT_NAME:
        return s
    clean = re.sub(r"[^A-Za-z0-9]+", "_", s)[:_CLEAN_CHARS].strip("_") or "x"
    return f"{clean}--{hashlib.sha256(s.encode('utf-8', 'surrogatepass')).hexdigest()[:_NAME_HASH]}"


def sample_key(ref: SampleRef) -> str:
    """Directory/key name of a sample inside the corpus."""
    return f"{safe_name(ref.part)}__{safe_name(ref.sample_id)}"


def segment_id(ref: SampleRef, k: int) -> str:
    """Id of the k-th segment of a sample (also a webdataset key prefix: no dots)."""
    return f"{safe_name(ref.part)}-{safe_name(ref.sample_id)}-s{k:03d}"


def check_keys(refs: list[SampleRef]) -> tuple[list[SampleRef], list[tuple[str, str]]]:
    """``refs`` less any two whose sample keys or segment ids would be one (never merged: both are refused), and
    (path, reason) for each refused."""
    owners: dict[str, list[SampleRef]] = {}
    for r in refs:
        owners.setdefault(sample_key(r), []).append(r)
        owners.setdefault("segment " + segment_id(r, 0), []).append(r)
    clash = {id(r): others for others in owners.values() if len(others) > 1 for r in others}
    refused = [
        (str(r.path), f"its key is also that of {', '.join(printable(o.name) for o in clash[id(r)] if o is not r)}: both refused")
        for r in refs
        if id(r) in clash
    ]
    return [r for r in refs if id(r) not in clash], refused


def split_of(recording: str, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)) -> str:
    """train / val / test from a hash of the recording id: stable under adding recordings."""
    u = int.from_bytes(hashlib.sha256(recording.encode()).digest()[:8], "big") / 2**64
    return "train" if u < fractions[0] else "val" if u < fractions[0] + fractions[1] else "test"


def file_digests(ref: SampleRef, known: dict | None = None) -> dict[str, list]:
    """[size, mtime_ns, sha256] of a sample's input files; a file whose size and mtime match ``known``
    reuses its recorded digest, so a rerun over hundreds of hours of video reads no video bytes."""
    out: dict[str, list] = {}
    for name, p in [(f, ref.path / f) for f in (STATE_FILE, SKELETON_FILE, RGB_FILE, DEPTH_FILE)] + [
        ("skeleton_edges.json", ref.edges_path)
    ]:
        if not p.exists():
            out[name] = [-1, -1, "missing"]
            continue
        st = p.stat()
        prev = (known or {}).get(name)
        if prev and prev[0] == st.st_size and prev[1] == st.st_mtime_ns:
            out[name] = prev
        else:
            out[name] = [st.st_size, st.st_mtime_ns, file_sha256(p)]
    return out


def input_hash(ref: SampleRef, options: IngestOptions, digests: dict[str, list] | None = None) -> str:
    """Hash of a sample's file contents and the options: the cache key of its ingest."""
    digests = digests or file_digests(ref)
    return text_sha256(ref.name, options.key(), *(f"{k}:{v[2]}" for k, v in sorted(digests.items())))[:32]


@dataclass(frozen=True)
class SampleInputs:
    """A sample's input hash and file digests, or why its files are not read: ``refused`` (a symlink
    out of the source tree: never read, quarantined) or ``unreadable`` (an I/O error: retried)."""

    hash: str
    digests: dict[str, list] | None
    refused: str = ""
    unreadable: str = ""


def sample_inputs(ref: SampleRef, options: IngestOptions, known: dict | None = None) -> SampleInputs:
    """The cache key of a sample's ingest (``input_hash``), computed without reading anything outside the
    source tree; ``known`` is its last record, whose digests are reused for files whose size and mtime match."""
    try:
        check_in_tree(ref)  # before anything is read: a symlink out of the source tree is never followed
        digests = file_digests(ref, (known or {}).get("files"))
    except SampleError as exc:
        return SampleInputs(text_sha256(ref.name, options.key(), str(exc))[:32], None, refused=str(exc))
    except OSError as exc:
        why = f"{exc.filename or ref.path}: unreadable ({type(exc).__name__}: {exc.strerror or exc})"
        return SampleInputs("unreadable", None, unreadable=why)
    return SampleInputs(input_hash(ref, options, digests), digests)


def valid_runs(valid: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """Maximal runs [start, stop) of True at least ``min_len`` long."""
    v = np.concatenate([[False], np.asarray(valid, bool), [False]])
    edges = np.flatnonzero(np.diff(v.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2]) if b - a >= min_len]


def _describe_invalid(sample: RecordedSample) -> str:
    parts = []
    for name, track in list(sample.entities.items()) + [("camera", None)]:
        bad = ~(track.valid if track is not None else sample.camera_valid)
        if bad.any():
            idx = np.flatnonzero(bad)
            parts.append(f"{name} invalid on {len(idx)} frames (first {int(idx[0])})")
    return "; ".join(parts) or "all frames valid"


# ------------------------------------------------------------------------------------------------
# summaries merged at finalize: running moments (Chan et al.) and per-action motion statistics


def moments(x: np.ndarray) -> dict:
    """count, mean, M2, min, max per column of (N, F) float64 data."""
    x = np.asarray(x, np.float64)
    return {
        "count": int(len(x)),
        "mean": x.mean(0).tolist(),
        "m2": ((x - x.mean(0)) ** 2).sum(0).tolist(),
        "min": x.min(0).tolist(),
        "max": x.max(0).tolist(),
    }


def merge_moments(a: dict | None, b: dict) -> dict:
    """Merge two moment summaries (parallel variance algorithm; stable for large offsets)."""
    if a is None or a["count"] == 0:
        return b
    if b["count"] == 0:
        return a
    na, nb = a["count"], b["count"]
    ma, mb = np.array(a["mean"]), np.array(b["mean"])
    d = mb - ma
    n = na + nb
    return {
        "count": n,
        "mean": (ma + d * nb / n).tolist(),
        "m2": (np.array(a["m2"]) + np.array(b["m2"]) + d**2 * na * nb / n).tolist(),
        "min": np.minimum(a["min"], b["min"]).tolist(),
        "max": np.maximum(a["max"], b["max"]).tolist(),
    }


def merge_action_stats(into: dict, more: dict) -> dict:
    """Fold per-entity-type action summaries ``more`` into ``into`` (frames and instances add up,
    the largest motion_frame and any wrap are kept); returns ``into``."""
    for etype, acts in more.items():
        for cid, d in acts.items():
            cur = into.setdefault(etype, {}).setdefault(
                str(cid), {"frames": 0, "max_motion_frame": -1, "wraps": False, "instances": []}
            )
            cur["frames"] += d["frames"]
            cur["max_motion_frame"] = max(cur["max_motion_frame"], d["max_motion_frame"])
            cur["wraps"] = cur["wraps"] or d["wraps"]
            cur["instances"] = cur["instances"] + d["instances"]
    return into


def action_stats(layout: Layout, state: np.ndarray, sample: RecordedSample, a: int, b: int, fps: float) -> dict:
    """Per articulated entity and composite action: frames, largest motion_frame, whether it wrapped,
    and per played instance the mean horizontal root speed (m/s) and the peak root-frame speed of any
    joint or owned attachment point (m/s)."""
    out: dict[str, dict[str, dict]] = {}
    n = b - a
    for e in layout.articulated:
        tr = sample.entities[e.name]
        rig_key = f"{e.rig.name}:{int(tr.type_id[a])}"
        act, mf = tr.action[a:b], tr.motion_frame[a:b]
        local = [state[:, layout.slice(f"{e.name}.joints")].reshape(n, -1, 3)]
        local += [state[:, layout.slice(f"{o.name}.points")].reshape(n, -1, 3) for o in layout.attachments if o.owner == e.name]
        p = np.concatenate(local, axis=1).astype(np.float64)
        body_speed = np.zeros(n)
        body_speed[1:] = np.linalg.norm(np.diff(p, axis=0), axis=-1).max(axis=1) * fps
        root = tr.joints_world[a:b, 0]
        root_speed = np.zeros(n)
        root_speed[1:] = np.linalg.norm(np.diff(root[:, [0, 2]], axis=0), axis=-1) * fps
        starts = np.flatnonzero(np.concatenate([[True], act[1:] != act[:-1]]))
        stops = np.concatenate([starts[1:], [n]])
        ent = out.setdefault(rig_key, {})
        for s, t in zip(starts, stops):
            cid = int(act[s])
            d = ent.setdefault(str(cid), {"frames": 0, "max_motion_frame": -1, "wraps": False, "instances": []})
            d["frames"] += int(t - s)
            d["max_motion_frame"] = max(d["max_motion_frame"], int(mf[s:t].max()))
            m = mf[s:t]
            d["wraps"] = bool(d["wraps"] or ((np.diff(m) < 0) & (m[1:] >= 0) & (m[:-1] >= 0)).any())  # -1 = invalid
            lo = s + 1 if s == 0 else s  # the segment's first frame has no previous frame
            if t - lo >= 1:
                d["instances"].append(
                    [round(float(root_speed[lo:t].mean()), 4), round(float(body_speed[lo:t].max()), 4), int(t - s)]
                )
    return out


# ------------------------------------------------------------------------------------------------


def _segment_table(layout: Layout, sample: RecordedSample, seg_id: str, a: int, b: int, state: np.ndarray) -> pa.Table:
    """Rows [a, b) of a sample as a state-shard table (``marionette.corpus.state_table``)."""
    cols: dict = {
        "segment": seg_id,
        "sample": sample.ref.name,
        "frame": np.arange(a, b, dtype=np.int32),
        "t": np.arange(a, b, dtype=np.float64) / sample.fps,
        "state": state,
    }
    for e in layout.articulated:
        tr = sample.entities[e.name]
        cols[f"{e.name}.type_id"] = tr.type_id[a:b].astype(np.int32)
        cols[f"{e.name}.action"] = tr.action[a:b]
        cols[f"{e.name}.motion_frame"] = tr.motion_frame[a:b]
        cols[f"{e.name}.hp"] = tr.hp[a:b]
        cols[f"{e.name}.root_world"] = tr.joints_world[a:b, 0]
        cols[f"{e.name}.rot_world"] = tr.rot[a:b]
        cols[f"{e.name}.pos_check_m"] = np.nan_to_num(np.linalg.norm(tr.pos[a:b] - tr.joints_world[a:b, 0], axis=1), nan=-1)
    for e in layout.attachments:
        cols[f"{e.name}.type_id"] = sample.entities[e.name].type_id[a:b].astype(np.int32)
    cols["camera.K"] = sample.camera_K[a:b]
    cols["camera.pos"] = sample.camera_pos[a:b]
    cols["camera.rot"] = sample.camera_rot[a:b]
    cols["valid"] = True
    return state_table(layout, cols, n=b - a)


def segment_states(layout: Layout, sample: RecordedSample, runs: list[tuple[int, int]]):
    """For each run [a, b) of valid frames: (k, (a, b), state (n, D) float32, shard table rows)."""
    for k, (a, b) in enumerate(runs):
        joints = {e.name: sample.entities[e.name].joints_world[a:b] for e in layout.entities}
        rots = {e.name: sample.entities[e.name].rot[a:b] for e in layout.articulated}
        state = geo.world_to_state(layout, joints, rots)
        yield k, (a, b), state, _segment_table(layout, sample, segment_id(sample.ref, k), a, b, state)


def staging_dir(corpus: Path, ref: SampleRef) -> Path:
    """``<corpus>/staging/<key>``: where a sample is staged (``marionette.corpus.paths``)."""
    return paths.staging_dir(corpus, sample_key(ref))


def known_record(corpus: Path, ref: SampleRef) -> dict | None:
    """The newest record of the sample: staged (ingested, not yet finalized) or committed."""
    for p in (staging_dir(corpus, ref) / "record.json", paths.sample_record(corpus, sample_key(ref))):
        if p.exists():
            return read_json(p)
    return None


def is_unchanged(known: dict | None, h: str) -> bool:
    """Whether a known record already answers for input hash ``h`` (a failure that may be transient —
    an I/O error, a bug — never does: it is retried on the next run)."""
    return known is not None and known["input_hash"] == h and not known.get("retry", False)


def ingest_sample(ref: SampleRef, corpus: Path, options: IngestOptions, worker: str = "") -> SampleResult:
    """Ingest one sample into the corpus staging area; no work when its input hash is unchanged."""
    corpus = Path(corpus)
    known = known_record(corpus, ref)
    inputs = sample_inputs(ref, options, known)
    digests, h, refused, unreadable = inputs.digests, inputs.hash, inputs.refused, inputs.unreadable
    if (digests is not None or refused) and is_unchanged(known, h):
        return SampleResult(ref.name, "unchanged", h, worker=worker)
    stage = staging_dir(corpus, ref)
    stage.mkdir(parents=True, exist_ok=True)
    (stage / "record.json").unlink(missing_ok=True)
    record: dict = {
        "sample": ref.name,
        "key": sample_key(ref),
        "input_hash": h,
        "options_key": options.key(),
        "files": digests,
        "source": str(ref.path.resolve()),
    }
    try:
        if refused:
            raise SampleError(refused)
        if digests is None:
            raise OSError(unreadable)
        record.update(_stage_sample(ref, stage, options))
        _check_finite(record, str(ref.path))  # a value no JSON can hold (an overflowed statistic) costs this sample only
        segs = record["segments"]
        result = SampleResult(ref.name, "ingested", h, segments=len(segs), frames=sum(s["frames"] for s in segs), worker=worker)
    except SampleSkipped as exc:
        record.update(status="skipped", reason=str(exc))
        result = SampleResult(ref.name, "skipped", h, reason=str(exc), worker=worker)
    except SampleError as exc:
        record.update(status="quarantined", reason=str(exc))
        result = SampleResult(ref.name, "quarantined", h, reason=str(exc), worker=worker)
    except Exception as exc:  # an unexpected failure quarantines this sample, never the build, and is retried next run
        reason = (
            str(exc) if isinstance(exc, OSError) and digests is None else f"{ref.path}: unexpected {type(exc).__name__}: {exc}"
        )
        record.update(status="quarantined", reason=reason, retry=True, traceback=traceback.format_exc(limit=6))
        result = SampleResult(ref.name, "quarantined", h, reason=reason, worker=worker)
    if record["status"] != "ingested":
        for f in ("state.arrow", "video.tar"):
            (stage / f).unlink(missing_ok=True)
    write_json(stage / "record.json", record)
    return result


def _check_finite(value: object, where: str, field: str = "record") -> None:
    """A SampleError naming the first field of ``value`` (a record about to be written) that is a non-finite float."""
    if isinstance(value, float) and not np.isfinite(value):
        raise SampleError(f"{where}: {field} is {value} (a statistic overflowed: a value in the sample is out of range)")
    if isinstance(value, dict):
        for k, v in value.items():
            _check_finite(v, where, f"{field}.{k}")
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            _check_finite(v, where, f"{field}[{i}]")


def _stage_sample(ref: SampleRef, stage: Path, options: IngestOptions) -> dict:
    """Read one sample, write its segments' state (``state.arrow``) and video chunks (``video.tar``) under ``stage``;
    returns the record's fields of an ingested sample. A sample with no valid segment is a ``SampleError``."""
    layout = options.layout_for(ref)
    sample = read_sample(ref, layout, options.type_filter(layout), options.max_member_bytes, options.max_frame_pixels)
    runs = valid_runs(sample.valid, options.min_segment_frames)
    if not runs:
        raise SampleError(
            f"{ref.path}: no valid segment of at least {options.min_segment_frames} frames "
            f"({sample.n_frames} frames; {_describe_invalid(sample)})"
        )
    split = split_of(ref.name, options.split_fractions)
    tables, segs, summaries, stats = _segments(ref, layout, sample, runs, split)
    write_ipc(stage / "state.arrow", pa.concat_tables(tables), options.compression)
    video_records = write_video_shard(
        stage / "video.tar",
        ref.path / RGB_FILE,
        [(s["segment"], s["start"], s["stop"], sample.camera_K[s["start"] : s["stop"]]) for s in segs],
        sample.fps,
        options.video,
        {"sample": ref.name},
    )
    per_seg_chunks: dict[str, int] = {}
    for r in video_records:
        per_seg_chunks[r["segment"]] = per_seg_chunks.get(r["segment"], 0) + 1
    for s in segs:
        s["chunks"] = per_seg_chunks.get(s["segment"], 0)
    fields = {
        "status": "ingested",
        "scene": layout.scene,
        "fps": sample.fps,
        "n_frames": sample.n_frames,
        "video_size": list(sample.video_size),
        "types": {e.name: int(sample.entities[e.name].type_id[runs[0][0]]) for e in layout.entities},
        "split": split,
        "segments": segs,
        "actions": summaries,
        "stats": stats,
        "pos_check_m": _pos_check(layout, sample, runs),
        "state_hash": file_sha256(stage / "state.arrow"),
    }
    if options.auto:  # its own layout travels with it to finalize
        fields["layout"] = {"hash": layout.hash, **layout.to_json()}
    return fields


def _segments(
    ref: SampleRef, layout: Layout, sample: RecordedSample, runs: list[tuple[int, int]], split: str
) -> tuple[list[pa.Table], list[dict], dict, dict | None]:
    """Per valid run: its state table, its segment record (id, frames, split, content hash), and the sample's action
    statistics and moments merged over the runs."""
    tables, segs, summaries, stats = [], [], {}, None
    for k, (a, b), state, table in segment_states(layout, sample, runs):
        tables.append(table)
        segs.append(
            {
                "segment": segment_id(ref, k),
                "start": a,
                "stop": b,
                "frames": b - a,
                "split": split,
                "hash": _segment_hash(table),
            }
        )
        merge_action_stats(summaries, action_stats(layout, state, sample, a, b, sample.fps))
        feats = {"state": state.astype(np.float64)}
        for e in layout.articulated:
            feats[f"{e.name}.root_world"] = sample.entities[e.name].joints_world[a:b, 0]
        part = {k: moments(v) for k, v in feats.items()}
        stats = part if stats is None else {k: merge_moments(stats[k], part[k]) for k in part}
    return tables, segs, summaries, stats


def _segment_hash(table: pa.Table) -> str:
    """A segment's content hash: over every column but the ids (state, actions, roots, camera, ...)."""
    seg_hash = hashlib.sha256()
    for name in table.column_names[2:]:
        seg_hash.update(name.encode())
        for buf in table[name].combine_chunks().buffers():
            if buf is not None:
                seg_hash.update(buf)
    return seg_hash.hexdigest()[:32]


def _pos_check(layout: Layout, sample: RecordedSample, runs: list[tuple[int, int]]) -> dict[str, float]:
    """Per articulated entity, the largest distance (m) between its recorded position and its root joint over the valid
    runs (−1 where neither is known)."""
    return {
        e.name: max(
            float(
                np.nan_to_num(
                    np.linalg.norm(sample.entities[e.name].pos[a:b] - sample.entities[e.name].joints_world[a:b, 0], axis=1),
                    nan=-1.0,
                ).max()
            )
            for a, b in runs
        )
        for e in layout.articulated
    }
