"""``meta/info.json``, typed: what a corpus holds, checked field by field when it is read.

The LeRobot convention: one metadata object (version, layout, rates, features, totals, path templates)
that readers use instead of the raw dict. A field of the wrong type, an unknown shard number or a path
template other than this version's is an error naming ``info.json`` and the field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from marionette.corpus import paths
from marionette.io import read_json

STATE_PATH = "state/shard-{shard:06d}.arrow"
VIDEO_PATH = "video/shard-{shard:06d}.tar"
POSE_PATH = "pose/shard-{shard:06d}.tar"


@dataclass(frozen=True)
class CorpusInfo:
    """The fields of ``meta/info.json`` (see ``marionette.ingest.finalize.write_metadata``)."""

    codebase_version: str
    layout: dict  # the scene layout's JSON, with its "hash"
    fps: float | list  # the source rate (a list when recordings differ)
    dynamics_fps: int
    ingest: dict  # IngestOptions.to_json()
    features: dict  # name → {dtype, shape, names}
    total_samples: int
    total_ingested: int
    total_quarantined: int
    total_skipped: int
    total_segments: int
    total_frames: int
    total_chunks: int
    frames_per_split: dict[str, int]
    shards: list[int]
    stages: dict[str, str]  # recording → stage
    vocab_hash: str
    state_path: str = STATE_PATH
    video_path: str = VIDEO_PATH
    pose_path: str = POSE_PATH  # absent from corpora written before pose targets had shards of their own
    layouts: dict = field(default_factory=dict)  # a corpus of several scenes: scene → layout JSON with "hash" (layout {})
    extra: dict = field(default_factory=dict, compare=False)  # fields a newer writer added, kept as read

    @property
    def source_fps(self) -> float:
        """The source rate (the first one when recordings differ)."""
        return float(self.fps[0] if isinstance(self.fps, list) else self.fps)

    @property
    def compression(self) -> str:
        """The Arrow codec of the state shards and derived tables."""
        return str(self.ingest.get("compression", "zstd"))

    @property
    def video(self) -> dict:
        """The video chunks' settings: height, width, chunk_frames, crf, preset, x264_options."""
        return dict(self.ingest["video"])

    def to_json(self) -> dict:
        """The JSON object written as ``meta/info.json``."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "extra"}
        if not d["layouts"]:  # a corpus of one scene says it in "layout", as corpora always have
            del d["layouts"]
        return {**self.extra, **d}

    @staticmethod
    def from_json(d: object, where: str) -> CorpusInfo:
        """Check and type a parsed info.json; errors name ``where`` and the field."""
        if not isinstance(d, dict):
            raise ValueError(f"{where}: not a JSON object")
        known = {f.name: f for f in dataclasses.fields(CorpusInfo) if f.name != "extra"}
        required = [n for n, f in known.items() if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        missing = [n for n in required if n not in d]
        if missing:
            raise ValueError(f"{where}: missing fields {missing} (not a corpus of this version?)")
        kinds = {
            "codebase_version": str,
            "layout": dict,
            "dynamics_fps": int,
            "ingest": dict,
            "features": dict,
            "frames_per_split": dict,
            "shards": list,
            "stages": dict,
            "vocab_hash": str,
            "state_path": str,
            "video_path": str,
            "pose_path": str,
            "layouts": dict,
        }
        kinds.update({n: int for n in known if n.startswith("total_")})
        for name, kind in kinds.items():
            if name in d and (not isinstance(d[name], kind) or isinstance(d[name], bool)):
                raise ValueError(f"{where}: field {name!r} is {type(d[name]).__name__}, expected {kind.__name__}")
        fps = d["fps"]
        if not (isinstance(fps, int | float) or (isinstance(fps, list) and fps and all(isinstance(v, int | float) for v in fps))):
            raise ValueError(f"{where}: field 'fps' is {fps!r}, expected a rate or a list of rates")
        for n in d["shards"]:
            paths.check_shard(n, f"{where}: field 'shards'")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in d["stages"].items()):
            raise ValueError(f"{where}: field 'stages' must map recording ids to stage ids (strings)")
        for name, template in (("state_path", STATE_PATH), ("video_path", VIDEO_PATH), ("pose_path", POSE_PATH)):
            if d.get(name, template) != template:
                raise ValueError(f"{where}: field {name!r} is {d[name]!r}; this reader knows {template!r}")
        video = d["ingest"].get("video")
        if not isinstance(video, dict) or not all(isinstance(video.get(k), int) for k in ("height", "width", "chunk_frames")):
            raise ValueError(f"{where}: field 'ingest.video' needs integer height, width and chunk_frames")
        return CorpusInfo(**{k: v for k, v in d.items() if k in known}, extra={k: v for k, v in d.items() if k not in known})

    @staticmethod
    def read(path: Path) -> CorpusInfo:
        """Read and check ``meta/info.json``."""
        return CorpusInfo.from_json(read_json(path), str(path))
