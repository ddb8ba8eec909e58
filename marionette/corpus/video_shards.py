"""The video shard format: webdataset tars of 81-frame chunks, read and written only here.

A shard ``video/shard-NNNNNN.tar`` holds, per chunk key ``<segment>__c<chunk:05d>`` (``paths.chunk_key``),
the members ``<key>.rgb.mp4`` (the training-resolution RGB), ``<key>.json`` (the chunk's record: source
frames, crop, intrinsics, and ``pose`` once its target is rendered) and, when rendered,
``<key>.pose.mkv`` (the bridge's lossless G-buffer), in that order. Members are regular files with a
fixed mtime and mode, so rewriting a shard with the same members gives the same bytes.

A shard is untrusted input: every member must be a regular file named ``<chunk key>.<kind>`` with a
known kind and a size under ``MAX_MEMBER_BYTES``, or the whole shard is refused with an error naming
it and the member. Nothing is ever extracted to disk.
"""

from __future__ import annotations

import contextlib
import io
import json
import tarfile
from collections.abc import Iterator
from pathlib import Path

from marionette.corpus.paths import CorpusPathError, chunk_key, parse_chunk_key
from marionette.io import atomic_path

KINDS = ("rgb.mp4", "json", "pose.mkv")  # member kinds, in the order they follow one another
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


def _checked(tar: tarfile.TarFile, path: Path) -> Iterator[tuple[tarfile.TarInfo, str, str]]:
    for m in tar:
        if not m.isfile():
            raise CorpusPathError(f"{path}: member {m.name!r} is not a regular file")
        key, kind = parse_member(m.name, str(path))
        if m.size > MAX_MEMBER_BYTES:
            raise CorpusPathError(f"{path}: member {m.name!r} is {m.size} bytes, over the {MAX_MEMBER_BYTES}-byte limit")
        yield m, key, kind


def read_members(path: Path) -> list[tuple[str, bytes]]:
    """Every member (name, bytes) of a shard, in order, each checked (module docstring)."""
    path = Path(path)
    try:
        with tarfile.open(path) as tar:
            return [(m.name, tar.extractfile(m).read()) for m, _, _ in _checked(tar, path)]
    except tarfile.TarError as exc:
        raise CorpusPathError(f"{path}: not a readable tar ({exc})") from None


def read_chunks(path: Path, segment: str | None = None, kinds: tuple[str, ...] = KINDS) -> dict[str, dict[str, bytes]]:
    """Chunk key → {kind: bytes} of a shard's chunks (of one ``segment``, if given), reading only ``kinds``."""
    path = Path(path)
    out: dict[str, dict[str, bytes]] = {}
    try:
        with tarfile.open(path) as tar:
            for m, key, kind in _checked(tar, path):
                if kind in kinds and (segment is None or parse_chunk_key(key)[0] == segment):
                    out.setdefault(key, {})[kind] = tar.extractfile(m).read()
    except tarfile.TarError as exc:
        raise CorpusPathError(f"{path}: not a readable tar ({exc})") from None
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


def write_members(path: Path, members: list[tuple[str, bytes]]) -> None:
    """Write a shard of ``members`` (name, bytes) atomically."""
    with writer(path) as tar:
        for name, data in members:
            add_member(tar, name, data)


__all__ = [
    "KINDS",
    "MAX_MEMBER_BYTES",
    "add_member",
    "chunk_key",
    "chunk_record",
    "member_name",
    "parse_member",
    "read_chunks",
    "read_members",
    "write_members",
    "writer",
]
