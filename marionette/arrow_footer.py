"""What an Arrow IPC file declares before any of it is inflated: each record batch's row count and the bytes its
buffers take once decompressed, read from the file's footer and its batches' message headers alone.

A compressed IPC buffer starts with its uncompressed length (an int64; -1 when it was stored as it is), so a file of
kilobytes can declare gigabytes: Arrow allocates what a buffer declares before it decompresses it. ``declared_batches``
reads those declarations (the flatbuffer tables of the format's ``File.fbs`` and ``Message.fbs``) so that a reader
can refuse a file whose declarations pass its limits before anything is allocated."""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass
from pathlib import Path

MAGIC = b"ARROW1"
RECORD_BATCH = 3  # Message.fbs: MessageHeader's member for a record batch


class ArrowFooterError(ValueError):
    """An IPC file whose footer or batch headers do not read as the format's."""


class _Buffer:
    """Bounds-checked little-endian reads from a byte buffer."""

    def __init__(self, data: bytes | mmap.mmap, where: str) -> None:
        self.data, self.where = data, where

    def read(self, fmt: str, pos: int) -> int:
        size = struct.calcsize(fmt)
        if pos < 0 or pos + size > len(self.data):
            raise ArrowFooterError(f"{self.where}: an offset ({pos}) points outside the file ({len(self.data)} bytes)")
        return struct.unpack_from(fmt, self.data, pos)[0]


class _Table:
    """A flatbuffer table at ``pos``: its fields by index (the schema's order)."""

    def __init__(self, buf: _Buffer, pos: int) -> None:
        self.buf, self.pos = buf, pos
        self.vtable = pos - buf.read("<i", pos)
        self.vtable_size = buf.read("<H", self.vtable)

    def _field(self, i: int) -> int | None:
        slot = 4 + 2 * i
        if slot + 2 > self.vtable_size:
            return None
        off = self.buf.read("<H", self.vtable + slot)
        return self.pos + off if off else None

    def scalar(self, i: int, fmt: str, default: int = 0) -> int:
        p = self._field(i)
        return default if p is None else self.buf.read(fmt, p)

    def table(self, i: int) -> _Table | None:
        p = self._field(i)
        return None if p is None else _Table(self.buf, p + self.buf.read("<I", p))

    def vector(self, i: int) -> tuple[int, int]:
        """(position of the first element, element count) of a vector field; (0, 0) where it is absent."""
        p = self._field(i)
        if p is None:
            return 0, 0
        v = p + self.buf.read("<I", p)
        return v + 4, self.buf.read("<I", v)


def _root(buf: _Buffer, pos: int) -> _Table:
    return _Table(buf, pos + buf.read("<I", pos))


@dataclass(frozen=True)
class DeclaredBatch:
    """One record batch as its header declares it: rows, and bytes once every buffer is decompressed."""

    rows: int
    inflated_bytes: int


def declared_batches(path: Path) -> list[DeclaredBatch]:
    """Every record batch of the IPC file at ``path`` as declared (``DeclaredBatch``), nothing inflated; an
    ``ArrowFooterError`` naming the file where the footer or a header does not read."""
    where = str(path)
    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        if size < 2 * len(MAGIC) + 4:
            raise ArrowFooterError(f"{where}: {size} bytes, too short for an Arrow IPC file")
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            if data[: len(MAGIC)] != MAGIC or data[-len(MAGIC) :] != MAGIC:
                raise ArrowFooterError(f"{where}: not an Arrow IPC file (no ARROW1 magic at both ends)")
            buf = _Buffer(data, where)
            footer_len = buf.read("<i", size - len(MAGIC) - 4)
            footer_at = size - len(MAGIC) - 4 - footer_len
            if footer_len <= 0 or footer_at < len(MAGIC):
                raise ArrowFooterError(f"{where}: a footer of {footer_len} bytes does not fit the file")
            first, count = _root(buf, footer_at).vector(3)  # Footer.recordBatches: [Block]
            return [_batch(buf, first + 24 * k) for k in range(count)]


def _batch(buf: _Buffer, block: int) -> DeclaredBatch:
    """The batch a footer Block (offset: long, metaDataLength: int, bodyLength: long) points at."""
    offset, meta_len = buf.read("<q", block), buf.read("<i", block + 8)
    at = offset + (8 if buf.read("<I", offset) == 0xFFFFFFFF else 4)  # a continuation marker, then the length
    message = _root(buf, at)
    if message.scalar(1, "<B") != RECORD_BATCH:
        raise ArrowFooterError(f"{buf.where}: a footer block at {offset} is not a record batch")
    header = message.table(2)
    if header is None:
        raise ArrowFooterError(f"{buf.where}: the record batch at {offset} has no header")
    rows = header.scalar(0, "<q")
    compressed = header.table(3) is not None
    body = offset + meta_len
    first, count = header.vector(2)  # RecordBatch.buffers: [Buffer (offset: long, length: long)]
    inflated = 0
    for k in range(count):
        b_off, b_len = buf.read("<q", first + 16 * k), buf.read("<q", first + 16 * k + 8)
        if b_off < 0 or b_len < 0:
            raise ArrowFooterError(f"{buf.where}: the record batch at {offset} declares a buffer at {b_off} of {b_len} bytes")
        if compressed and b_len >= 8:
            n = buf.read("<q", body + b_off)
            inflated += b_len - 8 if n == -1 else n
        else:
            inflated += b_len
    if rows < 0 or inflated < 0:
        raise ArrowFooterError(f"{buf.where}: the record batch at {offset} declares {rows} rows, {inflated} bytes")
    return DeclaredBatch(rows, inflated)
