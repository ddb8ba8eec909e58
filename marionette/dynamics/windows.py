"""The dynamics windows' arrays on disk: computed a shard at a time, memory-mapped.

**Window arrays on disk** (``shard_windows``). What a window reads — normalised root and body
(float32), tokens (int64), progress (float32), and when asked terrain features and ``known`` and the
relative feature — is computed one shard at a time and stored as one ``.npy`` file per array under
``<corpus>/derived/windows/shard-NNNNNN-<fps>fps-<method>-t<0|1>r<0|1>-<key>/`` (t, r: terrain
and relative arrays held) with ``segments.json`` (each
segment's [first, end) rows, contiguous in the view), written to a temporary directory and renamed
into place. ``WindowData`` opens them memory-mapped (``allow_pickle=False``; every array's dtype and
shape checked against the layout before use, a mismatch recomputed), so a process's memory holds the
pages its windows touch — the page cache, shared by the ranks and workers of one machine — and not
the split: its anonymous memory does not grow with the corpus. The key: sha256 over the shard's
dynamics-view key, the normaliser, the token tables' vocab hash and sizes, the terrain features' key
when they are read, the relative flag and ``WINDOWS_VERSION``; directories of the same shard, rate and
arrays under another key are removed after a write.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from marionette.corpus import MODEL_FPS, Corpus, fixed_rows, paths
from marionette.corpus.vocab import ActionTokens, entity_type_key  # noqa: F401 — the models' token tables
from marionette.dynamics.config import TERRAIN_FEATURES
from marionette.dynamics.features import _dynamics_key, relative_of_rows, terrain_feature_path, terrain_feature_shard
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.state import body_index, root_index
from marionette.io import atomic_dir, read_json, text_sha256, write_json
from marionette.schema import Layout, SchemaError

WINDOWS_DIR = "windows"


WINDOWS_VERSION = "2"  # 2: progress counts the time past the source frame


WINDOW_ARRAYS = ("root", "body", "action", "progress", "features", "known", "rel")


def _window_dtypes(layout: Layout) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """Each window array's dtype and shape after its row axis."""
    N = len(layout.articulated)
    return {
        "root": (np.dtype(np.float32), (len(root_index(layout)),)),
        "body": (np.dtype(np.float32), (len(body_index(layout)),)),
        "action": (np.dtype(np.int64), (N,)),
        "progress": (np.dtype(np.float32), (N,)),
        "features": (np.dtype(np.float32), (N, TERRAIN_FEATURES)),
        "known": (np.dtype(bool), (N, TERRAIN_FEATURES)),
        "rel": (np.dtype(np.float32), (N, 3)),
    }


def shard_windows_dir(
    c: Corpus, shard: int, normaliser: Normaliser, tokens: ActionTokens, *, terrain: bool, relative: bool, fps: float, method: str
) -> Path:
    """Where a shard's window arrays live under their current key (module doc: window arrays on disk)."""
    parts = [
        _dynamics_key(c, shard, fps, method),
        json.dumps(normaliser.to_json(), sort_keys=True),
        tokens.vocab_hash,
        json.dumps([list(tokens.entities), list(tokens.sizes)]),
        terrain_feature_path(c, shard, fps, method).name if terrain else "no terrain",
        f"relative={relative}",
        WINDOWS_VERSION,
    ]
    reads = f"t{int(terrain)}r{int(relative)}"
    return paths.derived(c.path, WINDOWS_DIR) / f"shard-{shard:06d}-{fps:g}fps-{method}-{reads}-{text_sha256(*parts)[:16]}"


def shard_windows(
    c: Corpus,
    shard: int,
    normaliser: Normaliser,
    tokens: ActionTokens,
    *,
    terrain: bool = False,
    relative: bool = False,
    fps: float = MODEL_FPS,
    method: str = "linear",
) -> tuple[dict[str, np.ndarray | None], dict[str, tuple[int, int]]]:
    """A shard's window arrays, memory-mapped read-only (None for the ones not asked for), and each segment's
    [first, end) rows; computed and stored on first use (module doc: window arrays on disk)."""
    d = shard_windows_dir(c, shard, normaliser, tokens, terrain=terrain, relative=relative, fps=fps, method=method)
    names = [k for k in WINDOW_ARRAYS if (k not in ("features", "known") or terrain) and (k != "rel" or relative)]
    if d.is_dir():
        opened = _open_windows(c, d, names)
        if opened is not None:
            return opened
        shutil.rmtree(d, ignore_errors=True)  # a stale or damaged cache is recomputed
    _write_windows(c, shard, d, normaliser, tokens, terrain=terrain, relative=relative, fps=fps, method=method)
    opened = _open_windows(c, d, names)
    if opened is None:
        raise SchemaError(f"{d}: the window arrays just written do not read back")
    return opened


def _open_windows(c: Corpus, d: Path, names: list[str]):
    """The arrays of ``d`` memory-mapped and its segment spans, or None when anything disagrees with the layout."""
    expected = _window_dtypes(c.layout)
    try:
        spans = {str(k): (int(v[0]), int(v[1])) for k, v in read_json(d / "segments.json").items()}
        arrays: dict[str, np.ndarray | None] = dict.fromkeys(WINDOW_ARRAYS)
        n = None
        for k in names:
            a = np.load(d / f"{k}.npy", mmap_mode="r", allow_pickle=False)
            dtype, tail = expected[k]
            if a.dtype != dtype or a.shape[1:] != tail or (n is not None and len(a) != n):
                return None
            n, arrays[k] = len(a), a
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None
    if any(not 0 <= a <= b <= (n or 0) for a, b in spans.values()):
        return None
    return arrays, spans


def _write_windows(
    c: Corpus,
    shard: int,
    d: Path,
    normaliser: Normaliser,
    tokens: ActionTokens,
    *,
    terrain: bool,
    relative: bool,
    fps: float,
    method: str,
) -> None:
    layout = c.layout
    view = c.dynamics_shard(shard, fps, method)
    state = fixed_rows(view["state"], layout.dim)
    out: dict[str, np.ndarray] = {
        "root": normaliser.normalise_root(state[:, root_index(layout)]).astype(np.float32),
        "body": normaliser.normalise_body(state[:, body_index(layout)]).astype(np.float32),
    }
    out["action"], out["progress"] = tokens.encode(layout, view, where=str(c.dynamics_dir(fps, method)))
    out["action"], out["progress"] = out["action"].astype(np.int64), out["progress"].astype(np.float32)
    if terrain:
        out["features"], out["known"] = terrain_feature_shard(c, shard, fps, method)
    if relative:
        out["rel"] = relative_of_rows(layout, view).astype(np.float32)
    names = view["segment"].to_numpy(zero_copy_only=False)
    spans: dict[str, list[int]] = {}
    for s in dict.fromkeys(names.tolist()):
        idx = np.flatnonzero(names == s)
        if idx[-1] - idx[0] + 1 != len(idx):
            raise SchemaError(f"{c.dynamics_dir(fps, method)}: shard {shard}'s rows of segment {s} are not contiguous")
        spans[str(s)] = [int(idx[0]), int(idx[-1]) + 1]
    with atomic_dir(d, exists="keep") as tmp:  # a DDP rank that put the same arrays there first wins
        for k, a in out.items():
            np.save(tmp / f"{k}.npy", np.ascontiguousarray(a), allow_pickle=False)
        write_json(tmp / "segments.json", spans)
    prefix = d.name[: -len(d.name.rsplit("-", 1)[1])]  # the same shard, rate and arrays
    for old in d.parent.glob(prefix + "*"):  # under an older key
        if old != d and old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
