"""Scanning a corpus's stages: each ingested recording's depth and contacts → its stage's chunks.

A stage lives at ``<corpus>/terrain/stage_<id>/`` (see ``terrain_scan.store``). A recording is
scanned again only when its input changes — its ingest input hash, its depth.mkv, or the scan
settings (decoder, stride, voxel size) — so an incremental scan after new recordings arrive reads
only the new ones, and rewrites only the chunks whose bytes change. A full scan re-reads every
recording of the stage; both give identical chunk files.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from marionette.corpus import paths
from marionette.ingest.wildworld import SampleError, SampleRef
from marionette.io import file_sha256, text_sha256
from terrain_scan.accumulate import scan_recording
from terrain_scan.depth import DepthDecoder
from terrain_scan.store import Stage

SCAN_VERSION = "3"  # 2: image-space steepness test, 20 m depth range; 3: edge leaks dropped


@dataclass(frozen=True)
class ScanOptions:
    """How depth becomes observations: the depth decoder, frame stride and voxel size."""

    decoder: dict = field(default_factory=lambda: DepthDecoder.synthetic().to_json())
    frame_stride: int = 1
    voxel_m: float = 0.25

    def key(self) -> str:
        return text_sha256(json.dumps(asdict(self), sort_keys=True), SCAN_VERSION)[:16]


def corpus_stages(corpus: Path) -> dict[str, list[dict]]:
    """Stage id → the ingested recordings on it (sample, source directory, ingest input hash)."""
    import pyarrow.parquet as pq

    meta = Path(corpus) / "meta"
    seg = pq.read_table(meta / "segments.parquet").to_pylist()
    stage_of = {r["sample"]: r["stage"] for r in seg}
    out: dict[str, list[dict]] = {}
    for r in pq.read_table(meta / "samples.parquet").to_pylist():
        if r["status"] == "ingested" and r["sample"] in stage_of:
            out.setdefault(stage_of[r["sample"]], []).append(r)
    return {k: sorted(v, key=lambda r: r["sample"]) for k, v in sorted(out.items())}


def _ref(source: str) -> SampleRef:
    p = Path(source)
    return SampleRef(p.parent.parent, p.parent.name, p.name)


def scan_stages(
    corpus: Path,
    stage: str | None = None,
    incremental: bool = True,
    options: ScanOptions | None = None,
    log=print,
    progress: bool = False,
) -> dict:
    """Scan one stage (or all) of a corpus; returns per stage what was scanned, what failed and which chunks changed.

    A recording that cannot be scanned (its depth.mkv or any other input unreadable, or any other
    error) is listed under ``failed`` with the reason and the other recordings are scanned.
    ``progress`` shows a bar over the recordings.
    """
    from marionette.corpus.lock import corpus_lock

    with corpus_lock(corpus, "terrain scan"):
        return _scan_stages(corpus, stage, incremental, options or ScanOptions(), log, progress)


def _scan_stages(corpus: Path, stage: str | None, incremental: bool, options: ScanOptions, log, progress: bool) -> dict:
    from marionette.corpus import Corpus

    decoder = DepthDecoder.from_json(options.decoder)
    c = Corpus(corpus)
    stages = corpus_stages(corpus)
    if stage is not None:
        if stage not in stages:
            raise ValueError(f"{corpus}: no ingested recording on stage {stage!r}; stages: {sorted(stages)}")
        stages = {stage: stages[stage]}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(len(v) for v in stages.values()), desc="terrain scan", unit="recording")
        if log is print:
            log = bar.write  # keeps the bar on its own line
    report: dict = {}
    try:
        for st, recs in stages.items():
            report[st] = _scan_stage(corpus, c.layout, st, recs, incremental, options, decoder, log, bar)
    finally:
        if bar is not None:
            bar.close()
    return report


def _scan_stage(
    corpus: Path, layout, st: str, recs: list[dict], incremental: bool, options: ScanOptions, decoder: DepthDecoder, log, bar
) -> dict:
    """Scan the recordings ``recs`` of stage ``st`` and rebuild its chunks."""
    S = Stage(paths.stage_dir(corpus, st))
    names = {r["sample"] for r in recs}
    for gone in sorted(set(S.recordings()) - names):  # no longer in the corpus
        S.remove(gone)
    scanned, skipped, failed = [], [], {}
    for r in recs:
        if bar is not None:
            bar.update(1)
        ref = _ref(r["source"])
        depth = ref.path / "depth.mkv"
        try:
            h = text_sha256(r["input_hash"], file_sha256(depth) if depth.exists() else "missing", options.key())[:32]
            if incremental and S.input_hash(r["sample"]) == h:
                skipped.append(r["sample"])
                continue
            res = scan_recording(ref, layout, decoder, frame_stride=options.frame_stride, voxel_m=options.voxel_m)
        except Exception as exc:  # one recording's failure never stops the others
            failed[r["sample"]] = _reason(exc, ref)
            log(f"terrain {st}: {r['sample']}: not scanned: {failed[r['sample']]}")
            continue
        S.put(r["sample"], res.observations, h, res.recording_ts)
        scanned.append({"sample": r["sample"], **res.counters(), "observations": len(res.observations)})
        log(f"terrain {st}: scanned {r['sample']}: {res.frames_used} frames, {len(res.observations)} cell observations")
    rb = S.rebuild()
    return {
        "dir": str(S.dir),
        "scanned": scanned,
        "unchanged": skipped,
        "failed": failed,
        "chunks_written": [list(c) for c in rb.written],  # [cx, cz] pairs (JSON-shaped)
        "chunks_unchanged": [list(c) for c in rb.unchanged],
        "chunks_removed": [list(c) for c in rb.removed],
        "layers": rb.layers,
        "filled": rb.filled,
    }


def _reason(exc: Exception, ref: SampleRef) -> str:
    """A failure as one line that names the file: SampleError and OSError messages already do."""
    if isinstance(exc, SampleError):
        return str(exc)
    if isinstance(exc, OSError) and exc.filename:
        return f"{exc.filename}: {type(exc).__name__}: {exc.strerror or exc}"
    return f"{ref.path}: {type(exc).__name__}: {exc}"
