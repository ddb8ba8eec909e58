"""A live session's recordings: the frames kept since the last reset (``History``), a free recording name, and the
written pair ``<name>.arrow`` (corpus-schema state, ``rollout.rollout_table``) and ``<name>.mkv`` (a G-buffer video of
them through the follow camera, ``bridge.targets.render_rows``) — what ``marionette render`` and ``marionette play
--replay`` read."""

from __future__ import annotations

import os
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from marionette.bridge.targets import TerrainScene, render_rows
from marionette.dynamics.engine import Rollout
from marionette.io import publish_new, write_ipc
from marionette.schema import Layout

MAX_HISTORY = 72_000  # frames kept since the last reset (an hour at 20 fps)


@dataclass
class History:
    """Everything a session's frames were: state rows, world roots and rotations, tokens and progress."""

    states: deque = field(default_factory=lambda: deque(maxlen=MAX_HISTORY))
    roots: deque = field(default_factory=lambda: deque(maxlen=MAX_HISTORY))
    quats: deque = field(default_factory=lambda: deque(maxlen=MAX_HISTORY))
    tokens: deque = field(default_factory=lambda: deque(maxlen=MAX_HISTORY))
    progress: deque = field(default_factory=lambda: deque(maxlen=MAX_HISTORY))

    def add(self, ro: Rollout, state: np.ndarray) -> None:
        self.states.append(np.asarray(state, np.float32))
        self.roots.append(ro.roots_world.copy())
        self.quats.append(ro.quats.copy())
        self.tokens.append(ro.tok.copy())
        self.progress.append(ro.progress.copy())

    def __len__(self) -> int:
        return len(self.states)


def name_taken(record_dir: Path, written: list[dict], name: str) -> bool:
    """Whether a recording ``name`` is written under ``record_dir`` (either file) or being written."""
    on_disk = any((record_dir / f"{name}{ext}").exists() for ext in (".arrow", ".mkv"))
    return on_disk or any(w["name"] == name for w in written)


def free_name(record_dir: Path, written: list[dict]) -> str:
    """The first ``session-NNN`` neither written under ``record_dir`` nor being written."""
    k = 1
    while name_taken(record_dir, written, f"session-{k:03d}"):
        k += 1
    return f"session-{k:03d}"


def write_recording(
    table: pa.Table,
    out: dict,
    record_dir: Path,
    layout: Layout,
    terrain: TerrainScene | None,
    size: tuple[int, int],
    log: Callable[[str], None],
) -> None:
    """Write ``out["arrow"]`` and ``out["mkv"]`` from ``table``; ``out["done"]`` on success, else ``out["error"]``
    (reported to the page; the session goes on)."""
    tmp = f".{out['name']}.{os.getpid()}.{threading.get_ident()}.tmp"  # renamed only to a free name
    try:
        record_dir.mkdir(parents=True, exist_ok=True)
        arrow, mkv = Path(out["arrow"]), Path(out["mkv"])
        write_ipc(record_dir / f"{tmp}.arrow", table)
        render_rows(layout, table, record_dir / f"{tmp}.mkv", terrain, camera="follow", size=size)
        publish_new(record_dir / f"{tmp}.arrow", arrow)
        publish_new(record_dir / f"{tmp}.mkv", mkv)
        out["done"] = True
        log(f"play: wrote {out['arrow']} and {out['mkv']} ({out['frames']} frames)")
    except Exception as err:  # noqa: BLE001 - reported to the page, the session goes on
        for ext in (".arrow", ".mkv"):
            (record_dir / f"{tmp}{ext}").unlink(missing_ok=True)
        out["error"] = f"{type(err).__name__}: {err}"
        log(f"play: recording {out['name']} failed: {out['error']}")
