"""A stage on disk: per-recording contributions, the derived TRN2 chunks, and a manifest.

```
<stage_dir>/manifest.json                 recordings (input hash, contribution sha256, time, observation count,
                                          chunks touched), chunks (file, sha256, contributing recordings, layer
                                          and filled counts) and what the last rebuild derived from ("rebuilt")
<stage_dir>/contributions/<key>.npz       one recording's merged observations (gx, gz, h, n, hits, ts)
<stage_dir>/chunks/chunk_<cx>_<cz>.trn2   the layered height field
```

A chunk is a function of the contributions' observations within its own cells and a halo of
``halo_cells(fill_rounds)`` cells around them (``derive``: merge, drop edge aliases, hole fill), so
chunks are derived one at a time from that neighbourhood alone, and a rebuild re-derives only the
chunks near a recording that was added, re-scanned with another result, or removed since the last
one. Any order of adding recordings, re-scanning one, an incremental or a full rebuild, and the
whole-stage derivation (``Stage.layers(whole=True)``) therefore give byte-identical chunk files. A rebuild writes
only the chunk files whose bytes change: untouched chunks keep their bytes and mtime.
"""

from __future__ import annotations

import hashlib
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from marionette.corpus.paths import CorpusPathError, inside, stage_dir
from marionette.io import atomic_path, read_json, regular_file, write_bytes, write_json
from terrain_scan.fill import fill_holes
from terrain_scan.layers import ALIAS_DOMINANCE, ALIAS_FRACTION, ALIAS_SUPPORT, MAX_LAYERS, Observations, drop_aliases, merge
from terrain_scan.trn2 import CELLS, FLAG_FILLED, FLAG_VALID, Chunk, chunk_filename, find_chunks, read_chunk, split_cell

MANIFEST_FORMAT = "marionette-terrain-stage"
MANIFEST_VERSION = 1
# bump when merge, the alias rule or the hole fill change: the next rebuild derives every chunk (2: ALIAS_FRACTION 0.25;
# 3: the alias rule by position, layers.drop_aliases)
DERIVE_VERSION = 3
FILL_ROUNDS = 2
DEFAULT_ALIAS = (ALIAS_FRACTION, ALIAS_DOMINANCE, ALIAS_SUPPORT)
CHUNK_NAME = re.compile(r"(-?\d{1,9})_(-?\d{1,9})")
REBUILD_MODES = ("incremental", "full", "whole")
# a contribution imported from chunk files (``import_chunks``) rather than scanned from a recording: a recording id
# cannot hold ':', so a scan never mistakes one for a recording that left the corpus
IMPORT_PREFIX = "import:"

ChunkKey = tuple[int, int]


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


def _is_chunk_list(v: object) -> bool:
    """A JSON list of [cx, cz] integer pairs."""
    return isinstance(v, list) and all(
        isinstance(c, list) and len(c) == 2 and all(isinstance(x, int) and not isinstance(x, bool) for x in c) for c in v
    )


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
            if not _is_chunk_list([c]):
                raise ValueError(f"{path}: recordings.{name}.chunks[{i}] is not [cx, cz]")
    for name, rec in chunks.items():
        cx, cz = parse_chunk_name(name, str(path))
        if not isinstance(rec, dict) or rec.get("file") != chunk_file(cx, cz):
            got = rec.get("file") if isinstance(rec, dict) else rec
            raise CorpusPathError(f"{path}: chunks.{name}.file is {got!r}, not {chunk_file(cx, cz)!r}")
    return manifest


def halo_cells(fill_rounds: int) -> int:
    """How far (cells, in x and z) a cell's derived layers reach: the edge-alias rule reads the merged layers
    of the 4 edge neighbours (1), and each hole-fill round the 8 neighbours as the round before left them
    (1 a round). Merge is per cell."""
    return 1 + max(fill_rounds, 0)


def derive(
    obs: Observations, max_layers: int, fill_rounds: int, alias: tuple[float, float, int] = DEFAULT_ALIAS
) -> tuple[Observations, np.ndarray]:
    """Layers of observations (merged, edge aliases dropped — ``alias`` the rule's (fraction, dominance,
    support) — then hole fill) and the filled mask, sorted by (gx, gz, h). A cell's result depends only on the
    observations within ``halo_cells(fill_rounds)`` of it."""
    fraction, dominance, support = alias
    layers = drop_aliases(merge(obs, max_layers=max_layers), fraction=fraction, dominance=dominance, support=support)
    return fill_holes(layers, rounds=fill_rounds)


def contribution_sha256(obs: Observations) -> str:
    """sha256 of a contribution's columns (dtype, shape and bytes): equal observations, equal hash."""
    h = hashlib.sha256()
    for name in Observations.FIELDS:
        a = np.ascontiguousarray(getattr(obs, name))
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


@dataclass
class RebuildReport:
    """What a rebuild did: the chunks it derived (all, when ``full``), and the stage's chunk files it wrote,
    left untouched (derived to the same bytes, or not derived) or removed; the stage's layer and filled counts."""

    written: list[tuple[int, int]] = field(default_factory=list)
    unchanged: list[tuple[int, int]] = field(default_factory=list)
    removed: list[tuple[int, int]] = field(default_factory=list)
    derived: list[tuple[int, int]] = field(default_factory=list)
    full: bool = True
    read: int = 0  # contributions read
    layers: int = 0
    filled: int = 0


class Stage:
    """One game stage's terrain: contributions in, chunks out."""

    def __init__(
        self,
        stage_dir: Path,
        max_layers: int = MAX_LAYERS,
        fill_rounds: int = FILL_ROUNDS,
        alias: tuple[float, float, int] = DEFAULT_ALIAS,
    ):
        self.dir = Path(stage_dir)
        self.max_layers = max_layers
        self.fill_rounds = fill_rounds
        self.alias = tuple(alias)
        path = self.dir / "manifest.json"
        if path.exists():
            try:
                raw = read_json(path)
            except ValueError as exc:
                raise ValueError(f"not a terrain stage manifest: {exc}") from None
            self.manifest = check_manifest(raw, path)
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

    @property
    def halo(self) -> int:
        """Cells around a chunk whose observations its derivation reads."""
        return halo_cells(self.fill_rounds)

    def around(self, key: ChunkKey) -> list[ChunkKey]:
        """The chunk and the chunks its halo reaches into, in (cx, cz) order."""
        r = -(-self.halo // CELLS)
        return [(key[0] + dx, key[1] + dz) for dx in range(-r, r + 1) for dz in range(-r, r + 1)]

    # -- contributions --------------------------------------------------------------------------

    def recordings(self) -> dict[str, dict]:
        return dict(self.manifest["recordings"])

    def input_hash(self, recording: str) -> str | None:
        return self.manifest["recordings"].get(recording, {}).get("input_hash")

    def put(self, recording: str, obs: Observations, input_hash: str, ts: int | None) -> None:
        """Store (or replace) one recording's observations, all stamped with the recording's time
        ``ts`` (unix seconds; None: each keeps its own, the newest is the recording's); takes effect at the next
        rebuild."""
        if ts is None:
            ts = int(obs.ts.max()) if len(obs) else 0
        else:
            obs = Observations(obs.gx, obs.gz, obs.h, obs.n, obs.hits, np.full(len(obs), int(ts), np.int64), obs.hugs)
        obs = merge(obs, max_layers=self.max_layers)
        path = self.dir / contribution_file(recording)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, gx=obs.gx, gz=obs.gz, h=obs.h, n=obs.n, hits=obs.hits, ts=obs.ts, hugs=obs.hugs)
        cx, cz, _ = split_cell(obs.gx, obs.gz)
        chunks = sorted({(int(a), int(b)) for a, b in zip(cx, cz)})
        self.manifest["recordings"][recording] = {
            "input_hash": input_hash,
            "sha256": contribution_sha256(obs),
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

    def contribution(self, recording: str) -> Observations:
        """One recording's stored observations."""
        return self._load(self.manifest["recordings"][recording])

    def _load(self, rec: dict) -> Observations:
        path = self.file(rec["file"])
        regular_file(path)
        with np.load(path, allow_pickle=False) as z:
            hugs = z["hugs"] if "hugs" in z.files else None  # stored before scans measured it: never an alias
            return Observations(z["gx"], z["gz"], z["h"], z["n"], z["hits"], z["ts"], hugs)

    def _contributors(self) -> dict[ChunkKey, list[str]]:
        """Chunk → the recordings whose contribution holds cells in it, in name order."""
        out: dict[ChunkKey, list[str]] = {}
        for name, rec in sorted(self.manifest["recordings"].items()):
            for cx, cz in rec["chunks"]:
                out.setdefault((cx, cz), []).append(name)
        return out

    # -- chunks ---------------------------------------------------------------------------------

    def covered(self) -> list[ChunkKey]:
        """Every chunk that can hold a layer: those the contributions touch and those their halo reaches."""
        return sorted({c for k in self._contributors() for c in self.around(k)})

    def chunk_layers(
        self, keys: list[ChunkKey], pieces: ChunkPieces | None = None
    ) -> Iterator[tuple[ChunkKey, Observations, np.ndarray]]:
        """Each chunk of ``keys`` in turn: its layers (``derive`` over the observations within its halo,
        then its own cells kept; empty when it has none) and their filled mask. The contributions are read
        through ``pieces`` (default: a new ``ChunkPieces`` for ``keys``), so what is held is a neighbourhood,
        not the stage."""
        pieces = ChunkPieces(self, keys) if pieces is None else pieces
        for key in keys:
            layers, filled = derive(pieces.window(key), self.max_layers, self.fill_rounds, self.alias)
            cx, cz, _ = split_cell(layers.gx, layers.gz)
            own = np.flatnonzero((cx == key[0]) & (cz == key[1]))
            yield key, layers.take(own), filled[own]

    def layers(self, whole: bool = False) -> tuple[Observations, np.ndarray]:
        """All layers of the stage and their filled mask, sorted by (gx, gz, h): chunk by chunk, or with
        ``whole`` derived from all contributions at once (the definition, kept as the reference; its dense
        grids span the stage's bounding box)."""
        if whole:
            parts = [self._load(r) for _, r in sorted(self.manifest["recordings"].items())]
            return derive(Observations.concat(parts), self.max_layers, self.fill_rounds, self.alias)
        chunks = [(layers, filled) for _, layers, filled in self.chunk_layers(self.covered())]
        if not chunks:
            return Observations.empty(), np.zeros(0, bool)
        layers, filled = Observations.concat([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])
        order = np.lexsort((layers.h, layers.gz, layers.gx))  # stable: a cell's rows keep their order
        return layers.take(order), filled[order]

    def rebuild(self, mode: str = "incremental") -> RebuildReport:
        """Derive the chunks from the contributions; write only the files whose bytes change.

        ``incremental``: only the chunks whose own or halo neighbourhood's contributions changed since the
        last rebuild (and any chunk whose file is missing); every chunk when the manifest does not record
        the last rebuild, or records other settings. ``full``: every chunk, one neighbourhood at a time.
        ``whole``: every chunk from the whole stage's layers at once (``layers(whole=True)``): the
        definition the other two equal byte for byte, kept as their reference.
        """
        if mode not in REBUILD_MODES:
            raise ValueError(f"rebuild mode {mode!r} is not one of {REBUILD_MODES}")
        for rec in self.manifest["recordings"].values():
            if "sha256" not in rec:  # stored before contributions were hashed: hashed once, here
                rec["sha256"] = contribution_sha256(self._load(rec))
        stale = self._stale() if mode == "incremental" else None
        report = RebuildReport(full=stale is None)
        pieces = None
        if mode == "whole":
            derived = _split_by_chunk(*self.layers(whole=True))
        else:
            keys = sorted(stale) if stale is not None else self.covered()
            pieces = ChunkPieces(self, keys)
            derived = self.chunk_layers(keys, pieces)
        entries = dict(self.manifest["chunks"]) if stale is not None else {}
        where = str(self.dir / "manifest.json")
        old = {parse_chunk_name(k, where) for k in self.manifest["chunks"]}
        contributors = self._contributors()
        for (cx, cz), layers, filled in derived:
            report.derived.append((cx, cz))
            entries.pop(f"{cx}_{cz}", None)
            if not len(layers):
                continue
            data = _to_chunks(layers, filled, self.max_layers)[(cx, cz)].to_bytes()
            path = self.dir / "chunks" / chunk_filename(cx, cz)
            if not (path.exists() and path.read_bytes() == data):
                write_bytes(path, data)
                report.written.append((cx, cz))
            entries[f"{cx}_{cz}"] = {
                "file": chunk_file(cx, cz),
                "sha256": hashlib.sha256(data).hexdigest(),
                "recordings": contributors.get((cx, cz), []),
                "layers": len(layers),
                "filled": int(filled.sum()),
            }
        kept = {parse_chunk_name(k, where) for k in entries}
        for cx, cz in sorted(old - kept):
            (self.dir / "chunks" / chunk_filename(cx, cz)).unlink(missing_ok=True)
            report.removed.append((cx, cz))
        report.unchanged = sorted(kept - set(report.written))
        report.read = len(pieces.read) if pieces is not None else len(self.manifest["recordings"])
        report.layers = sum(e.get("layers", 0) for e in entries.values())
        report.filled = sum(e.get("filled", 0) for e in entries.values())
        self.manifest["chunks"] = entries
        self.manifest["rebuilt"] = self._inputs()
        write_json(self.dir / "manifest.json", self.manifest)
        return report

    def _inputs(self) -> dict:
        """What chunks are derived from now: the derivation's version and settings, and per recording its
        contribution's sha256 and chunks (kept after the recording is removed, to find the chunks it touched)."""
        return {
            "derive_version": DERIVE_VERSION,
            "max_layers": self.max_layers,
            "fill_rounds": self.fill_rounds,
            "alias": list(self.alias),
            "recordings": {
                name: {"sha256": rec["sha256"], "chunks": rec["chunks"]} for name, rec in self.manifest["recordings"].items()
            },
        }

    def _stale(self) -> set[ChunkKey] | None:
        """The chunks whose own or halo neighbourhood's contributions differ from the last rebuild's, and those
        whose file is missing; None when the manifest cannot tell (no, or a malformed, record of the last
        rebuild, or one made by another derivation or other settings)."""
        last, now = self.manifest.get("rebuilt"), self._inputs()
        if not isinstance(last, dict) or any(
            last.get(k) != now[k] for k in ("derive_version", "max_layers", "fill_rounds", "alias")
        ):
            return None
        before = last.get("recordings")
        if not isinstance(before, dict) or not all(
            isinstance(r, dict) and _is_chunk_list(r.get("chunks")) for r in before.values()
        ):
            return None
        touched: set[ChunkKey] = set()
        for name in before.keys() | now["recordings"].keys():
            a, b = before.get(name), now["recordings"].get(name)
            if a is None or b is None or a.get("sha256") != b["sha256"]:
                touched |= {(cx, cz) for r in (a, b) if r is not None for cx, cz in r["chunks"]}
        stale = {c for k in touched for c in self.around(k)}
        for name, rec in self.manifest["chunks"].items():
            if not self.file(rec["file"]).exists():
                stale.add(parse_chunk_name(name, str(self.dir / "manifest.json")))
        return stale


class ChunkPieces:
    """A stage's contributions split by chunk, for deriving ``keys`` in their order: a recording is read the
    first time a chunk near it is derived, and a chunk's pieces are dropped once every chunk of ``keys`` that
    reads them is done. What is held is the neighbourhoods being derived plus the not yet needed chunks of the
    recordings read so far, never the whole stage's layers."""

    def __init__(self, stage: Stage, keys: list[ChunkKey]):
        self.stage = stage
        self.by_chunk = stage._contributors()
        self.waiting = Counter(c for k in keys for c in stage.around(k) if c in self.by_chunk)
        self.pieces: dict[ChunkKey, list[Observations]] = {}
        self.read: set[str] = set()  # the recordings whose contribution was read

    def window(self, key: ChunkKey) -> Observations:
        """The observations of chunk ``key`` and its halo, from every recording."""
        near = self.stage.around(key)
        for c in near:
            for name in self.by_chunk.get(c, ()):
                if name not in self.read:
                    self._read(name)
        h = self.stage.halo
        x0, z0, w = key[0] * CELLS - h, key[1] * CELLS - h, CELLS + 2 * h
        parts = []
        for c in near:
            for p in self.pieces.get(c, ()):
                if c != key:  # a neighbour: only its cells within the halo
                    p = p.take(np.flatnonzero((p.gx >= x0) & (p.gx < x0 + w) & (p.gz >= z0) & (p.gz < z0 + w)))
                parts.append(p)
            if c in self.waiting:
                self.waiting[c] -= 1
                if not self.waiting[c]:
                    del self.waiting[c]
                    self.pieces.pop(c, None)
        return Observations.concat(parts)

    def _read(self, name: str) -> None:
        """Read one recording's contribution and keep its pieces of the chunks still to be read."""
        rec = self.stage.manifest["recordings"][name]
        obs = self.stage._load(rec)
        self.read.add(name)
        if not len(obs):
            return
        cx, cz, _ = split_cell(obs.gx, obs.gz)
        key = (cx - cx.min()) * (int(cz.max() - cz.min()) + 1) + (cz - cz.min())  # one int per chunk
        order = np.argsort(key, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(key[order]) != 0])
        listed = {tuple(c) for c in rec["chunks"]}
        for start, end in zip(starts.tolist(), np.r_[starts[1:], len(key)].tolist()):
            c = (int(cx[order[start]]), int(cz[order[start]]))
            if c not in listed:
                raise ValueError(
                    f"{self.stage.file(rec['file'])}: holds cells of chunk {c}, which its manifest entry does not list"
                )
            if self.waiting.get(c):
                self.pieces.setdefault(c, []).append(obs.take(order[start:end]))


def chunk_observations(chunk: Chunk, filled: bool = False) -> Observations:
    """A chunk's layers as observations (gx, gz, h, n, hits, ts), sorted by cell and height: its valid slots with a
    finite height, those the hole fill made only with ``filled`` (an import leaves them to its rebuild)."""
    flags = chunk.cells["flags"]
    keep = ((flags & FLAG_VALID) != 0) & np.isfinite(chunk.cells["h"])
    if not filled:
        keep &= (flags & FLAG_FILLED) == 0
    cell, slot = np.nonzero(keep)
    rec = chunk.cells[cell, slot]
    obs = Observations(
        (chunk.cx * CELLS + cell % CELLS).astype(np.int64),
        (chunk.cz * CELLS + cell // CELLS).astype(np.int64),
        rec["h"].astype(np.float64),
        rec["n"].astype(np.float64),
        np.maximum(rec["hits"].astype(np.int64), 1),
        rec["ts"].astype(np.int64),
    )
    return obs.take(np.lexsort((obs.h, obs.gz, obs.gx)))


@dataclass
class ImportReport:
    """What ``import_chunks`` did: the contribution's name, the chunk files read, the layers taken (and the
    hole-filled ones left to the rebuild), whether the same files were imported before, and the rebuild."""

    name: str
    chunks: int
    layers: int
    skipped_filled: int
    unchanged: bool
    rebuild: RebuildReport


def import_chunks(stage: Stage, src: Path, name: str | None = None, mode: str = "incremental") -> ImportReport:
    """Make a directory of TRN2 chunks (ours or the upstream release's naming: ``trn2.find_chunks``) one
    contribution of ``stage``, called ``import:<name>`` (default: the directory's name), then rebuild the stage.
    The chunks' measured layers are taken with their hit counts and times; hole-filled ones are left out (the
    rebuild fills holes from every contribution). Importing the same files again changes nothing."""

    src = Path(src)
    files = find_chunks(src)
    label = IMPORT_PREFIX + (name if name is not None else src.resolve().name)
    digest = hashlib.sha256()
    parts, filled = [], 0
    for (cx, cz), path in sorted(files.items()):
        chunk = read_chunk(path, at=(cx, cz))
        digest.update(f"{cx}_{cz}:".encode())
        digest.update(chunk.to_bytes())
        flags = chunk.cells["flags"]
        filled += int((((flags & FLAG_VALID) != 0) & ((flags & FLAG_FILLED) != 0)).sum())
        parts.append(chunk_observations(chunk))
    obs = Observations.concat(parts) if parts else Observations.empty()
    input_hash = digest.hexdigest()
    unchanged = stage.input_hash(label) == input_hash
    if not unchanged:
        stage.put(label, obs, input_hash, ts=None)
    return ImportReport(label, len(files), len(obs), filled, unchanged, stage.rebuild(mode))


def _split_by_chunk(layers: Observations, filled: np.ndarray) -> Iterator[tuple[ChunkKey, Observations, np.ndarray]]:
    """Layers (sorted by cell, then height) chunk by chunk, in (cx, cz) order."""
    cx, cz, _ = split_cell(layers.gx, layers.gz)
    for key in sorted(set(zip(cx.tolist(), cz.tolist()))):
        own = np.flatnonzero((cx == key[0]) & (cz == key[1]))
        yield key, layers.take(own), filled[own]


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


def stage_terrain(corpus: Path | str, stage: str) -> Stage | None:
    """A corpus's scanned terrain of ``stage`` (its ``Stage``), or None when it was never scanned."""
    d = stage_dir(Path(corpus), stage)
    if not (d / "manifest.json").is_file():
        return None
    scanned = Stage(d)
    return scanned if scanned.manifest["chunks"] else None


def segment_terrain(corpus, segment: str) -> Stage | None:
    """The one answer to "this segment's terrain" in a ``marionette.corpus.Corpus``: its stage's ``Stage``, or None
    when that stage is unscanned."""
    return stage_terrain(corpus.path, corpus.stage_of(segment))
