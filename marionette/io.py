"""Atomic writes and content hashes: a crash never leaves a half-written file or directory under its final name."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from marionette.arrow_footer import ArrowFooterError, declared_batches


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
        _fsync_dir(path.parent)
    except OSError as exc:
        if exc.filename is None:  # a failed write (disk full) names no file: name the one being written
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    finally:
        tmp.unlink(missing_ok=True)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_dir(path: Path, exists: str = "replace") -> Iterator[Path]:
    """Yield a fresh empty directory beside ``path`` (mode 0755) to fill; on success fsync its files, rename it to
    ``path`` and fsync the parent. Where ``path`` is a directory already, ``exists`` says what wins: "replace" moves
    the old one aside, renames the new one in and deletes the old one (readers see one or the other, never a mix);
    "keep" keeps the one there (another process, a DDP rank, published the same content first) and discards the
    new one. On an error the temp directory is deleted and ``path`` is as it was."""
    if exists not in ("replace", "keep"):
        raise ValueError(f"atomic_dir: exists must be 'replace' or 'keep', not {exists!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a fresh name: writers on other machines sharing the directory may have this process's pid
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes 0700; what is published is read by other users and services
    try:
        yield tmp
        for f in sorted(tmp.rglob("*")):
            if f.is_file():
                with open(f, "rb") as fh:
                    os.fsync(fh.fileno())
        if path.is_dir() and exists == "replace":
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-", dir=path.parent))
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        elif not path.is_dir():
            try:
                os.replace(tmp, path)
            except OSError:  # another process renamed its copy in first
                if exists == "replace" or not path.is_dir():
                    raise
        _fsync_dir(path.parent)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def publish_new(tmp: Path, path: Path) -> None:
    """Give the finished file ``tmp`` the name ``path`` unless a file has it already (``FileExistsError`` naming it,
    ``tmp`` removed): a hard link is created only where the name is free, so two writers never overwrite each other."""
    tmp, path = Path(tmp), Path(path)
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, "exists already; choose another name", str(path)) from None
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(path.parent)


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


MAX_STRING_BYTES = 4096  # bytes a string cell of an Arrow file from outside may take (ids and names: a few dozen)


def max_row_bytes(t: pa.DataType | pa.Schema) -> int:
    """The most bytes one row of a schema (or one value of a type) can take once inflated: fixed widths as they are,
    a string ``MAX_STRING_BYTES``, each with its validity bit (a byte, to be safe) and its offset."""
    if isinstance(t, pa.Schema):
        return sum(max_row_bytes(f.type) for f in t)
    if pa.types.is_fixed_size_list(t):
        return 1 + t.list_size * max_row_bytes(t.value_type)
    if pa.types.is_struct(t):
        return 1 + sum(max_row_bytes(t.field(i).type) for i in range(t.num_fields))
    if pa.types.is_string(t) or pa.types.is_binary(t) or pa.types.is_large_string(t) or pa.types.is_large_binary(t):
        return 1 + 8 + MAX_STRING_BYTES
    if pa.types.is_boolean(t):
        return 2
    try:
        return 1 + t.bit_width // 8
    except ValueError:  # a variable-size type the project never writes: as much as a string
        return 1 + 8 + MAX_STRING_BYTES


def read_ipc(path: Path, rows: int | None = None, check_schema: Callable[[pa.Schema], None] | None = None) -> pa.Table:
    """Read a whole Arrow IPC file (memory-mapped; a regular file only, ``regular_file``), its declarations checked
    before anything is inflated (``arrow_footer.declared_batches``): the schema by ``check_schema`` (a layout check),
    the batches' rows against ``rows`` where the caller knows how many the file holds, and the bytes they inflate to
    against what that many rows of the schema can take (``max_row_bytes``)."""
    regular_file(path)
    try:
        declared = declared_batches(path)
    except ArrowFooterError as exc:
        raise ValueError(str(exc)) from None
    with pa.memory_map(str(path), "r") as src:
        try:
            reader = pa.ipc.open_file(src)
        except (pa.ArrowException, OSError) as exc:
            raise ValueError(f"{path}: unreadable Arrow IPC file ({type(exc).__name__}: {exc})") from None
        if check_schema is not None:
            check_schema(reader.schema)
        n = sum(b.rows for b in declared)
        if len(declared) != reader.num_record_batches:
            raise ValueError(f"{path}: {reader.num_record_batches} record batches, its footer read as {len(declared)}")
        if rows is not None and n != rows:
            raise ValueError(f"{path}: its batches declare {n:,} rows; the corpus says it holds {rows:,}")
        limit = n * max_row_bytes(reader.schema) + (1 << 20)
        inflated = sum(b.inflated_bytes for b in declared)
        if inflated > limit:
            raise ValueError(
                f"{path}: its batches declare {inflated:,} bytes once inflated, more than {n:,} rows of its schema can take "
                f"({limit:,}): refused before it is inflated"
            )
        try:
            return reader.read_all()
        except (pa.ArrowException, OSError) as exc:  # a damaged body (a bad codec frame, a buffer past the end)
            raise ValueError(f"{path}: unreadable Arrow IPC file ({type(exc).__name__}: {exc})") from None


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


def printable(s: str) -> str:
    """``s`` with every character a terminal would act on or hide (control characters, undecodable bytes) written as
    its escape, for a name from outside printed in a log line or error."""
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in s)


MAX_JSON_DEPTH = 64  # nesting a JSON file from outside may have; the project's deepest is under 10


_KINDS = (
    (stat.S_ISDIR, "directory"),
    (stat.S_ISFIFO, "FIFO"),
    (stat.S_ISCHR, "character device"),
    (stat.S_ISBLK, "block device"),
    (stat.S_ISSOCK, "socket"),
)


def _check_regular(path: Path, st: os.stat_result) -> os.stat_result:
    """``st`` if it is a regular file's; a ValueError naming ``path`` and what it is otherwise."""
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "special file")
        raise ValueError(f"{path}: a {kind}, not a regular file")
    return st


def regular_file(path: Path) -> os.stat_result:
    """The stat of ``path`` (a link followed) if it is a regular file; a ValueError naming it otherwise. A FIFO, device
    or socket is never opened for a blocking read (one could hang the command, or never end)."""
    return _check_regular(path, os.stat(path))


def read_bounded(path: Path, max_bytes: int, what: str = "this file") -> bytes:
    """A regular file's bytes, at most ``max_bytes`` read whatever its size says (a ValueError naming the file past
    it). Opened without blocking and checked on the open descriptor, so a file swapped for a FIFO is refused too."""
    path = Path(path)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        _check_regular(path, os.fstat(fd))
        os.set_blocking(fd, True)
        chunks, got = [], 0
        while got <= max_bytes and (chunk := os.read(fd, min(1 << 20, max_bytes + 1 - got))):
            chunks.append(chunk)
            got += len(chunk)
    finally:
        os.close(fd)
    if got > max_bytes:
        raise ValueError(f"{path}: over the {max_bytes}-byte limit for {what}")
    return b"".join(chunks)


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_JSON_BRACKET = re.compile(r"[\[\]{}]")


def json_depth(text: str) -> int:
    """The deepest nesting of brackets outside strings in JSON text, counted without recursing (so a value nested
    too deep for the parser is measured, not parsed)."""
    depth = deepest = 0
    for m in _JSON_BRACKET.finditer(_JSON_STRING.sub("", text)):
        depth += 1 if m.group() in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def loads_json(raw: bytes | str, where: str, max_depth: int = MAX_JSON_DEPTH):
    """The value of JSON text from outside, nested at most ``max_depth`` deep (measured before it is parsed); a
    ValueError naming ``where`` when it is not UTF-8 JSON or nested deeper."""
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else raw
    except UnicodeDecodeError as exc:
        raise ValueError(f"{where}: not JSON ({exc})") from None
    if (depth := json_depth(text)) > max_depth:
        raise ValueError(f"{where}: JSON nested {depth} deep, past the limit of {max_depth}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not JSON ({exc})") from None


def read_json(path: Path, max_bytes: int = 64 << 20, max_depth: int = MAX_JSON_DEPTH):
    """A JSON file's value, through ``read_bounded`` and ``loads_json``; a ValueError naming the file when it is not a
    regular file, too large, nested past ``max_depth`` or not JSON."""
    return loads_json(read_bounded(path, max_bytes, "a JSON file"), str(path), max_depth)


def read_tensors(path: Path) -> dict:
    """The tensors of a safetensors file (never a pickle); a ValueError naming the file if it is not one."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    regular_file(path)
    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as exc:
        raise ValueError(f"{path}: not a readable safetensors file ({exc})") from None
