"""Atomic writes and content hashes: a crash never leaves a half-written file under its final name."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a fresh temp path beside ``path``; on success fsync it, rename it over ``path`` and fsync
    the directory. Concurrent writers (threads or processes) never share a temp file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    os.chmod(tmp, 0o644)  # mkstemp makes 0600; corpus files are read by other users and services
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError as exc:
        if exc.filename is None:  # a failed write (disk full) names no file: name the one being written
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: Path, data: bytes) -> None:
    """Write bytes atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: Path, obj) -> None:
    """Write JSON atomically (sorted keys, indented, so reruns give identical bytes)."""
    write_bytes(path, (json.dumps(obj, indent=1, sort_keys=True, allow_nan=False) + "\n").encode())


def write_parquet(path: Path, table: pa.Table) -> None:
    """Write a Parquet table atomically."""
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def write_ipc(path: Path, table: pa.Table, compression: str | None = "zstd") -> None:
    """Write an Arrow IPC file atomically; compression None, 'lz4' or 'zstd'."""
    opts = pa.ipc.IpcWriteOptions(compression=None if compression in (None, "none") else compression)
    with atomic_path(path) as tmp, pa.OSFile(str(tmp), "wb") as sink, pa.ipc.new_file(sink, table.schema, options=opts) as w:
        w.write_table(table)


def read_ipc(path: Path) -> pa.Table:
    """Read a whole Arrow IPC file (memory-mapped)."""
    with pa.memory_map(str(path), "r") as src:
        return pa.ipc.open_file(src).read_all()


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while b := fh.read(chunk):
            h.update(b)
    return h.hexdigest()


def text_sha256(*parts: str) -> str:
    """Hex sha256 of strings joined by newlines."""
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def check_json_fields(cls: type, d: dict, what: str) -> None:
    """Fail, naming them, on keys of ``d`` that are not fields of the dataclass ``cls`` (a config JSON from another version)."""
    unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ValueError(f"{what} JSON has unknown fields {unknown}")


def read_json(path: Path, max_bytes: int = 64 << 20):
    """A JSON file's value; a ValueError naming the file when it is too large or not JSON."""
    path = Path(path)
    size = path.stat().st_size
    if size > max_bytes:
        raise ValueError(f"{path}: {size} bytes, over the {max_bytes}-byte limit for a JSON file")
    try:
        return json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None


def read_tensors(path: Path) -> dict:
    """The tensors of a safetensors file (never a pickle); a ValueError naming the file if it is not one."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as exc:
        raise ValueError(f"{path}: not a readable safetensors file ({exc})") from None
