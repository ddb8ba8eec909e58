"""The TRN2 chunk file: a 100 m × 100 m chunk of 100 × 100 cells, up to ``max_layers`` layers per cell.

Little-endian. A 32-byte header — ``b"TRN2"``, int32 version = 2, int32 cx, int32 cz,
int32 chunk_m = 100, float32 cell_m = 1.0, int32 cell_count = 10000, int32 max_layers — then
cell_count × max_layers records of 24 bytes, cell-major (all slots of cell 0, then cell 1):
float32 h, float32 nx, ny, nz, uint16 hit_count (saturating), uint8 flags (bit 0 valid, bit 1
filled by hole-fill), uint8 pad = 0, uint32 last_ts (unix seconds of the newest recording that
observed the layer). Unused slots are all zero; slot order carries no meaning.

Cell index = row × 100 + col; world x = cx·100 + col, world z = cz·100 + row; a cell covers
[x, x+1) × [z, z+1). Chunk and cell of a world point use floor, never truncation.
"""

from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from marionette.io import regular_file, write_bytes

MAGIC = b"TRN2"
VERSION = 2
CHUNK_M = 100
CELL_M = 1.0
CELLS = 100  # cells per side
CELL_COUNT = CELLS * CELLS
HEADER = struct.Struct("<4siiiifii")
RECORD = np.dtype([("h", "<f4"), ("n", "<f4", (3,)), ("hits", "<u2"), ("flags", "u1"), ("pad", "u1"), ("ts", "<u4")])
FLAG_VALID = 1
FLAG_FILLED = 2
assert HEADER.size == 32 and RECORD.itemsize == 24


class TerrainFormatError(ValueError):
    """A chunk file does not follow TRN2; the message names the file and what is wrong."""


@dataclass
class Chunk:
    """One chunk: ``cells`` is a (10000, max_layers) structured array of RECORD."""

    cx: int
    cz: int
    cells: np.ndarray

    @property
    def max_layers(self) -> int:
        return self.cells.shape[1]

    @staticmethod
    def empty(cx: int, cz: int, max_layers: int = 8) -> Chunk:
        return Chunk(cx, cz, np.zeros((CELL_COUNT, max_layers), RECORD))

    def valid(self) -> np.ndarray:
        """(10000, L) bool: slots holding a layer."""
        return (self.cells["flags"] & FLAG_VALID) != 0

    def to_bytes(self) -> bytes:
        """The exact file bytes."""
        head = HEADER.pack(MAGIC, VERSION, self.cx, self.cz, CHUNK_M, CELL_M, CELL_COUNT, self.max_layers)
        return head + np.ascontiguousarray(self.cells, RECORD).tobytes()

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Chunk) and self.to_bytes() == other.to_bytes()


def chunk_of(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chunk indices (cx, cz) of world points (floor division; −0.5 m is in chunk −1)."""
    return np.floor(np.asarray(x, np.float64) / CHUNK_M).astype(np.int64), np.floor(np.asarray(z, np.float64) / CHUNK_M).astype(
        np.int64
    )


def cell_of(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global cell indices (world x and z of the cell's lower corner, in cells) by floor."""
    return np.floor(np.asarray(x, np.float64) / CELL_M).astype(np.int64), np.floor(np.asarray(z, np.float64) / CELL_M).astype(
        np.int64
    )


def split_cell(gx: np.ndarray, gz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Global cell indices → (cx, cz, index within the chunk = row × 100 + col)."""
    cx, col = np.divmod(gx, CELLS)
    cz, row = np.divmod(gz, CELLS)
    return cx, cz, row * CELLS + col


def _header(head: bytes, where: str) -> tuple[int, int, int]:
    """(cx, cz, max_layers) of a 32-byte TRN2 header; any deviation raises TerrainFormatError naming ``where``."""
    if len(head) < HEADER.size:
        raise TerrainFormatError(f"{where}: truncated: {len(head)} bytes, the header alone is {HEADER.size}")
    magic, version, cx, cz, chunk_m, cell_m, cell_count, max_layers = HEADER.unpack_from(head)
    if magic != MAGIC:
        raise TerrainFormatError(f"{where}: bad magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise TerrainFormatError(f"{where}: unsupported version {version}, expected {VERSION}")
    if chunk_m != CHUNK_M or cell_m != CELL_M or cell_count != CELL_COUNT:
        raise TerrainFormatError(
            f"{where}: chunk_m={chunk_m}, cell_m={cell_m}, cell_count={cell_count}; expected {CHUNK_M}, {CELL_M}, {CELL_COUNT}"
        )
    if not 1 <= max_layers <= 255:
        raise TerrainFormatError(f"{where}: max_layers={max_layers} out of range 1..255")
    return int(cx), int(cz), int(max_layers)


def _check_size(size: int, max_layers: int, where: str) -> None:
    """The file size the header implies: 32 + 10000 × max_layers × 24 bytes."""
    want = HEADER.size + CELL_COUNT * max_layers * RECORD.itemsize
    if size != want:
        raise TerrainFormatError(
            f"{where}: {'truncated' if size < want else 'trailing bytes'}: {size} bytes, expected {want} "
            f"(header: max_layers={max_layers})"
        )


def _cells(body: bytes, max_layers: int, where: str) -> np.ndarray:
    cells = np.frombuffer(body, RECORD, count=CELL_COUNT * max_layers).reshape(CELL_COUNT, max_layers).copy()
    valid = (cells["flags"] & FLAG_VALID) != 0
    if not np.isfinite(cells["h"][valid]).all() or not np.isfinite(cells["n"][valid]).all():
        raise TerrainFormatError(f"{where}: a valid layer holds a non-finite height or normal")
    return cells


def decode(data: bytes, where: str = "<bytes>") -> Chunk:
    """Parse TRN2 bytes; any deviation from the format raises TerrainFormatError naming ``where``."""
    cx, cz, max_layers = _header(data[: HEADER.size], where)
    _check_size(len(data), max_layers, where)
    return Chunk(cx, cz, _cells(memoryview(data)[HEADER.size :], max_layers, where))


def read_chunk(path: Path, at: tuple[int, int] | None = None) -> Chunk:
    """Read one chunk file: its size is checked against the header before the body is read; with ``at`` (the
    (cx, cz) its file name gives) the header must say the same."""
    path = Path(path)
    where = str(path)
    try:
        regular_file(path)  # a FIFO would block the read
        fh = open(path, "rb")  # noqa: SIM115 (closed by the with below)
    except FileNotFoundError:
        raise TerrainFormatError(f"{path}: no such chunk file") from None
    except ValueError as exc:  # not a regular file
        raise TerrainFormatError(str(exc)) from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        cx, cz, max_layers = _header(fh.read(HEADER.size), where)
        _check_size(size, max_layers, where)
        body = fh.read(size - HEADER.size)
    _check_size(HEADER.size + len(body), max_layers, where)  # the file changed while it was read
    if at is not None and (cx, cz) != tuple(at):
        raise TerrainFormatError(f"{path}: header says chunk ({cx}, {cz}), the file name ({at[0]}, {at[1]})")
    return Chunk(cx, cz, _cells(body, max_layers, where))


def write_chunk(path: Path, chunk: Chunk) -> None:
    """Write one chunk file atomically."""
    write_bytes(path, chunk.to_bytes())


def chunk_filename(cx: int, cz: int) -> str:
    """File name of a chunk in a stage directory, e.g. ``chunk_-10_8.trn2``."""
    return f"chunk_{cx}_{cz}.trn2"


# Chunk file names: ours (a stage's ``chunks/`` directory) and the upstream release's (``c_<cx>_<cz>.bin`` in
# the directory itself, no manifest); the same TRN2 bytes either way.
OWN_NAME = re.compile(r"chunk_(-?\d{1,9})_(-?\d{1,9})\.trn2")
UPSTREAM_NAME = re.compile(r"c_(-?\d{1,9})_(-?\d{1,9})\.bin")


def find_chunks(stage_dir: Path) -> dict[tuple[int, int], Path]:
    """(cx, cz) → chunk file of a stage directory in either naming: ours (``chunks/chunk_<cx>_<cz>.trn2``) or
    the upstream release's (``c_<cx>_<cz>.bin`` in the directory itself). Only regular files whose names match
    and that resolve inside the directory are taken. A missing directory, one holding no chunk file in either
    naming, or one holding both is a ``TerrainFormatError`` naming it."""
    stage_dir = Path(stage_dir)
    if not stage_dir.is_dir():
        raise TerrainFormatError(f"{stage_dir}: no such stage directory")
    root = stage_dir.resolve()
    found: dict[str, dict[tuple[int, int], Path]] = {}
    for naming, folder, pattern in (("ours", stage_dir / "chunks", OWN_NAME), ("upstream", stage_dir, UPSTREAM_NAME)):
        if not folder.is_dir():
            continue
        for entry in sorted(os.scandir(folder), key=lambda e: e.name):
            m = pattern.fullmatch(entry.name)
            if m is None or not entry.is_file():
                continue
            path = Path(entry.path)
            if root not in path.resolve().parents:
                raise TerrainFormatError(f"{path}: resolves to {path.resolve()}, outside the stage directory {root}")
            found.setdefault(naming, {})[(int(m[1]), int(m[2]))] = path
    if len(found) > 1:
        raise TerrainFormatError(
            f"{stage_dir}: holds chunks in both namings (chunks/chunk_<cx>_<cz>.trn2 and c_<cx>_<cz>.bin); keep one"
        )
    if not found:
        raise TerrainFormatError(
            f"{stage_dir}: no terrain chunk in it (neither chunks/chunk_<cx>_<cz>.trn2 nor c_<cx>_<cz>.bin): "
            "not a stage directory, or one never scanned"
        )
    return next(iter(found.values()))
