"""The ``rescan-stage`` flow: scan new or changed recordings of a stage, then bring the pose targets up to date.

    refresh (one task: ``marionette.pipeline.refresh``, the same call ``marionette terrain scan`` makes) → report artifact

Incremental by default: recordings whose inputs and scan settings are unchanged are not read, and
only chunk files whose bytes change are rewritten. The pose-control targets of the video chunks
(``marionette.bridge.targets``) are then brought up to date: only chunks whose cameras see a changed
terrain chunk are rendered again (``render_targets=False`` skips this). The corpus lock is held
throughout; a recording or chunk that fails is listed in the report, and the rest goes on.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from marionette import pipeline
from terrain_scan.depth import DepthDecoder
from terrain_scan.scan import ScanOptions


@task(cache_policy=NO_CACHE, task_run_name="refresh-{corpus}")
def refresh_corpus(corpus: str, stage: str | None, incremental: bool, options: ScanOptions, render_targets: bool) -> dict:
    """Scan the stage(s), then render the pose targets whose inputs changed; logs each line of the summary."""
    logger = get_run_logger()
    done = pipeline.refresh(
        Path(corpus), stage, incremental=incremental, scan_options=options, pose=render_targets, log=logger.info
    )
    for line in done.lines():
        logger.info(line)
    return {**done.terrain, **({"_pose_targets": done.pose} if done.pose is not None else {})}


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
) -> dict:
    """Scan one stage (or every stage) of ``corpus``; returns per stage what was scanned and written, and the
    pose pass under ``"_pose_targets"``."""
    decoder = DepthDecoder.synthetic() if depth_decoder is None else DepthDecoder.from_json(depth_decoder)
    options = ScanOptions(decoder=decoder.to_json(), frame_stride=frame_stride, voxel_m=voxel_m)
    report = refresh_corpus(corpus, stage, incremental, options, render_targets)
    create_markdown_artifact(key="rescan-stage-report", markdown=report_markdown(corpus, report))
    return report
