"""The ``evaluate`` flow: run the evaluation protocol on a dynamics checkpoint (and, when given, an observation
model and a pixel-AR baseline) over a corpus's held-out windows, write the report directory and publish its
tables as artifacts.

    evaluate (Table 1 observation layer, Table 2 controllability, Table 3 driving states, long-horizon
    curves, the state layer) → report dir → artifacts

``protocol`` names the counts and lengths (``marionette.eval.config.PROTOCOLS``: "paper", "quick");
``segments``, ``seed_frames``, ``horizon``, ``rollouts`` and ``state_rollouts`` change them when given. The report directory holds
``report.md``, ``report.json`` and the plots; the flow publishes ``report.md`` as a markdown artifact and the
headline numbers as a table artifact.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE


@task(cache_policy=NO_CACHE, task_run_name="evaluate-{dynamics}")
def run_protocol(
    dynamics: str,
    corpus: str,
    out: str,
    protocol: str,
    observation: str | None,
    baseline: str | None,
    overrides: dict,
    seed: int,
) -> dict:
    """The whole protocol (``marionette.eval.report.evaluate``); returns its summary."""
    from marionette.eval.report import evaluate as run

    return run(
        dynamics,
        corpus,
        out,
        protocol=protocol,
        observation=observation,
        baseline=baseline,
        seed=seed,
        log=get_run_logger().info,
        **overrides,
    )


@flow(name="evaluate")
def evaluate(
    dynamics: str,
    corpus: str,
    out: str,
    protocol: str = "paper",
    observation: str | None = None,
    baseline: str | None = None,
    segments: int | None = None,
    seed_frames: int | None = None,
    horizon: int | None = None,
    rollouts: int | None = None,
    state_rollouts: int | None = None,
    seed: int = 0,
) -> dict:
    """Evaluate a dynamics checkpoint (training directory or checkpoint) on ``corpus``; the report goes to ``out``."""
    given = {"probe_windows": segments, "seed_frames": seed_frames, "horizon": horizon, "rollouts": rollouts}
    given["state_rollouts"] = state_rollouts
    overrides = {k: v for k, v in given.items() if v is not None}
    summary = run_protocol(dynamics, corpus, out, protocol, observation, baseline, overrides, seed)
    markdown = Path(summary["report_md"]).read_text()
    create_markdown_artifact(key="evaluation-report", markdown=markdown, description=f"evaluate {dynamics} on {corpus}")
    headline = summary.get("headline", {})
    if headline:
        create_table_artifact(key="evaluation-headline", table=[{"metric": k, "value": v} for k, v in headline.items()])
    return summary
