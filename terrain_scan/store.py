"""A stage on disk: per-recording contributions, the derived TRN2 chunks, and a manifest.

```
<stage_dir>/manifest.json                 recordings (input hash, time, observation count, chunks touched)
                                          and chunks (file, sha256, contributing recordings)
<stage_dir>/contributions/<key>.npz       one recording's merged observations (gx, gz, h, n, hits, ts)
<stage_dir>/chunks/chunk_<cx>_<cz>.trn2   the layered height field
```

Chunks are always derived from all contributions (merge, then hole fill), so adding recordings in
any order, re-scanning one, or rebuilding from scratch give byte-identical chunk files. A rebuild
writes only the chunk files whose bytes change: untouched chunks keep their bytes and mtime.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from marionette.corpus.paths import CorpusPathError, inside
from marionette.io import atomic_path, write_bytes, write_json
from terrain_scan.fill import fill_holes
from terrain_scan.layers import MAX_LAYERS, Observations, drop_aliases, merge
from terrain_scan.trn2 import FLAG_FILLED, FLAG_VALID, Chunk, chunk_filename, split_cell

MANIFEST_FORMAT = "marionette-terrain-stage"
MANIFEST_VERSION = 1
FILL_ROUNDS = 2
CHUNK_NAME = re.compile(r"(-?\d{1,9})_(-?\d{1,9})")


def recording_key(recording: str) -> str:
    """File-safe, collision-free name of a recording's contribution."""
    clean = re.sub(r"[^A-Za-z0-9_-]", "-", recording)
    return f"{clean}--{hashlib.sha256(recording.encode()).hexdigest()[:8]}"


def contribution_file(recording: str) -> str:
    """``contributions/<key>.npz``: where a recording's contribution lives, relative to the stage."""
    return f"contributions/{recording_key(recording)}.npz"


def chunk_file(cx: int, cz: int) -> str:
    """``chunks/chunk_<cx>_<cz>.trn2``, relative to the stage."""
    return f"chunks/{chunk_filename(cx, cz)}"


def parse_chunk_name(name: object, where: str) -> tuple[int, int]:
    """(cx, cz) of a manifest chunk name ``"<cx>_<cz>"``, else CorpusPathError naming ``where``."""
    m = CHUNK_NAME.fullmatch(name) if isinstance(name, str) else None
    if m is None:
        raise CorpusPathError(f"{where}: chunk name {name!r} is not <cx>_<cz>")
    return int(m[1]), int(m[2])


def check_manifest(manifest: object, path: Path) -> dict:
    """A stage manifest read from disk, checked: its format, and every file it names is the one its
    recording or chunk name gives (so no entry can point outside the stage); else an error naming the entry."""
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{path}: not a terrain stage manifest")
    recs, chunks = manifest.get("recordings"), manifest.get("chunks")
    if not isinstance(recs, dict) or not isinstance(chunks, dict):
        raise ValueError(f"{path}: a stage manifest needs 'recordings' and 'chunks' objects")
    for name, rec in recs.items():
        if not isinstance(rec, dict) or rec.get("file") != contribution_file(name):
            got = rec.get("file") if isinstance(rec, dict) else rec
            raise CorpusPathError(f"{path}: recordings.{name}.file is {got!r}, not {contribution_file(name)!r}")
        for i, c in enumerate(rec.get("chunks", [])):
            if not (isinstance(c, list) and len(c) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in c)):
                raise ValueError(f"{path}: recordings.{name}.chunks[{i}] is not [cx, cz]")
    for name, rec in chunks.items():
        cx, cz = parse_chunk_name(name, str(path))
        if not isinstance(rec, dict) or rec.get("file") != chunk_file(cx, cz):
            got = rec.get("file") if isinstance(rec, dict) else rec
            raise CorpusPathError(f"{path}: chunks.{name}.file is {got!r}, not {chunk_file(cx, cz)!r}")
    return manifest


@dataclass
class RebuildReport:
    """Which chunk files a rebuild wrote, left untouched, or removed."""

    written: list[tuple[int, int]] = field(default_factory=list)
    unchanged: list[tuple[int, int]] = field(default_factory=list)
    removed: list[tuple[int, int]] = field(default_factory=list)
    layers: int = 0
    filled: int = 0


class Stage:
    """One game stage's terrain: contributions in, chunks out."""

    def __init__(self, stage_dir: Path, max_layers: int = MAX_LAYERS, fill_rounds: int = FILL_ROUNDS):
        self.dir = Path(stage_dir)
        self.max_layers = max_layers
        self.fill_rounds = fill_rounds
        path = self.dir / "manifest.json"
        if path.exists():
            try:
                self.manifest = check_manifest(json.loads(path.read_text()), path)
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise ValueError(f"{path}: not a terrain stage manifest ({exc})") from None
        else:
            self.manifest = {
                "format": MANIFEST_FORMAT,
                "version": MANIFEST_VERSION,
                "max_layers": max_layers,
                "fill_rounds": fill_rounds,
                "recordings": {},
                "chunks": {},
            }

    def file(self, rel: str) -> Path:
        """A file of the stage named by its (checked) manifest, resolved inside the stage directory."""
        return inside(self.dir, self.dir / rel, str(self.dir / "manifest.json"))

    def chunk_files(self) -> dict[str, tuple[Path, str]]:
        """Manifest chunk name "cx_cz" → (its TRN2 file, its sha256), in name order."""
        return {name: (self.file(rec["file"]), rec["sha256"]) for name, rec in sorted(self.manifest["chunks"].items())}

    # -- contributions --------------------------------------------------------------------------

    def recordings(self) -> dict[str, dict]:
        return dict(self.manifest["recordings"])

    def input_hash(self, recording: str) -> str | None:
        return self.manifest["recordings"].get(recording, {}).get("input_hash")

    def put(self, recording: str, obs: Observations, input_hash: str, ts: int) -> None:
        """Store (or replace) one recording's observations, all stamped with the recording's time
        ``ts`` (unix seconds); takes effect at the next rebuild."""
        obs = Observations(obs.gx, obs.gz, obs.h, obs.n, obs.hits, np.full(len(obs), int(ts), np.int64))
        obs = merge(obs, max_layers=self.max_layers)
        path = self.dir / contribution_file(recording)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, gx=obs.gx, gz=obs.gz, h=obs.h, n=obs.n, hits=obs.hits, ts=obs.ts)
        cx, cz, _ = split_cell(obs.gx, obs.gz)
        chunks = sorted({(int(a), int(b)) for a, b in zip(cx, cz)})
        self.manifest["recordings"][recording] = {
            "input_hash": input_hash,
            "ts": int(ts),
            "observations": len(obs),
            "file": contribution_file(recording),
            "chunks": [list(c) for c in chunks],
        }
        write_json(self.dir / "manifest.json", self.manifest)

    def remove(self, recording: str) -> None:
        """Forget one recording's contribution; takes effect at the next rebuild."""
        rec = self.manifest["recordings"].pop(recording, None)
        if rec is not None:
            write_json(self.dir / "manifest.json", self.manifest)
            self.file(rec["file"]).unlink(missing_ok=True)

    def _load(self, rec: dict) -> Observations:
        with np.load(self.file(rec["file"]), allow_pickle=False) as z:
            return Observations(z["gx"], z["gz"], z["h"], z["n"], z["hits"], z["ts"])

    # -- chunks ---------------------------------------------------------------------------------

    def layers(self) -> tuple[Observations, np.ndarray]:
        """All layers of the stage (merged contributions without edge aliases, then hole fill) and the filled mask."""
        parts = [self._load(r) for _, r in sorted(self.manifest["recordings"].items())]
        merged = drop_aliases(merge(Observations.concat(parts), max_layers=self.max_layers))
        return fill_holes(merged, rounds=self.fill_rounds)

    def rebuild(self) -> RebuildReport:
        """Derive every chunk from the contributions; write only the files whose bytes change."""
        report = RebuildReport()
        layers, filled = self.layers()
        report.layers, report.filled = len(layers), int(filled.sum())
        chunks = _to_chunks(layers, filled, self.max_layers)
        contributors = self._contributors()
        old = {parse_chunk_name(k, str(self.dir / "manifest.json")) for k in self.manifest["chunks"]}
        new_manifest_chunks = {}
        for (cx, cz), chunk in sorted(chunks.items()):
            data = chunk.to_bytes()
            path = self.dir / "chunks" / chunk_filename(cx, cz)
            if path.exists() and path.read_bytes() == data:
                report.unchanged.append((cx, cz))
            else:
                write_bytes(path, data)
                report.written.append((cx, cz))
            new_manifest_chunks[f"{cx}_{cz}"] = {
                "file": chunk_file(cx, cz),
                "sha256": hashlib.sha256(data).hexdigest(),
                "recordings": sorted(contributors.get((cx, cz), [])),
            }
        for cx, cz in sorted(old - set(chunks)):
            (self.dir / "chunks" / chunk_filename(cx, cz)).unlink(missing_ok=True)
            report.removed.append((cx, cz))
        self.manifest["chunks"] = new_manifest_chunks
        write_json(self.dir / "manifest.json", self.manifest)
        return report

    def _contributors(self) -> dict[tuple[int, int], list[str]]:
        out: dict[tuple[int, int], list[str]] = {}
        for name, rec in self.manifest["recordings"].items():
            for cx, cz in rec["chunks"]:
                out.setdefault((cx, cz), []).append(name)
        return out


def _to_chunks(layers: Observations, filled: np.ndarray, max_layers: int) -> dict[tuple[int, int], Chunk]:
    """Pack layers (sorted by cell, then height) into TRN2 chunks; slots in height order."""
    out: dict[tuple[int, int], Chunk] = {}
    if not len(layers):
        return out
    cx, cz, idx = split_cell(layers.gx, layers.gz)
    cell = layers.gx * (1 << 32) + layers.gz
    start = np.r_[True, cell[1:] != cell[:-1]]
    first = np.maximum.accumulate(np.where(start, np.arange(len(cell)), 0))
    slot = np.arange(len(cell)) - first
    for key in sorted(set(zip(cx.tolist(), cz.tolist()))):
        sel = np.flatnonzero((cx == key[0]) & (cz == key[1]))
        ch = Chunk.empty(key[0], key[1], max_layers)
        rec = ch.cells
        i, s = idx[sel], slot[sel]
        rec["h"][i, s] = layers.h[sel]
        rec["n"][i, s] = layers.n[sel]
        rec["hits"][i, s] = np.minimum(layers.hits[sel], 65535)
        rec["flags"][i, s] = FLAG_VALID | np.where(filled[sel], FLAG_FILLED, 0)
        rec["ts"][i, s] = np.clip(layers.ts[sel], 0, 2**32 - 1)
        out[key] = ch
    return out
