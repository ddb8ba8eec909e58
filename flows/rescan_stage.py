"""The ``rescan-stage`` flow: scan new or changed recordings of a stage, then bring the pose targets up to date.

    refresh (``marionette.pipeline.refresh``, the call ``marionette terrain scan`` makes)
        scan-recordings (subflow: one ``scan-<stage>-<sample>`` task per recording, on Dask) → commit in order,
        rebuild → render-pose-targets (subflow: one ``pose-shard-<n>`` task per video shard, on Dask)
    → report artifact

The scan fans out like ingest: a local Dask cluster of ``n_workers`` processes, or the scheduler at
``dask_address``. Each task hashes its recording's inputs and scans it unless the stage already holds that
hash; the flow's process commits the contributions in recording order and rebuilds the chunks, so the
stage's files are the bytes of a serial scan. The pose pass then fans out the same way, one task per
video shard (a shard's targets depend only on its own chunks).

Incremental by default: recordings whose inputs and scan settings are unchanged are not read, and
only chunk files whose bytes change are rewritten. The pose-control targets of the video chunks
(``marionette.bridge.targets``) are then brought up to date: only chunks whose cameras see a changed
terrain chunk are rendered again (``render_targets=False`` skips this). The corpus lock is held
throughout; a recording or chunk that fails is listed in the report, and the rest goes on.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact

from flows.fanout import dask_cluster, dask_mapper
from marionette import pipeline
from terrain_scan.depth import DepthDecoder
from terrain_scan.options import ScanOptions


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
            f"pose targets: {len(pose['rendered'])} of {pose['chunks']} video chunks rendered, pose shards written: "
            f"{pose['shards_rewritten']}, failed: {len(pose['failed'])}",
        ]
        failed += [f"- pose `{k}`: {why}" for k, why in sorted(pose["failed"].items())]
    return "\n".join(lines + ([""] + failed if failed else []))


@flow(name="rescan-stage")
def rescan_stage(
    corpus: str,
    stage: str | None = None,
    incremental: bool = True,
    frame_stride: int | None = None,
    voxel_m: float | None = None,
    depth_decoder: dict | None = None,
    scan: dict | None = None,
    render_targets: bool = True,
    dask_address: str | None = None,
    n_workers: int = 2,
) -> dict:
    """Scan one stage (or every stage) of ``corpus``, its recordings fanned out on Dask (a local cluster of
    ``n_workers`` processes, or the scheduler at ``dask_address``); returns per stage what was scanned and
    written, and the pose pass under ``"_pose_targets"``. The scan options are the corpus's last (its
    ``meta/scan.json``, else the defaults) with ``scan`` (any ``terrain_scan.scan.KNOBS``), ``depth_decoder``,
    ``frame_stride`` and ``voxel_m`` laid over them; they are kept for the next scan."""
    logger = get_run_logger()
    base = ScanOptions.of_corpus(Path(corpus))
    if scan:
        base = base.merged(scan, "rescan-stage parameter scan")
    decoder = None if depth_decoder is None else DepthDecoder.from_json(depth_decoder).to_json()
    options = base.updated(decoder=decoder, frame_stride=frame_stride, voxel_m=voxel_m)
    logger.info("scan options: %s", options.describe())
    with dask_cluster(dask_address, n_workers) as address:  # one cluster for the scan and the render
        done = pipeline.refresh(
            Path(corpus),
            stage,
            incremental=incremental,
            scan_options=options,
            pose=render_targets,
            log=logger.info,
            scan_mapper=dask_mapper("scan-recordings", address, n_workers),
            pose_mapper=dask_mapper("render-pose-targets", address, n_workers),
        )
    for line in done.lines():
        logger.info(line)
    report = {**done.terrain, **({"_pose_targets": done.pose} if done.pose is not None else {})}
    create_markdown_artifact(key="rescan-stage-report", markdown=report_markdown(corpus, report))
    return report
