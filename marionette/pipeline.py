"""The build, in one place for the CLI and the flows: ingest, then the terrain scan, then the pose targets.

``refresh`` is what follows ingest (and what a re-scan runs): every stage's terrain scanned, then every
video chunk's pose target brought up to date. ``build`` is ingest followed by ``refresh``. Both hold the
corpus lock for the whole of their work (shared with the writers they call, so nobody else can write in
between) and return a report whose ``failures`` count every quarantined sample, every recording whose
scan failed and every chunk without a pose target, each listed with its reason.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from marionette.corpus.lock import corpus_lock
from marionette.io import printable


@dataclass
class RefreshReport:
    """What a refresh did: per stage the scan report (``terrain_scan.scan.scan_stages``), and the pose pass."""

    terrain: dict = field(default_factory=dict)
    pose: dict | None = None  # ``TargetsReport`` as a dict, None when the pass was not run

    def failures(self) -> dict[str, dict[str, str]]:
        """{"terrain": {recording: reason}, "pose": {chunk or shard: reason}}."""
        terrain = {f"{st}/{rec}": why for st, r in self.terrain.items() for rec, why in r.get("failed", {}).items()}
        return {"terrain": terrain, "pose": dict((self.pose or {}).get("failed", {}))}

    def mapping_failed(self) -> dict[str, float]:
        """{recording: how far its scanned ground stood from its feet, m} for each recording kept out of the terrain
        because the depth mapping does not fit it (``ScanOptions.max_contact_gap_m``)."""
        return {rec: gap for r in self.terrain.values() for rec, gap in r.get("mapping_failed", {}).items()}

    def lines(self) -> list[str]:
        """One summary line per stage and one for the pose pass, then one line per failure."""
        out = []
        for r in self.terrain.values():
            out += [f"terrain: placed {line}" for line in r.get("placed", [])]
        for st, r in self.terrain.items():
            out.append(
                f"terrain {st}: {len(r['scanned'])} recordings scanned, {len(r['unchanged'])} unchanged, {len(r['failed'])} failed; "
                f"chunks {len(r['chunks_written'])} written, {len(r['chunks_unchanged'])} unchanged, {len(r['chunks_removed'])} removed; "
                f"{r['layers']} layers ({r['filled']} filled) in {r['dir']}"
            )
        if self.pose is not None:
            p = self.pose
            out.append(
                f"pose targets: {len(p['rendered'])} of {p['chunks']} video chunks rendered ({p['frames_rendered']} frames), "
                f"{len(p['shards_rewritten'])} pose shards written, {len(p['failed'])} failed"
            )
        for kind, failed in self.failures().items():
            out += [f"{kind} failed: {name}: {why}" for name, why in sorted(failed.items())]
        if misfits := self.mapping_failed():
            out.append(
                f"depth mapping: it does not fit {len(misfits)} recording(s), kept out of the terrain (their "
                "ground is not where their characters stood): calibrate it (`marionette calibrate-depth <recordings> "
                "--corpus <corpus>`), then scan again (`marionette terrain scan <corpus>`)"
            )
        return [printable(line) for line in out]  # recording names from outside, control characters escaped


def refresh(
    corpus: Path,
    stage: str | None = None,
    incremental: bool = True,
    scan_options=None,
    terrain: bool = True,
    pose: bool = True,
    progress: bool = False,
    log=lambda *_: None,
    workers: int = 1,
    scan_mapper=None,
    pose_mapper=None,
) -> RefreshReport:
    """Scan the terrain of one stage (or all), then bring every pose target up to date, under the corpus lock.

    ``scan_options`` is a ``terrain_scan.options.ScanOptions`` (default: the synthetic game's depth decoder). The
    recordings are scanned on ``workers`` local processes, or by ``scan_mapper`` (``terrain_scan.scan.Mapper``:
    the flows' run them on Dask); the pose targets likewise, a shard a job (``pose_mapper``).
    """
    from marionette.bridge.targets import render_pose_targets
    from terrain_scan.scan import scan_stages

    report = RefreshReport()
    with corpus_lock(corpus, "terrain scan and pose targets", share=True):
        if terrain:
            report.terrain = scan_stages(
                corpus, stage, incremental, scan_options, log=log, progress=progress, workers=workers, mapper=scan_mapper
            )
        if pose:
            report.pose = asdict(render_pose_targets(corpus, progress=progress, workers=workers, mapper=pose_mapper))
    return report


def build(
    source: Path,
    corpus: Path,
    options,
    workers: int = 1,
    terrain: bool = True,
    pose: bool = True,
    progress: bool = True,
    scan_options=None,
    log=lambda *_: None,
) -> dict:
    """Ingest every sample under ``source`` (``marionette.ingest.build_corpus``), then ``refresh`` the corpus
    (``scan_options`` as there; both fan out over ``workers`` processes); returns the build report with "refresh" (a RefreshReport) and "failures" (counts
    by kind) added."""
    from marionette.ingest import build_corpus

    with corpus_lock(corpus, "ingest", share=True):
        report = build_corpus(source, corpus, options, workers=workers, progress=progress)
        done = RefreshReport()
        if report["info"]["total_ingested"] and (terrain or pose):
            done = refresh(
                corpus, terrain=terrain, pose=pose, progress=progress, scan_options=scan_options, log=log, workers=workers
            )
    report["refresh"] = done
    failed = done.failures()
    report["failures"] = {
        "quarantined": sum(r["status"] == "quarantined" for r in report["results"]),
        "terrain": len(failed["terrain"]),
        "depth_mapping": len(done.mapping_failed()),
        "pose": len(failed["pose"]),
    }
    return report
