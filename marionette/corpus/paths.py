"""Every path inside a corpus, formatted in one place from validated ids.

A corpus is untrusted input: ids, plan entries, manifest entries and tar member names read from it
become paths only through this module, and only when they match their pattern. Patterns admit no
dot-dot, no separator and no absolute path, so a formatted path always stays inside its root;
``inside`` checks the resolved result as well, so a symlink planted in the corpus cannot lead out.

```
meta/info.json  meta/segments.parquet  meta/samples.parquet  meta/quarantine.parquet
meta/vocab.json meta/stats.json        meta/samples/<key>.json  meta/finalize-plan.json  meta/.lock
state/shard-NNNNNN.arrow               video/shard-NNNNNN.tar    pose/shard-NNNNNN.tar
staging/<key>/{record.json,state.arrow,video.tar}
derived/pose/<segment>__c<chunk:05d>-<hash>.gbz
terrain/stage_<stage>/{manifest.json, chunks/chunk_<cx>_<cz>.trn2, contributions/<key>.npz}
```
"""

from __future__ import annotations

import re
from pathlib import Path

# A segment id, sample key, stage id or recording key: letters, digits, '_' and '-' only (what
# ``safe_name`` produces), so it is one path component that can never be '.', '..' or absolute.
ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,200}")
CHUNK_KEY = re.compile(r"(?P<segment>[A-Za-z0-9_-]{1,200})__c(?P<chunk>\d{5})")
SHARD_NAME = re.compile(r"shard-(?P<n>\d{6})")
STAGED_FILES = ("record.json", "state.arrow", "video.tar")
POSE_HASH = re.compile(r"[0-9a-f]{16}")
# the fixed metadata files under meta/ (``meta``)
INFO = "info.json"
SEGMENTS = "segments.parquet"
SAMPLES = "samples.parquet"
QUARANTINE = "quarantine.parquet"
VOCAB = "vocab.json"
STATS = "stats.json"
SCAN = "scan.json"
DERIVED_NAME = re.compile(r"[A-Za-z0-9_.-]{1,200}")


class CorpusPathError(ValueError):
    """A name read from a corpus (or given for one) does not match its pattern or leaves its root."""


def check_id(value: object, what: str, where: str = "") -> str:
    """``value`` if it is a valid id (ID_PATTERN), else CorpusPathError naming ``where`` and ``what``."""
    if not isinstance(value, str) or not ID_PATTERN.fullmatch(value):
        raise CorpusPathError(f"{where + ': ' if where else ''}{what} {value!r} is not a valid id (letters, digits, '_', '-')")
    return value


def check_shard(n: object, where: str = "") -> int:
    """``n`` if it is a shard number (an int in [0, 999999]), else CorpusPathError."""
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= 999_999:
        raise CorpusPathError(f"{where + ': ' if where else ''}shard {n!r} is not a shard number")
    return n


def inside(root: Path, path: Path, where: str = "") -> Path:
    """``path`` if it resolves (symlinks followed) inside ``root``, else CorpusPathError."""
    root_r, path_r = Path(root).resolve(), Path(path).resolve()
    if path_r != root_r and root_r not in path_r.parents:
        raise CorpusPathError(f"{where + ': ' if where else ''}{path} resolves to {path_r}, outside {root_r}")
    return path


def shard_name(n: int) -> str:
    """``shard-NNNNNN`` (the stem of a state or video shard)."""
    return f"shard-{check_shard(n):06d}"


def state_shard(root: Path, n: int) -> Path:
    """``<root>/state/shard-NNNNNN.arrow``."""
    return state_dir(root) / f"{shard_name(n)}.arrow"


def video_shard(root: Path, n: int) -> Path:
    """``<root>/video/shard-NNNNNN.tar``."""
    return video_dir(root) / f"{shard_name(n)}.tar"


def jitter_dir(root: Path, jitter: str) -> Path:
    """``<root>/derived/jitter-<jitter>``: the pose targets rendered from state jittered by the ``bridge.jitter.Jitter``
    whose key is ``jitter`` (16 hex digits), in the layout of the corpus's own (``targets/``, ``pose/``)."""
    if not POSE_HASH.fullmatch(jitter):
        raise CorpusPathError(f"jitter key {jitter!r} is not 16 hex digits")
    return derived(root, f"jitter-{jitter}")


def pose_shard(root: Path, n: int, jitter: str | None = None) -> Path:
    """``<root>/pose/shard-NNNNNN.tar``: the pose targets of video shard ``n``, keyed like its chunks (with ``jitter``,
    those of jittered state, under ``jitter_dir``)."""
    return (Path(root) if jitter is None else jitter_dir(root, jitter)) / "pose" / f"{shard_name(n)}.tar"


def meta_dir(root: Path) -> Path:
    """``<root>/meta``: the corpus's metadata (info, segments, samples, vocab, stats, the scan's options, the lock)."""
    return Path(root) / "meta"


def meta(root: Path, name: str) -> Path:
    """``<root>/meta/<name>`` for one of the corpus's fixed metadata files."""
    return meta_dir(root) / name


def samples_dir(root: Path) -> Path:
    """``<root>/meta/samples``: one record per committed sample (``sample_record``)."""
    return meta_dir(root) / "samples"


def builds_dir(root: Path) -> Path:
    """``<root>/meta/builds``: the build flow's reports and its task cache."""
    return meta_dir(root) / "builds"


def derived(root: Path, name: str) -> Path:
    """``<root>/derived/<name>``: a product derived from the corpus (the dynamics view, terrain features, windows,
    Wan latents, jittered pose targets), rebuilt when missing."""
    if not DERIVED_NAME.fullmatch(name) or name in (".", ".."):
        raise CorpusPathError(f"{name!r} is not a derived product's name")
    return Path(root) / "derived" / name


def state_dir(root: Path) -> Path:
    """``<root>/state``: the Arrow state shards."""
    return Path(root) / "state"


def video_dir(root: Path) -> Path:
    """``<root>/video``: the webdataset video shards."""
    return Path(root) / "video"


def staging_root(root: Path) -> Path:
    """``<root>/staging``: samples staged by ingest, not yet committed (``staging_dir``)."""
    return Path(root) / "staging"


def terrain_dir(root: Path) -> Path:
    """``<root>/terrain``: the stages' terrain (``stage_dir``)."""
    return Path(root) / "terrain"


def sample_record(root: Path, key: str, where: str = "") -> Path:
    """``<root>/meta/samples/<key>.json``: a committed sample's record."""
    return samples_dir(root) / f"{check_id(key, 'sample key', where)}.json"


def staging_dir(root: Path, key: str, where: str = "") -> Path:
    """``<root>/staging/<key>``: a sample staged by ingest, not yet committed."""
    return staging_root(root) / check_id(key, "sample key", where)


def staged_file(root: Path, key: str, name: str, where: str = "") -> Path:
    """``<root>/staging/<key>/<name>`` for one of the staged files (record.json, state.arrow, video.tar)."""
    if name not in STAGED_FILES:
        raise CorpusPathError(f"{where + ': ' if where else ''}{name!r} is not a staged file {STAGED_FILES}")
    return staging_dir(root, key, where) / name


def chunk_key(segment: str, chunk: int) -> str:
    """``<segment>__c<chunk:05d>``: a video chunk's webdataset key (no dots)."""
    check_id(segment, "segment")
    if isinstance(chunk, bool) or not isinstance(chunk, int) or not 0 <= chunk <= 99_999:
        raise CorpusPathError(f"chunk {chunk!r} of {segment!r} is not a chunk number")
    return f"{segment}__c{chunk:05d}"


def parse_chunk_key(key: str, where: str = "") -> tuple[str, int]:
    """(segment, chunk) of a chunk key, else CorpusPathError."""
    m = CHUNK_KEY.fullmatch(key) if isinstance(key, str) else None
    if m is None:
        raise CorpusPathError(f"{where + ': ' if where else ''}{key!r} is not a chunk key <segment>__cNNNNN")
    return m["segment"], int(m["chunk"])


def pose_targets_dir(root: Path, jitter: str | None = None) -> Path:
    """``<root>/derived/pose``: the rendered pose-control targets (with ``jitter``: ``jitter_dir``'s ``targets``)."""
    return derived(root, "pose") if jitter is None else jitter_dir(root, jitter) / "targets"


def pose_target(root: Path, key: str, digest: str, jitter: str | None = None) -> Path:
    """``<root>/derived/pose/<chunk key>-<digest>.gbz``: a rendered pose-control target (``pose_targets_dir``)."""
    parse_chunk_key(key)
    if not POSE_HASH.fullmatch(digest):
        raise CorpusPathError(f"pose target digest {digest!r} is not 16 hex digits")
    return pose_targets_dir(root, jitter) / f"{key}-{digest}.gbz"


def stage_dir(root: Path, stage: str) -> Path:
    """``<root>/terrain/stage_<id>``; a stage id that is not an id (``ID_PATTERN``) is refused, never made one (two
    ids made alike would share a directory)."""
    return terrain_dir(root) / f"stage_{check_id(stage, 'stage id')}"


def resolve_plan_entry(root: Path, rel: object, where: str) -> Path:
    """A relative path written in ``meta/finalize-plan.json`` → the path, if it is one a plan may name:
    a staged state/video file, or a state/video shard."""
    if isinstance(rel, str):
        parts = rel.split("/")
        if len(parts) == 3 and parts[0] == "staging" and ID_PATTERN.fullmatch(parts[1]) and parts[2] in STAGED_FILES[1:]:
            return inside(root, Path(root) / rel, where)
        kind = (parts[0], Path(parts[1]).suffix) if len(parts) == 2 else None
        if kind in (("state", ".arrow"), ("video", ".tar")) and SHARD_NAME.fullmatch(Path(parts[1]).stem):
            return inside(root, Path(root) / rel, where)
    raise CorpusPathError(f"{where}: entry {rel!r} is not a staged file or a shard of this corpus")
