"""The ``evaluate`` flow: run the evaluation protocol on a dynamics checkpoint (and, when given, an observation
model) over a corpus's held-out windows, write the report directory and publish its tables as artifacts.

    evaluate (state-layer metrics, controllability probe, rule ablation, proxy-FVD) → report dir → artifacts

The report directory holds ``report.md``, ``report.json`` and the plots; the flow publishes ``report.md``
as a markdown artifact and the headline numbers as a table artifact.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE


@task(cache_policy=NO_CACHE, task_run_name="evaluate-{dynamics}")
def run_protocol(
    dynamics: str, corpus: str, out: str, observation: str | None, segments: int, seed_frames: int, horizon: int, seed: int
) -> dict:
    """The whole protocol (``marionette.eval.report.evaluate``); returns its summary."""
    from marionette.eval.report import evaluate as run

    return run(
        dynamics,
        corpus,
        out,
        observation=observation,
        segments=segments,
        seed_frames=seed_frames,
        horizon=horizon,
        seed=seed,
        log=get_run_logger().info,
    )


@flow(name="evaluate")
def evaluate(
    dynamics: str,
    corpus: str,
    out: str,
    observation: str | None = None,
    segments: int = 8,
    seed_frames: int = 64,
    horizon: int = 120,
    seed: int = 0,
) -> dict:
    """Evaluate a dynamics checkpoint (training directory or checkpoint) on ``corpus``; the report goes to ``out``."""
    summary = run_protocol(dynamics, corpus, out, observation, segments, seed_frames, horizon, seed)
    markdown = Path(summary["report_md"]).read_text()
    create_markdown_artifact(key="evaluation-report", markdown=markdown, description=f"evaluate {dynamics} on {corpus}")
    headline = summary.get("headline", {})
    if headline:
        create_table_artifact(key="evaluation-headline", table=[{"metric": k, "value": v} for k, v in headline.items()])
    return summary
