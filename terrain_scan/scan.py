"""Scanning a corpus's stages: each ingested recording's depth and contacts → its stage's chunks.

A stage lives at ``<corpus>/terrain/stage_<id>/`` (see ``terrain_scan.store``). A recording is
scanned again only when its input changes — its ingest input hash, its depth.mkv, or the scan
settings (decoder, stride, voxel size) — so an incremental scan after new recordings arrive reads
only the new ones, derives only the chunks near a changed contribution, and rewrites only the chunks
whose bytes change. A full scan re-reads every recording of the stage and derives every chunk; both
give identical chunk files.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from marionette.corpus import paths
from marionette.fanout import Mapper, pool_mapper, worker_identity
from marionette.ingest.wildworld import SampleError, SampleRef
from marionette.io import file_sha256, text_sha256
from terrain_scan.accumulate import ScanResult, scan_recording
from terrain_scan.depth import DepthDecoder
from terrain_scan.store import IMPORT_PREFIX, Stage

SCAN_VERSION = (
    "4"  # 2: image-space steepness test, 20 m depth range; 3: edge leaks dropped; 4: observations keep the edges they hug
)


@dataclass(frozen=True)
class ScanOptions:
    """How depth becomes observations: the depth decoder, frame stride, voxel size and depth subsampling (every
    ``depth_subsample``-th pixel of every such row, ``accumulate.subsampled``)."""

    decoder: dict = field(default_factory=lambda: DepthDecoder.synthetic().to_json())
    frame_stride: int = 1
    voxel_m: float = 0.25
    depth_subsample: int = 1

    def __post_init__(self) -> None:
        if self.frame_stride < 1 or self.depth_subsample < 1 or not self.voxel_m > 0:
            raise ValueError(
                f"ScanOptions: frame_stride and depth_subsample must be at least 1 and voxel_m positive, not "
                f"{self.frame_stride}, {self.depth_subsample}, {self.voxel_m}"
            )

    def key(self) -> str:
        d = asdict(self)
        if d["depth_subsample"] == 1:  # the key of a scan made before the knob existed
            del d["depth_subsample"]
        return text_sha256(json.dumps(d, sort_keys=True), SCAN_VERSION)[:16]


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


@dataclass(frozen=True)
class ScanJob:
    """One recording of one stage to scan: all a worker needs (small and picklable; the work reads the files)."""

    stage: str
    sample: str
    source: str  # the recording's directory
    ingest_hash: str  # the ingest input hash of its files and options
    stored_hash: str | None  # the contribution's hash the stage holds now (None: none, or a full scan)

    @property
    def name(self) -> str:
        return f"scan-{self.stage}-{self.sample}"


@dataclass
class ScanOutcome:
    """A job's end: its contribution's hash, and the scan (None when unchanged or failed, ``reason`` saying why)."""

    job: ScanJob
    input_hash: str = ""
    result: ScanResult | None = None
    reason: str | None = None
    worker: str = ""

    @property
    def unchanged(self) -> bool:
        return self.result is None and self.reason is None


def scan_job(job: ScanJob, layout, options: ScanOptions) -> ScanOutcome:
    """Hash a recording's scan inputs (ingest input, depth.mkv, scan settings) and scan it unless the stage
    already holds that hash. Never raises: a failure is the outcome's ``reason``, naming the file."""
    out = ScanOutcome(job, worker=worker_identity())
    ref = _ref(job.source)
    depth = ref.path / "depth.mkv"
    try:
        out.input_hash = text_sha256(job.ingest_hash, file_sha256(depth) if depth.exists() else "missing", options.key())[:32]
        if job.stored_hash == out.input_hash:
            return out
        decoder = DepthDecoder.from_json(options.decoder)
        out.result = scan_recording(
            ref,
            layout,
            decoder,
            frame_stride=options.frame_stride,
            voxel_m=options.voxel_m,
            depth_subsample=options.depth_subsample,
        )
    except Exception as exc:  # one recording's failure never stops the others
        out.reason = _reason(exc, ref)
    return out


def scan_stages(
    corpus: Path,
    stage: str | None = None,
    incremental: bool = True,
    options: ScanOptions | None = None,
    log=print,
    progress: bool = False,
    workers: int = 1,
    mapper: Mapper | None = None,
) -> dict:
    """Scan one stage (or all) of a corpus; returns per stage what was scanned, what failed and which chunks changed.

    The recordings are scanned as independent jobs (``scan_job``) by ``mapper`` (``marionette.fanout``;
    default: ``pool_mapper(workers)``; the ``rescan-stage`` flow passes one that runs them on Dask) and
    committed to their stage in the stage's recording order, whatever order they finish in, so any number of
    workers writes the bytes a serial scan writes. A recording that cannot be scanned (its depth.mkv or any other input unreadable, or any other
    error) is listed under ``failed`` with the reason and the other recordings are scanned. ``progress``
    shows a bar over the recordings.
    """
    from marionette.corpus.lock import corpus_lock

    with corpus_lock(corpus, "terrain scan"):
        run = mapper or pool_mapper(workers)
        return _scan_stages(corpus, stage, incremental, options or ScanOptions(), log, progress, run)


def _scan_stages(corpus: Path, stage: str | None, incremental: bool, options: ScanOptions, log, progress: bool, mapper) -> dict:
    from marionette.corpus import Corpus

    DepthDecoder.from_json(options.decoder)  # a bad decoder is one error here, not one per recording
    c = Corpus(corpus)
    stages = corpus_stages(corpus)
    if stage is not None:
        if stage not in stages:
            raise ValueError(f"{corpus}: no ingested recording on stage {stage!r}; stages: {sorted(stages)}")
        stages = {stage: stages[stage]}
    held = {st: Stage(paths.stage_dir(corpus, st)) for st in stages}
    jobs: list[ScanJob] = []
    for st, recs in stages.items():
        S = held[st]
        kept = {r["sample"] for r in recs}
        for gone in sorted(n for n in S.recordings() if n not in kept and not n.startswith(IMPORT_PREFIX)):  # left the corpus
            S.remove(gone)
        jobs += [
            ScanJob(st, r["sample"], r["source"], r["input_hash"], S.input_hash(r["sample"]) if incremental else None)
            for r in recs
        ]
    reports = {st: {"scanned": [], "unchanged": [], "failed": {}} for st in stages}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="terrain scan", unit="recording")
        if log is print:
            log = bar.write  # keeps the bar on its own line
    order = {(j.stage, j.sample): k for k, j in enumerate(jobs)}
    waiting: dict[int, ScanOutcome] = {}
    done = 0
    try:
        for out in mapper(scan_job, jobs, {"layout": c.layout, "options": options}):
            if bar is not None:
                bar.update(1)
            waiting[order[(out.job.stage, out.job.sample)]] = out
            while done in waiting:  # commit in job order: the stage's manifest and files as a serial scan writes them
                _commit(held[jobs[done].stage], waiting.pop(done), reports[jobs[done].stage], log)
                done += 1
    finally:
        if bar is not None:
            bar.close()
    if done != len(jobs):
        missing = [j.sample for j in jobs[done:]]
        raise RuntimeError(f"{corpus}: the scan's workers returned no outcome for {missing}")
    report: dict = {}
    for st in stages:
        rb = held[st].rebuild("incremental" if incremental else "full")
        report[st] = {
            "dir": str(held[st].dir),
            **reports[st],
            "chunks_written": [list(c) for c in rb.written],  # [cx, cz] pairs (JSON-shaped)
            "chunks_unchanged": [list(c) for c in rb.unchanged],
            "chunks_removed": [list(c) for c in rb.removed],
            "chunks_derived": [list(c) for c in rb.derived],
            "layers": rb.layers,
            "filled": rb.filled,
        }
    return report


def _commit(S: Stage, out: ScanOutcome, report: dict, log) -> None:
    """One outcome into its stage (a scanned contribution stored) and its report."""
    st, sample = out.job.stage, out.job.sample
    if out.reason is not None:
        report["failed"][sample] = out.reason
        log(f"terrain {st}: {sample}: not scanned: {out.reason}")
    elif out.unchanged:
        report["unchanged"].append(sample)
    else:
        res = out.result
        S.put(sample, res.observations, out.input_hash, res.recording_ts)
        report["scanned"].append(
            {"sample": sample, **res.counters(), "observations": len(res.observations), "worker": out.worker}
        )
        log(
            f"terrain {st}: scanned {sample} on {out.worker}: {res.frames_used} frames, {len(res.observations)} cell observations"
        )


def _reason(exc: Exception, ref: SampleRef) -> str:
    """A failure as one line that names the file: SampleError and OSError messages already do."""
    if isinstance(exc, SampleError):
        return str(exc)
    if isinstance(exc, OSError) and exc.filename:
        return f"{exc.filename}: {type(exc).__name__}: {exc.strerror or exc}"
    return f"{ref.path}: {type(exc).__name__}: {exc}"
