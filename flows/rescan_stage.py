"""The ``rescan-stage`` flow: scan new or changed recordings of a stage, then bring the pose targets up to date.

    refresh (``marionette.pipeline.refresh``, the call ``marionette terrain scan`` makes)
        scan-recordings (subflow: one ``scan`` task per recording, on Dask) → commit in order, rebuild → pose targets
    → report artifact

The scan fans out like ingest: a local Dask cluster of ``n_workers`` processes, or the scheduler at
``dask_address``. Each task hashes its recording's inputs and scans it unless the stage already holds that
hash; the flow's process commits the contributions in recording order and rebuilds the chunks, so the
stage's files are the bytes of a serial scan.

Incremental by default: recordings whose inputs and scan settings are unchanged are not read, and
only chunk files whose bytes change are rewritten. The pose-control targets of the video chunks
(``marionette.bridge.targets``) are then brought up to date: only chunks whose cameras see a changed
terrain chunk are rendered again (``render_targets=False`` skips this). The corpus lock is held
throughout; a recording or chunk that fails is listed in the report, and the rest goes on.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task, unmapped
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from flows.build_corpus import dask_runner, worker_identity
from marionette import pipeline
from terrain_scan.depth import DepthDecoder
from terrain_scan.scan import Mapper, ScanJob, ScanOptions, ScanOutcome, scan_job


@task(cache_policy=NO_CACHE, task_run_name="scan-{job.stage}-{job.sample}")
def scan_one(job: ScanJob, layout, options: ScanOptions) -> ScanOutcome:
    """One recording's scan (``terrain_scan.scan.scan_job``); a failure is in the outcome, not raised."""
    out = scan_job(job, layout, options)
    out.worker = worker_identity()
    return out


@flow(name="scan-recordings")
def scan_recordings(jobs: list[ScanJob], layout, options: ScanOptions) -> list[ScanOutcome]:
    """Fan ``scan_one`` out over this flow's task runner; one outcome per job."""
    futures = scan_one.map(jobs, layout=unmapped(layout), options=unmapped(options))
    return [f.result() for f in futures]


def dask_mapper(dask_address: str | None, n_workers: int) -> Mapper:
    """A ``terrain_scan.scan.Mapper`` that runs the jobs in the ``scan-recordings`` subflow on Dask."""

    def run(jobs: list[ScanJob], layout, options: ScanOptions) -> list[ScanOutcome]:
        if not jobs:
            return []
        return scan_recordings.with_options(task_runner=dask_runner(dask_address, n_workers))(jobs, layout, options)

    return run


def report_markdown(corpus: str, report: dict) -> str:
    lines = [
        f"# rescan-stage `{corpus}`",
        "",
        "| stage | scanned | unchanged | failed | chunks written | unchanged | removed | layers |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for st, r in report.items():
        if st == "_pose_targets":
            continue
        lines.append(
            f"| {st} | {len(r['scanned'])} | {len(r['unchanged'])} | {len(r['failed'])} | {len(r['chunks_written'])} "
            f"| {len(r['chunks_unchanged'])} | {len(r['chunks_removed'])} | {r['layers']} |"
        )
    failed = [
        f"- terrain `{st}/{rec}`: {why}" for st, r in report.items() if st != "_pose_targets" for rec, why in r["failed"].items()
    ]
    pose = report.get("_pose_targets")
    if pose is not None:
        lines += [
            "",
            f"pose targets: {len(pose['rendered'])} of {pose['chunks']} video chunks rendered, shards rewritten: "
            f"{pose['shards_rewritten']}, failed: {len(pose['failed'])}",
        ]
        failed += [f"- pose `{k}`: {why}" for k, why in sorted(pose["failed"].items())]
    return "\n".join(lines + ([""] + failed if failed else []))


@flow(name="rescan-stage")
def rescan_stage(
    corpus: str,
    stage: str | None = None,
    incremental: bool = True,
    frame_stride: int = 1,
    voxel_m: float = 0.25,
    depth_decoder: dict | None = None,
    render_targets: bool = True,
    dask_address: str | None = None,
    n_workers: int = 2,
) -> dict:
    """Scan one stage (or every stage) of ``corpus``, its recordings fanned out on Dask (a local cluster of
    ``n_workers`` processes, or the scheduler at ``dask_address``); returns per stage what was scanned and
    written, and the pose pass under ``"_pose_targets"``."""
    logger = get_run_logger()
    decoder = DepthDecoder.synthetic() if depth_decoder is None else DepthDecoder.from_json(depth_decoder)
    options = ScanOptions(decoder=decoder.to_json(), frame_stride=frame_stride, voxel_m=voxel_m)
    done = pipeline.refresh(
        Path(corpus),
        stage,
        incremental=incremental,
        scan_options=options,
        pose=render_targets,
        log=logger.info,
        scan_mapper=dask_mapper(dask_address, n_workers),
    )
    for line in done.lines():
        logger.info(line)
    report = {**done.terrain, **({"_pose_targets": done.pose} if done.pose is not None else {})}
    create_markdown_artifact(key="rescan-stage-report", markdown=report_markdown(corpus, report))
    return report
