"""The ``train-dynamics`` flow: train ActionGPT + PoseGPT on a corpus and record the checkpoint and its metrics.

    train (one process, or ``nproc`` DDP processes under torchrun) → report artifact

A rerun with the same ``out`` resumes from its latest checkpoint (the same loss sequence as an
uninterrupted run), so a crashed or cancelled run loses at most ``checkpoint_every`` steps; a finished
run asked for the same ``steps`` does no work. Metrics also go to TensorBoard under ``<out>/tensorboard``.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from marionette.dynamics.config import TrainConfig
from marionette.dynamics.train import run


@task(cache_policy=NO_CACHE, task_run_name="train-{config.preset}")
def train_models(corpus: str, out: str, config: TrainConfig, nproc: int) -> dict:
    """Train (resuming when ``out`` holds a checkpoint; ``nproc`` > 1: under torchrun); returns the run's
    summary without the loss history."""
    summary = run(corpus, out, config, nproc=nproc, log=get_run_logger().info)
    return {k: v for k, v in summary.items() if k != "losses"}


def report_markdown(corpus: str, out: str, s: dict) -> str:
    lines = [
        f"# train-dynamics `{corpus}`",
        "",
        f"checkpoint `{s['checkpoint']}` after {s['steps']} steps (window {s['window']} frames); parameters "
        + ", ".join(f"{k} {v:,}" for k, v in s["parameters"].items()),
        f"TensorBoard: `tensorboard --logdir {Path(out) / 'tensorboard'}`",
    ]
    if s.get("final"):
        lines += ["", "final training terms: " + ", ".join(f"{k} {v:.4g}" for k, v in s["final"].items() if k != "step")]
    ev, base = s.get("eval"), s.get("baselines")
    if ev and base:
        lines += [
            "",
            f"held-out ({ev['windows']} windows) | model | baseline |",
            "|---|---|---|",
            f"| next-action accuracy | {ev['action_accuracy']:.4f} | copy-last {base['copy_last_action_accuracy']:.4f}, "
            f"most-frequent {base['most_frequent_action_accuracy']:.4f} |",
            f"| body MSE (normalised) | {ev['body_mse']:.5f} | copy-last {base['copy_last_body_mse']:.5f} |",
            f"| root MSE (normalised) | {ev['root_mse']:.5f} | constant velocity {base['constant_velocity_root_mse']:.5f} |",
        ]
    else:
        lines += ["", "no held-out split: nothing evaluated"]
    return "\n".join(lines)


@flow(name="train-dynamics")
def train_dynamics(
    corpus: str,
    out: str,
    preset: str = "tiny",
    steps: int = 1000,
    batch_size: int = 16,
    window: int | None = None,
    lr: float = 3e-4,
    seed: int = 0,
    relative: bool = True,
    checkpoint_every: int = 500,
    eval_every: int = 0,
    nproc: int = 1,
    loader_workers: int = 0,
) -> dict:
    """Train both dynamics models on ``corpus`` into ``out``; returns the summary (checkpoint, eval, baselines).
    ``loader_workers`` DataLoader processes per rank stack the batches (0: the training process does)."""
    config = TrainConfig(
        preset=preset,
        steps=steps,
        batch_size=batch_size,
        window=window,
        lr=lr,
        seed=seed,
        relative=relative,
        checkpoint_every=checkpoint_every,
        eval_every=eval_every,
        loader_workers=loader_workers,
    )
    summary = train_models(corpus, out, config, nproc)
    create_markdown_artifact(key="train-dynamics-report", markdown=report_markdown(corpus, out, summary))
    get_run_logger().info("checkpoint %s", summary["checkpoint"])
    return summary
