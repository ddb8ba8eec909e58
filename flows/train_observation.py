"""The ``train-observation`` flow: bring a corpus's pose-control targets up to date, train the observation
model on its video shards, and record the checkpoint and its held-out loss.

    pose targets (cached: only chunks whose inputs changed are rendered) → train → report artifact

A rerun with the same ``out`` resumes from its latest checkpoint; one that finds the run finished
trains nothing.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from flows.fanout import dask_mapper
from marionette.bridge.targets import render_pose_targets
from marionette.observation.config import ObservationTrainConfig
from marionette.observation.train import run


@task(cache_policy=NO_CACHE, task_run_name="train-observation-{config.control}")
def train_model(corpus: str, out: str, config: ObservationTrainConfig, nproc: int = 1) -> dict:
    """Train (resuming when ``out`` holds a checkpoint; ``nproc`` > 1: under torchrun); returns the summary
    without the loss history."""
    summary = run(corpus, out, config, nproc=nproc, log=get_run_logger().info)
    return {k: v for k, v in summary.items() if k != "losses"}


def report_markdown(corpus: str, s: dict) -> str:
    first, last = s["evals"][0], s["evals"][-1]
    return "\n".join(
        [
            f"# train-observation `{corpus}`",
            "",
            f"checkpoint `{s['checkpoint']}` after {s['steps']} steps; {s['parameters']:,} parameters; "
            f"{s['chunks']} train chunks, {s['held_out']} held-out ({s['held_out_split']})",
            "",
            "| held-out flow loss | step |",
            "|---|---|",
            f"| {first['held_out_loss']:.4f} (initialisation) | {first['step']} |",
            f"| {last['held_out_loss']:.4f} | {last['step']} |",
        ]
    )


@flow(name="train-observation")
def train_observation(
    corpus: str,
    out: str,
    preset: str = "tiny",
    steps: int = 1000,
    batch_size: int = 4,
    frames: int | None = None,
    reduce: int = 4,
    patch: int | None = None,
    lr: float = 3e-4,
    seed: int = 0,
    control: str = "pose",
    checkpoint_every: int = 250,
    reference_swap: float | None = None,
    nproc: int = 1,
    dask_address: str | None = None,
    n_workers: int = 2,
) -> dict:
    """Pose targets up to date (the ``render-pose-targets`` subflow: a task per video shard on Dask, the
    scheduler at ``dask_address`` or ``n_workers`` local processes), then train the observation model (or the
    pixel-AR baseline, control="actions"); ``reference_swap`` None: the trainer's default (0.2 under pose
    control, 0 for the baseline)."""
    config = ObservationTrainConfig(
        preset=preset,
        steps=steps,
        batch_size=batch_size,
        frames=frames,
        reduce=reduce,
        patch=patch,
        lr=lr,
        seed=seed,
        control=control,
        checkpoint_every=checkpoint_every,
        reference_swap=reference_swap,
    )

    r = render_pose_targets(Path(corpus), mapper=dask_mapper("render-pose-targets", dask_address, n_workers))
    get_run_logger().info("pose targets: %d of %d chunks rendered, %d failed", len(r.rendered), r.chunks, len(r.failed))
    summary = train_model(corpus, out, config, nproc)
    create_markdown_artifact(key="train-observation-report", markdown=report_markdown(corpus, summary))
    return summary
