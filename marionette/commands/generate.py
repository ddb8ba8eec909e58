"""The generate command: paint RGB onto a pose-control video with a trained observation model."""

from __future__ import annotations

import argparse
from dataclasses import MISSING, dataclass
from pathlib import Path

from marionette.commands import command
from marionette.knobs import add_options, option
from marionette.options import (
    non_negative_int,
    positive_float,
    positive_int,
)


@dataclass(frozen=True, kw_only=True)
class GenerateOptions:
    """``marionette generate``'s options."""

    ckpt: Path = option(
        MISSING,
        "an observation checkpoint or training directory, or a Wan2.2-Fun-Control model directory (`train wan`'s OUT/model)",
        parse=Path,
        positional=True,
    )
    pose: Path = option(
        MISSING, "a pose-control G-buffer video (.mkv), from `marionette export-chunk` or `marionette render`", parse=Path
    )
    first_frame: Path = option(MISSING, "the first frame: an image of the pose video's size", parse=Path)
    out: Path = option(MISSING, "output .mp4", parse=Path)
    chunks: int | None = option(None, "chunks to relay (default: all the pose video holds)", parse=positive_int)
    steps: int = option(20, "sampling steps per chunk", parse=positive_int)
    seed: int = option(0, "seed of the sampling noise", parse=non_negative_int)
    fps: float = option(30.0, "frame rate of the output video", parse=positive_float)
    references: bool = option(
        True,
        "a model trained with entity references paints without them (each chunk sees only its first frame)",
        flag="--no-references",
        switch=True,
    )


def generate_arguments(ap: argparse.ArgumentParser) -> None:
    """The generate command's arguments."""
    add_options(ap, GenerateOptions)


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
