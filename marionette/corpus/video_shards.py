"""The video and pose shard formats: webdataset tars of 81-frame chunks, read and written only here.

A video shard ``video/shard-NNNNNN.tar`` holds, per chunk key ``<segment>__c<chunk:05d>``
(``paths.chunk_key``), the members ``<key>.rgb.mp4`` (the training-resolution RGB) and ``<key>.json``
(the chunk's record: source frames, crop, intrinsics), in that order; ingest writes it and nothing
rewrites it. Its pose shard ``pose/shard-NNNNNN.tar`` holds, for every chunk whose pose-control target
is rendered, ``<key>.pose.json`` (``pose_record``: the render's key, the terrain chunks it saw, and what
it was rendered from) and ``<key>.pose.gbz`` (the bridge's lossless G-buffer, ``bridge.gbuffer``), in the video shard's
chunk order. Readers join the two by key (webdataset's rule: members sharing a key are one sample), so
re-rendering pose targets never touches an RGB byte. A pose member is joined only while its record names
the chunk's current json and state shard (``pose_matches``): a video shard replaced by a re-ingest never
borrows the old recording's targets. Members are regular files with a fixed mtime and mode, so
rewriting a shard with the same members gives the same bytes.

A shard is untrusted input: every member must be a regular file named ``<chunk key>.<kind>`` with a
kind of its shard and a size under ``MAX_MEMBER_BYTES``, or the whole shard is refused with an error
naming it and the member. Nothing is ever extracted to disk.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import tarfile
from collections.abc import Callable, Iterator
from pathlib import Path

from marionette.corpus.paths import CorpusPathError, chunk_key, parse_chunk_key
from marionette.io import atomic_path, regular_file

RGB_KIND = "rgb.mp4"  # a chunk's recorded RGB (H.264)
CHUNK_KIND = "json"  # a chunk's record: its source frames, cameras, keys
POSE_RECORD_KIND = "pose.json"  # a pose target's record: what it was rendered from
POSE_KIND = "pose.gbz"  # a chunk's pose-control target (the bridge's G-buffer file)
OLD_POSE_KIND = "pose.mkv"  # a target of an earlier bridge version (FFV1): read past, never joined
VIDEO_KINDS = (RGB_KIND, CHUNK_KIND)  # a video shard's member kinds, in the order they follow one another
POSE_KINDS = (POSE_RECORD_KIND, POSE_KIND)  # a pose shard's
KINDS = VIDEO_KINDS + POSE_KINDS + (OLD_POSE_KIND,)
MAX_MEMBER_BYTES = 1 << 30  # an 81-frame chunk at the training resolution is a few MB


def member_name(key: str, kind: str) -> str:
    """``<key>.<kind>`` for a known kind."""
    if kind not in KINDS:
        raise CorpusPathError(f"{kind!r} is not a video-shard member kind {KINDS}")
    parse_chunk_key(key)
    return f"{key}.{kind}"


def parse_member(name: str, where: str = "") -> tuple[str, str]:
    """(chunk key, kind) of a member name, else CorpusPathError naming ``where``."""
    key, dot, kind = name.partition(".")
    if not dot or kind not in KINDS:
        raise CorpusPathError(f"{where + ': ' if where else ''}member {name!r} is not <segment>__cNNNNN.{{{','.join(KINDS)}}}")
    parse_chunk_key(key, f"{where + ': ' if where else ''}member {name!r}")
    return key, kind


def shard_kinds(path: Path) -> tuple[str, ...]:
    """The member kinds a shard may hold: a pose shard's (under ``pose/``) or a video shard's. Either may hold
    targets of an earlier bridge (``OLD_POSE_KIND``: a video shard written before pose targets had shards of their
    own, a pose shard before the next pose pass rewrites it); they are read past, never joined."""
    return (*POSE_KINDS, OLD_POSE_KIND) if Path(path).parent.name == "pose" else (*VIDEO_KINDS, OLD_POSE_KIND)


def _checked(tar: tarfile.TarFile, path: Path) -> Iterator[tuple[tarfile.TarInfo, str, str]]:
    allowed = shard_kinds(path)
    for m in tar:
        if not m.isfile():
            raise CorpusPathError(f"{path}: member {m.name!r} is not a regular file")
        key, kind = parse_member(m.name, str(path))
        if kind not in allowed:
            raise CorpusPathError(f"{path}: member {m.name!r} is not one of this shard's kinds {allowed}")
        if m.size > MAX_MEMBER_BYTES:
            raise CorpusPathError(f"{path}: member {m.name!r} is {m.size} bytes, over the {MAX_MEMBER_BYTES}-byte limit")
        yield m, key, kind


@contextlib.contextmanager
def _open_shard(path: Path) -> Iterator[tarfile.TarFile]:
    """A shard opened for reading: a regular file only (``regular_file``: a FIFO would block the read), and a tar
    error while it is read raised as a ``CorpusPathError`` naming it."""
    regular_file(path)
    try:
        with tarfile.open(path) as tar:
            yield tar
    except tarfile.TarError as exc:
        raise CorpusPathError(f"{path}: not a readable tar ({exc})") from None


def read_members(path: Path) -> list[tuple[str, bytes]]:
    """Every member (name, bytes) of a shard, in order, each checked (module docstring)."""
    path = Path(path)
    with _open_shard(path) as tar:
        return [(m.name, tar.extractfile(m).read()) for m, _, _ in _checked(tar, path)]


def read_chunks(path: Path, segment: str | None = None, kinds: tuple[str, ...] = VIDEO_KINDS) -> dict[str, dict[str, bytes]]:
    """Chunk key → {kind: bytes} of a shard's chunks (of one ``segment``, if given), reading only ``kinds``."""
    path = Path(path)
    out: dict[str, dict[str, bytes]] = {}
    with _open_shard(path) as tar:
        for m, key, kind in _checked(tar, path):
            if kind in kinds and (segment is None or parse_chunk_key(key)[0] == segment):
                out.setdefault(key, {})[kind] = tar.extractfile(m).read()
    return out


def chunk_record(data: bytes, key: str, where: str) -> dict:
    """A chunk's json member as a dict, checked to name the segment its key names."""
    try:
        rec = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{where}: member {key}.json is not JSON ({exc})") from None
    segment, chunk = parse_chunk_key(key, where)
    if not isinstance(rec, dict) or rec.get("segment") != segment or rec.get("chunk") != chunk:
        raise ValueError(
            f"{where}: member {key}.json names segment {rec.get('segment')!r} chunk {rec.get('chunk')!r}, its key {key!r}"
        )
    return rec


def pose_record(key: str, render_key: str, terrain_chunks: list[str], frames: int, chunk_json: bytes, state_hash: str) -> dict:
    """A chunk's ``pose.json``: the render's key (``derived/pose/<key>-<render key>.gbz``), the terrain chunks its
    cameras saw, its frame count, and what it belongs to: the sha256 of the chunk's video ``json`` member and the
    ingest hash of the state shard it was rendered from."""
    segment, chunk = parse_chunk_key(key)
    return {
        "segment": segment,
        "chunk": chunk,
        "key": render_key,
        "terrain_chunks": list(terrain_chunks),
        "frames": int(frames),
        "video_json": hashlib.sha256(chunk_json).hexdigest(),
        "state_hash": state_hash,
    }


def pose_matches(rec: dict, chunk_json: bytes, state_hash: str) -> bool:
    """Whether a ``pose.json`` record belongs to the chunk whose video json is ``chunk_json``, rendered from the
    state shard of ingest hash ``state_hash`` (a stale record, left by an earlier recording, does not)."""
    return rec.get("video_json") == hashlib.sha256(chunk_json).hexdigest() and rec.get("state_hash") == state_hash


def member_index(path: Path) -> dict[str, dict[str, tarfile.TarInfo]]:
    """Chunk key → {kind: member header} of a shard, every header checked (module docstring); no member's bytes
    are read. ``offset_data`` and ``size`` of a header locate its bytes in the file (``read_at``)."""
    path = Path(path)
    out: dict[str, dict[str, tarfile.TarInfo]] = {}
    with _open_shard(path) as tar:
        for m, key, kind in _checked(tar, path):
            out.setdefault(key, {})[kind] = m
    return out


def read_at(path: Path, offset: int, size: int) -> bytes:
    """``size`` bytes of a shard from ``offset`` (a member located by ``member_index``), or a ValueError naming the
    shard when it holds fewer (it changed since it was indexed)."""
    regular_file(path)
    with open(path, "rb") as f:
        f.seek(offset)
        data = f.read(size)
    if len(data) != size:
        raise ValueError(f"{path}: {size} bytes at offset {offset} expected, {len(data)} there (the shard changed?)")
    return data


class PoseShard:
    """Random access to one pose shard by chunk key: member headers indexed once (each checked), a member's
    bytes read when asked for. A missing shard is an empty one."""

    def __init__(self, path: Path, read: bool = True):
        self.path = Path(path)
        self._tar: tarfile.TarFile | None = None
        self._index: dict[str, tarfile.TarInfo] = {}
        if not read or not self.path.exists():  # unread: empty whatever the file holds (a damaged one, to replace)
            return
        regular_file(self.path)
        try:
            tar = tarfile.open(self.path)  # noqa: SIM115 (held open for ``get``; ``close`` closes it)
        except tarfile.TarError as exc:
            raise CorpusPathError(f"{self.path}: not a readable tar ({exc})") from None
        try:
            self._index = {m.name: m for m, _, _ in _checked(tar, self.path)}
        except (tarfile.TarError, CorpusPathError) as exc:
            tar.close()
            raise CorpusPathError(
                str(exc) if isinstance(exc, CorpusPathError) else f"{self.path}: not a readable tar ({exc})"
            ) from None
        self._tar = tar

    def member(self, key: str, chunk_json: bytes, state_hash: str) -> tuple[dict, tarfile.TarInfo] | None:
        """(``pose.json`` record, ``pose.gbz`` header) of the chunk ``key`` whose video json is ``chunk_json``, or
        None where the shard holds no target for it or only a stale one (``pose_matches``)."""
        info, target = self._index.get(f"{key}.{POSE_RECORD_KIND}"), self._index.get(f"{key}.{POSE_KIND}")
        if info is None or target is None or self._tar is None:
            return None
        try:
            rec = json.loads(self._tar.extractfile(info).read())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{self.path}: member {info.name} is not JSON ({exc})") from None
        if not isinstance(rec, dict) or not pose_matches(rec, chunk_json, state_hash):
            return None
        return rec, target

    def names(self) -> list[str]:
        """Its members' names, in order (none for a missing shard)."""
        return list(self._index)

    def read(self, member: tarfile.TarInfo) -> bytes:
        """The bytes of a ``pose.gbz`` header that ``member`` returned."""
        return self._tar.extractfile(member).read()

    def get(self, key: str, chunk_json: bytes, state_hash: str) -> tuple[dict, bytes] | None:
        """(``pose.json`` record, ``pose.gbz`` bytes) of the chunk (``member``), or None."""
        got = self.member(key, chunk_json, state_hash)
        return None if got is None else (got[0], self.read(got[1]))

    def close(self) -> None:
        if self._tar is not None:
            self._tar.close()
            self._tar = None

    def __enter__(self) -> PoseShard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_joined(
    video: Path, pose: Path, state_hash: str, segment: str | None = None, kinds: tuple[str, ...] = KINDS
) -> dict[str, dict[str, bytes]]:
    """Chunk key → {kind: bytes} of a video shard's chunks (of one ``segment``, if given) joined with their pose
    targets from ``pose`` (current ones only: ``PoseShard.get``), reading only ``kinds``."""
    chunks = read_chunks(video, segment, tuple(k for k in VIDEO_KINDS if k in kinds or k == CHUNK_KIND))
    with PoseShard(pose) as ps:
        for key, m in chunks.items():
            got = ps.get(key, m[CHUNK_KIND], state_hash) if CHUNK_KIND in m and set(kinds) & set(POSE_KINDS) else None
            if got is not None:
                rec, target = got
                m.update({POSE_RECORD_KIND: json.dumps(rec, sort_keys=True).encode(), POSE_KIND: target})
            for kind in KINDS:
                if kind not in kinds:
                    m.pop(kind, None)
    return chunks


def add_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    """Append one member (a checked name, fixed mtime and mode: reruns give identical bytes)."""
    parse_member(name)
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = len(data), 0, 0o644
    tar.addfile(info, io.BytesIO(data))


@contextlib.contextmanager
def writer(path: Path) -> Iterator[tarfile.TarFile]:
    """An open shard to ``add_member`` to; it appears under ``path`` only when the block completes."""
    with atomic_path(path) as tmp, tarfile.open(tmp, "w", format=tarfile.USTAR_FORMAT) as tar:
        yield tar


def write_members(path: Path, members: list[tuple[str, bytes | Path | Callable[[], bytes]]]) -> None:
    """Write a shard of ``members`` (name, and bytes, a file holding them or a call returning them) atomically, one
    member in memory at a time."""
    with writer(path) as tar:
        for name, data in members:
            if callable(data):
                data = data()
            add_member(tar, name, data if isinstance(data, bytes) else Path(data).read_bytes())


__all__ = [
    "KINDS",
    "MAX_MEMBER_BYTES",
    "POSE_KINDS",
    "VIDEO_KINDS",
    "PoseShard",
    "add_member",
    "chunk_key",
    "chunk_record",
    "member_index",
    "member_name",
    "parse_member",
    "pose_matches",
    "pose_record",
    "read_at",
    "read_chunks",
    "read_joined",
    "read_members",
    "shard_kinds",
    "write_members",
    "writer",
]
