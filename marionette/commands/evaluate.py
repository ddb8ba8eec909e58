"""The eval command: the paper's three tables, long-horizon curves and state metrics of a checkpoint."""

from __future__ import annotations

import argparse
from dataclasses import MISSING, dataclass
from pathlib import Path

from marionette.commands import command
from marionette.eval.config import OVERRIDES, PROTOCOLS, EvalProtocol
from marionette.knobs import add_config_arguments, add_options, option
from marionette.options import (
    non_negative_int,
)
from marionette.progress import ProgressBars


@dataclass(frozen=True, kw_only=True)
class EvalOptions:
    """``marionette eval``'s options beside the protocol's counts (``eval.config.OVERRIDES``, flags made from
    ``EvalProtocol``'s knobs)."""

    dynamics: Path = option(MISSING, "a dynamics checkpoint or training directory", parse=Path, positional=True)
    corpus: Path = option(
        MISSING, "a corpus directory (its test split, else train, gives the windows)", parse=Path, positional=True
    )
    out: Path = option(MISSING, "the report directory", parse=Path)
    protocol: str = option("paper", "counts and lengths (quick: the demo's)", choices=sorted(PROTOCOLS))
    observation: Path | None = option(None, "observation checkpoint or training directory (default: no FVD columns)", parse=Path)
    baseline: Path | None = option(None, "pixel-AR baseline checkpoint (control actions) for Table 1 (default: none)", parse=Path)
    seed: int = option(0, "seed of the window choice and the samplers", parse=non_negative_int)
    i3d: Path | None = option(
        None, "Inception-I3D weights (safetensors) for FVD proper (default: the labelled proxy)", parse=Path
    )
    quiet: bool = option(False, "no progress bars", switch=True)


def cmd_eval(a: argparse.Namespace) -> int:
    """Run the evaluation protocol on a dynamics checkpoint (and an observation model) and write the report."""
    from marionette.eval.report import evaluate

    bars = None if a.quiet else ProgressBars()
    overrides = {k: getattr(a, k) for k in OVERRIDES if getattr(a, k) is not None}
    try:
        options = dict(protocol=a.protocol, observation=a.observation, baseline=a.baseline, seed=a.seed, i3d=a.i3d)
        s = evaluate(a.dynamics, a.corpus, a.out, **options, **overrides, progress=bars)
    finally:
        if bars is not None:
            bars.close()
    print(f"report: {s['report_md']}")
    return 0


def register(sub) -> None:
    """Add eval to ``sub`` (the ``marionette`` subparsers)."""
    s = command("eval", "evaluate a dynamics checkpoint: the paper's three tables, long-horizon curves, state metrics", sub)

    add_options(s, EvalOptions)
    add_config_arguments(s, EvalProtocol, OVERRIDES, default="the protocol's")
    s.set_defaults(fn=cmd_eval)
