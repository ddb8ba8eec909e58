"""The generate command: paint RGB onto a pose-control video with a trained observation model."""

from __future__ import annotations

import argparse
from pathlib import Path

from marionette.commands import command
from marionette.options import (
    non_negative_int,
    positive_float,
    positive_int,
)


def generate_arguments(ap: argparse.ArgumentParser) -> None:
    """The generate command's arguments."""
    ap.add_argument(
        "ckpt",
        type=Path,
        help="an observation checkpoint or training directory, or a Wan2.2-Fun-Control model directory (`train wan`'s OUT/model)",
    )
    pose_help = "a pose-control G-buffer video (.mkv), from `marionette export-chunk` or `marionette render`"
    ap.add_argument("--pose", type=Path, required=True, help=pose_help)
    ap.add_argument("--first-frame", type=Path, required=True, help="the first frame: an image of the pose video's size")
    ap.add_argument("--out", type=Path, required=True, help="output .mp4")
    ap.add_argument("--chunks", type=positive_int, default=None, help="chunks to relay (default: all the pose video holds)")
    ap.add_argument("--steps", type=positive_int, default=20, help="sampling steps per chunk")
    ap.add_argument("--seed", type=non_negative_int, default=0, help="seed of the sampling noise")
    ap.add_argument("--fps", type=positive_float, default=30.0, help="frame rate of the output video")
    ap.add_argument(
        "--no-references",
        dest="references",
        action="store_false",
        help="a model trained with entity references paints without them (each chunk sees only its first frame)",
    )


def cmd_generate(a: argparse.Namespace) -> int:
    """Paint RGB onto a pose-control video with a trained observation model."""
    from marionette.observation.generate import paint_video

    paint_video(
        a.ckpt, a.pose, a.first_frame, a.out, chunks=a.chunks, steps=a.steps, seed=a.seed, fps=a.fps, references=a.references
    )
    return 0


def register(sub) -> None:
    """Add generate to ``sub`` (the ``marionette`` subparsers)."""
    s = command("generate", "paint RGB onto a pose-control video with a trained observation model", sub)
    generate_arguments(s)
    s.set_defaults(fn=cmd_generate)
