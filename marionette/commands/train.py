"""The train commands: train dynamics, train observation, train wan."""

from __future__ import annotations

import argparse
import json

from marionette.commands import command
from marionette.dynamics.config import TrainConfig
from marionette.knobs import add_training_arguments, config_from_args, nodes_from_args
from marionette.observation.config import ObservationTrainConfig, WanTrainConfig


def cmd_train_dynamics(a: argparse.Namespace) -> int:
    """Train ActionGPT + PoseGPT on a corpus (resuming from --out when it holds a checkpoint)."""
    from marionette.dynamics.config import TrainConfig
    from marionette.dynamics.train import run

    config = config_from_args(TrainConfig, a)
    summary = run(a.corpus, a.out, config, nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return 0


def cmd_train_observation(a: argparse.Namespace) -> int:
    """Train the observation model on a corpus's video shards (resuming from --out)."""
    from marionette.observation.config import ObservationTrainConfig
    from marionette.observation.train import run

    config = config_from_args(ObservationTrainConfig, a)
    summary = run(a.corpus, a.out, config, nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return 0


def cmd_train_wan(a: argparse.Namespace) -> int:
    """Fine-tune Wan2.2-Fun-Control on a corpus's pose-control chunks (resuming from --out)."""
    from marionette.observation.config import WanTrainConfig
    from marionette.observation.wan_train import run

    config = config_from_args(WanTrainConfig, a)
    summary = run(a.corpus, a.out, config, nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return 0


def register(sub) -> None:
    """Add train dynamics, train observation, train wan to ``sub`` (the ``marionette`` subparsers)."""
    t = command("train", "train a model on a corpus", sub)
    tsub = t.add_subparsers(dest="train_cmd", required=True, metavar="COMMAND")
    s = command("dynamics", "train ActionGPT + PoseGPT (a rerun with the same --out resumes)", tsub)
    add_training_arguments(s, TrainConfig)
    s.set_defaults(fn=cmd_train_dynamics)

    s = command("observation", "train the observation model (pose video + first frame → RGB) on the video shards", tsub)
    add_training_arguments(s, ObservationTrainConfig)
    s.set_defaults(fn=cmd_train_observation)

    s = command(
        "wan", "fine-tune Wan2.2-Fun-Control on the corpus's pose-control chunks (latent cache, full or LoRA; resumes)", tsub
    )
    add_training_arguments(s, WanTrainConfig)
    s.set_defaults(fn=cmd_train_wan)
