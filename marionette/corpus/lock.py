"""The corpus lock: one writer at a time (ingest, terrain scan, pose targets; CLI and flows alike).

``<corpus>/meta/.lock`` is held with ``flock`` for the whole of a write, and holds the writer's pid
and what it is doing, so a second writer fails at once with a message naming them. Every writer takes
the lock itself; a pipeline that runs several writers in turn (ingest, then the scan, then the pose
pass) holds it with ``share=True``, and the writers it calls in the same process join that hold
instead of failing. A hold without ``share`` admits nobody, in this process or another. Readers
(training, evaluation) take no lock.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import threading
from collections.abc import Iterator
from pathlib import Path

from marionette.corpus.paths import meta

_held: dict[str, list] = {}  # resolved lock path → [shared, depth] of this process's hold
_guard = threading.Lock()


class CorpusLocked(RuntimeError):
    """Another process is writing the corpus."""


@contextlib.contextmanager
def corpus_lock(corpus: Path, what: str = "write", share: bool = False) -> Iterator[None]:
    """Hold ``<corpus>/meta/.lock`` exclusively while writing (``what`` names the writer to others); a
    second writer fails at once (CorpusLocked), unless this process holds it with ``share=True``."""
    path = meta(corpus, ".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    name = str(path.resolve())
    with _guard:
        joined = name in _held and _held[name][0]
        if joined:
            _held[name][1] += 1
    if joined:
        try:
            yield
        finally:
            with _guard:
                _held[name][1] -= 1
        return
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "another process"
            raise CorpusLocked(f"{corpus}: another build, {holder}, holds {path}; wait for it to finish") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} ({what})\n".encode(), 0)
        with _guard:
            _held[name] = [share, 1]
        try:
            yield
        finally:
            with _guard:
                del _held[name]
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
