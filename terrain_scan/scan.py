"""Scanning a corpus's stages: each ingested recording's depth and contacts → its stage's chunks.

A stage lives at ``<corpus>/terrain/stage_<id>/`` (see ``terrain_scan.store``). A recording is
scanned again only when its input changes — its ingest input hash, its depth.mkv, or the scan
settings (decoder, stride, voxel size) — so an incremental scan after new recordings arrive reads
only the new ones, derives only the chunks near a changed contribution, and rewrites only the chunks
whose bytes change. A full scan re-reads every recording of the stage and derives every chunk; both
give identical chunk files.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from pathlib import Path

from marionette.corpus import Corpus, paths
from marionette.corpus.lock import corpus_lock
from marionette.corpus.stages import UNPLACED, read_stage_file, write_placements
from marionette.fanout import Mapper, pool_mapper, threads_per_worker, worker_identity
from marionette.ingest.finalize import write_metadata
from marionette.io import file_sha256, printable, text_sha256
from marionette.recordings.errors import SampleError
from marionette.recordings.wildworld import DEPTH_FILE, SampleRef
from terrain_scan.accumulate import ScanResult, load_kernels, scan_recording, use_threads
from terrain_scan.depth import DepthDecoder
from terrain_scan.grouping import place
from terrain_scan.layers import Observations
from terrain_scan.options import ScanOptions
from terrain_scan.store import IMPORT_PREFIX, Stage, chunk_observations
from terrain_scan.trn2 import read_chunk, split_cell


def corpus_stages(corpus: Path) -> dict[str, list[dict]]:
    """Stage id → the ingested recordings on it (sample, source directory, ingest input hash)."""
    import pyarrow.parquet as pq

    seg = pq.read_table(paths.meta(corpus, paths.SEGMENTS)).to_pylist()
    stage_of = {r["sample"]: r["stage"] for r in seg}
    scene_of = {r["sample"]: r.get("scene") for r in seg}
    out: dict[str, list[dict]] = {}
    for r in pq.read_table(paths.meta(corpus, paths.SAMPLES)).to_pylist():
        if r["status"] == "ingested" and r["sample"] in stage_of:
            out.setdefault(stage_of[r["sample"]], []).append({**r, "scene": scene_of[r["sample"]]})
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
    scene: str | None = None  # the recording's scene (its layout says which joints are bodies to mask)

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
    contact_gap_m: float | None = None  # set where the scan failed the depth mapping's check (``reason`` says so)

    @property
    def unchanged(self) -> bool:
        return self.result is None and self.reason is None


def scan_job(job: ScanJob, layouts: dict, options: ScanOptions, threads: int | None = None) -> ScanOutcome:
    """Hash a recording's scan inputs (ingest input, depth.mkv, scan settings) and scan it unless the stage
    already holds that hash. Never raises: a failure is the outcome's ``reason``, naming the file. ``threads``:
    the most threads the scan's thread pools take in this worker (``accumulate.use_threads``)."""
    if threads is not None:
        use_threads(threads)
    out = ScanOutcome(job, worker=worker_identity())
    ref = _ref(job.source)
    depth = ref.path / DEPTH_FILE
    try:
        out.input_hash = text_sha256(job.ingest_hash, file_sha256(depth) if depth.exists() else "missing", options.key())[:32]
        if job.stored_hash == out.input_hash:
            return out
        decoder = DepthDecoder.from_json(options.decoder)
        layout = layouts[job.scene] if job.scene in layouts else next(iter(layouts.values()))
        out.result = scan_recording(ref, layout, decoder, **options.scan_kwargs())
    except Exception as exc:  # one recording's failure never stops the others
        out.reason = _reason(exc, ref)
        return out
    misfit = out.result.mapping_misfit(options.max_contact_gap_m)
    if misfit is not None:
        out.reason = (
            f"{ref.path}: {misfit}: the depth mapping does not fit this recording; run "
            "`marionette calibrate-depth <recordings> --corpus <corpus>`, then scan again"
        )
        out.result, out.contact_gap_m = None, out.result.contact_gap_m
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

    ``options`` default to those of the corpus's last scan (``ScanOptions.stored``), else the defaults; the
    options used are stored for the next.

    The recordings are scanned as independent jobs (``scan_job``) by ``mapper`` (``marionette.fanout``;
    default: ``pool_mapper(workers)``; the ``rescan-stage`` flow passes one that runs them on Dask) and
    committed to their stage in the stage's recording order, whatever order they finish in, so any number of
    workers writes the bytes a serial scan writes. The local pool's k workers take ``threads_per_worker(k)``
    threads each (the machine's cores split between them). A recording that cannot be scanned (its depth.mkv or any other input unreadable, or any other
    error) is listed under ``failed`` with the reason and the other recordings are scanned. ``progress``
    shows a bar over the recordings.
    """

    with corpus_lock(corpus, "terrain scan"):
        if mapper is None and workers > 1:
            load_kernels()  # once here, not once in each forked worker
        run = mapper or _sharing_cores(pool_mapper(workers), threads_per_worker(workers))
        if options is None:
            options = ScanOptions.of_corpus(corpus)
        report = _scan_stages(corpus, stage, incremental, options, log, progress, run)
        options.store(corpus)
        return report


def _sharing_cores(mapper: Mapper, threads: int) -> Mapper:
    """``mapper`` with each ``scan_job`` told how many threads its share of the machine's cores is."""
    return lambda fn, jobs, static: mapper(fn, jobs, {**static, "threads": threads})


def _scan_stages(corpus: Path, stage: str | None, incremental: bool, options: ScanOptions, log, progress: bool, mapper) -> dict:

    DepthDecoder.from_json(options.decoder)  # a bad decoder is one error here, not one per recording
    c = Corpus(corpus)
    placements, ready = _place_recordings(corpus, c, options, incremental, mapper, log, progress)
    stages = corpus_stages(corpus)
    if stage is not None:
        if stage not in stages:
            raise ValueError(f"{corpus}: no ingested recording on stage {stage!r}; stages: {sorted(stages)}")
        stages = {stage: stages[stage]}
    held = {st: Stage(paths.stage_dir(corpus, st), alias=options.alias()) for st in stages}
    if stage is None:  # a stage every recording left (moved by a placement): its scanned contributions go
        for d in sorted(paths.terrain_dir(corpus).glob("stage_*")):
            st = d.name[len("stage_") :]
            if st not in stages and paths.ID_PATTERN.fullmatch(st) and (d / "manifest.json").exists():
                held[st] = Stage(d, alias=options.alias())
                stages[st] = []
    jobs: list[ScanJob] = []
    for st, recs in stages.items():
        S = held[st]
        kept = {r["sample"] for r in recs}
        for gone in sorted(n for n in S.recordings() if n not in kept and not n.startswith(IMPORT_PREFIX)):  # left the corpus
            S.remove(gone)
        jobs += [
            ScanJob(st, r["sample"], r["source"], r["input_hash"], S.input_hash(r["sample"]) if incremental else None, r["scene"])
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
    # recordings the placement has just scanned are committed from its outcomes, not scanned twice
    ready = [o for o in ready if (o.job.stage, o.job.sample) in order]
    scanned = {(o.job.stage, o.job.sample) for o in ready}
    todo = [j for j in jobs if (j.stage, j.sample) not in scanned]
    try:
        for out in itertools.chain(ready, mapper(scan_job, todo, {"layouts": c.layouts, "options": options})):
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
            "placed": [p.line() for p in placements if p.stage == st],
        }
    return report


def _near(S: Stage):
    """A stage's observations in the chunks a recording's observations touch (its derived chunk files)."""

    def near(obs: Observations) -> Observations:
        cx, cz, _ = split_cell(obs.gx, obs.gz)
        parts = []
        for key in sorted({(int(a), int(b)) for a, b in zip(cx, cz, strict=True)}):
            rec = S.manifest["chunks"].get(f"{key[0]}_{key[1]}")
            if rec is not None:
                parts.append(chunk_observations(read_chunk(S.file(rec["file"]), at=key)))
        return Observations.concat(parts)

    return near


def _new_stage_name(used: set[str]) -> str:
    """``default`` for the first stage a corpus finds (the name a corpus of one stage has always had), then
    ``stage2``, ``stage3``, …"""
    if "default" not in used:
        return "default"
    return next(f"stage{k}" for k in range(2, len(used) + 3) if f"stage{k}" not in used)


def _place_recordings(
    corpus: Path, c, options: ScanOptions, incremental: bool, mapper, log, progress: bool = False
) -> tuple[list, list]:
    """Put every recording that no ``stages.json`` places onto a stage by terrain agreement (``grouping.place``),
    write the placement to ``meta/stages.json`` and the segments' stage column; apply a user's edit of that file.

    Returns the placements and the scan outcomes of the recordings scanned to place them (for the scan to commit).
    A recording whose scan fails stays unplaced (stage ``default``) and fails again, reported, in the scan."""

    given = dict(c.info.stages)  # the source tree's stages.json: the user's word
    placed, found = read_stage_file(corpus)
    now = {r["sample"]: (st, r) for st, recs in corpus_stages(corpus).items() for r in recs}
    key = options.key()
    # placed by the grouping (not since moved by the user) with other scan options: compared other terrain, so again
    stale = {s for s, f in found.items() if s in placed and placed[s] == f["stage"] and f["scan"] != key and s not in given}
    for s in stale:
        del placed[s]
    pending = sorted(s for s in now if s not in given and s not in placed)
    placements, ready = [], []
    if pending:
        held = {st: Stage(paths.stage_dir(corpus, st), alias=options.alias()) for st in {now[s][0] for s in pending}}
        jobs = [
            ScanJob(
                now[s][0],
                s,
                now[s][1]["source"],
                now[s][1]["input_hash"],
                held[now[s][0]].input_hash(s) if incremental else None,
                now[s][1]["scene"],
            )
            for s in pending
        ]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(jobs), desc="terrain scan (placing on stages)", unit="recording")
        outcomes = {}
        try:
            for o in mapper(scan_job, jobs, {"layouts": c.layouts, "options": options}):
                outcomes[o.job.sample] = o
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        seen = {}  # what each recording saw: its fresh scan, or its stored contribution when unchanged
        for s in pending:
            o = outcomes[s]
            if o.reason is None:
                seen[s] = o.result.observations if o.result is not None else held[o.job.stage].contribution(s)
        existing = sorted(set(given.values()) | set(placed.values()))
        near = {st: _near(Stage(paths.stage_dir(corpus, st))) for st in existing}
        placements = place(list(seen.items()), near, _new_stage_name)
        for p in placements:
            log(printable(f"terrain: placed {p.line()}"))
            o = outcomes[p.recording]
            placed[p.recording] = p.stage
            found[p.recording] = {"stage": p.stage, "scan": key}
            if o.result is not None:
                ready.append(replace(o, job=replace(o.job, stage=p.stage, stored_hash=None)))
            elif p.stage != o.job.stage:  # unchanged, moved: its stored contribution goes with it
                Stage(paths.stage_dir(corpus, p.stage), alias=options.alias()).put(
                    p.recording, seen[p.recording], o.input_hash, None
                )
        write_placements(
            corpus, {s: st for s, st in placed.items() if s in now or s in given}, {s: f for s, f in found.items() if s in now}
        )
    want = {s: given.get(s, placed.get(s, UNPLACED)) for s in now}
    if any(want[s] != now[s][0] for s in now):
        write_metadata(Path(corpus))
    return placements, ready


def _commit(S: Stage, out: ScanOutcome, report: dict, log) -> None:
    """One outcome into its stage (a scanned contribution stored) and its report."""
    st, sample = out.job.stage, out.job.sample
    if out.reason is not None:
        report["failed"][sample] = out.reason
        if out.contact_gap_m is not None:
            report.setdefault("mapping_failed", {})[sample] = _gap_json(out.contact_gap_m)
        log(printable(f"terrain {st}: {sample}: not scanned: {out.reason}"))
    elif out.unchanged:
        report["unchanged"].append(sample)
    else:
        res = out.result
        S.put(sample, res.observations, out.input_hash, res.recording_ts)
        gap = res.contact_gap_m
        report["scanned"].append(
            {
                "sample": sample,
                **res.counters(),
                "observations": len(res.observations),
                "contact_gap_m": _gap_json(gap),
                "worker": out.worker,
            }
        )
        log(
            printable(
                f"terrain {st}: scanned {sample} on {out.worker}: {res.frames_used} frames, {len(res.observations)} cell "
                f"observations, ground {'unseen where the feet stood' if gap != gap else f'{gap:+.3f} m from the feet'}"
            )
        )


def _gap_json(gap: float) -> float | None:
    """A contact gap as a report holds it: metres to the tenth of a millimetre, None where no cell held both."""
    return None if gap != gap else round(gap, 4)


def _reason(exc: Exception, ref: SampleRef) -> str:
    """A failure as one line that names the file: SampleError and OSError messages already do."""
    if isinstance(exc, SampleError):
        return str(exc)
    if isinstance(exc, OSError) and exc.filename:
        return f"{exc.filename}: {type(exc).__name__}: {exc.strerror or exc}"
    return f"{ref.path}: {type(exc).__name__}: {exc}"
