"""The ``rescan-stage`` flow: scan new or changed recordings of a stage into its terrain chunks.

    scan (one task per stage: `terrain_scan.scan.scan_stages`) → pose targets → report artifact

Incremental by default: recordings whose inputs and scan settings are unchanged are not read, and
only chunk files whose bytes change are rewritten. The pose-control targets of the video chunks
(``marionette.bridge.targets``) are then brought up to date: only chunks whose cameras see a changed
terrain chunk are rendered again (``render_targets=False`` skips this).
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from terrain_scan.depth import DepthDecoder
from terrain_scan.scan import ScanOptions, corpus_stages, scan_stages


@task(cache_policy=NO_CACHE, task_run_name="scan-stage-{stage}")
def scan_stage(corpus: str, stage: str, incremental: bool, options: ScanOptions) -> dict:
    """Scan one stage; logs each recording."""
    logger = get_run_logger()
    return scan_stages(Path(corpus), stage, incremental=incremental, options=options, log=logger.info)[stage]


@task(cache_policy=NO_CACHE, task_run_name="pose-targets")
def pose_targets(corpus: str) -> dict:
    """Render the video chunks' pose targets whose inputs changed; rewrite only the shards that change."""
    from marionette.bridge.targets import render_pose_targets

    r = render_pose_targets(Path(corpus))
    get_run_logger().info("pose targets: %d of %d chunks rendered, shards rewritten %s", len(r.rendered), r.chunks, r.shards_rewritten)
    return {"chunks": r.chunks, "rendered": r.rendered, "shards_rewritten": r.shards_rewritten, "frames_rendered": r.frames_rendered}


def report_markdown(corpus: str, report: dict) -> str:
    lines = [
        f"# rescan-stage `{corpus}`",
        "",
        "| stage | scanned | unchanged | failed | chunks written | unchanged | removed | layers |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for st, r in report.items():
        lines.append(
            f"| {st} | {len(r['scanned'])} | {len(r['unchanged'])} | {len(r['failed'])} | {len(r['chunks_written'])} "
            f"| {len(r['chunks_unchanged'])} | {len(r['chunks_removed'])} | {r['layers']} |"
        )
    return "\n".join(lines)


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
    """Scan one stage (or every stage) of ``corpus``; returns per stage what was scanned and written."""
    decoder = DepthDecoder.synthetic() if depth_decoder is None else DepthDecoder.from_json(depth_decoder)
    options = ScanOptions(decoder=decoder.to_json(), frame_stride=frame_stride, voxel_m=voxel_m)
    stages = [stage] if stage is not None else list(corpus_stages(Path(corpus)))
    report = {st: scan_stage(corpus, st, incremental, options) for st in stages}
    markdown = report_markdown(corpus, report)
    if render_targets:
        pose = pose_targets(corpus)
        markdown += f"\n\npose targets: {len(pose['rendered'])} of {pose['chunks']} video chunks rendered, shards rewritten: {pose['shards_rewritten']}"
        report = {**report, "_pose_targets": pose}
    create_markdown_artifact(key="rescan-stage-report", markdown=markdown)
    return report
