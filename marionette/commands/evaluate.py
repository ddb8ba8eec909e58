"""The eval command: the paper's three tables, long-horizon curves and state metrics of a checkpoint."""

from __future__ import annotations

import argparse
from pathlib import Path

from marionette.commands import command
from marionette.eval.config import OVERRIDES, PROTOCOLS, EvalProtocol
from marionette.knobs import add_config_arguments
from marionette.options import (
    non_negative_int,
)
from marionette.progress import ProgressBars


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

    s.add_argument("dynamics", type=Path, help="a dynamics checkpoint or training directory")
    s.add_argument("corpus", type=Path, help="a corpus directory (its test split, else train, gives the windows)")
    s.add_argument("--out", type=Path, required=True, help="the report directory")
    s.add_argument("--protocol", choices=sorted(PROTOCOLS), default="paper", help="counts and lengths (quick: the demo's)")
    s.add_argument("--observation", type=Path, help="observation checkpoint or training directory (default: no FVD columns)")
    s.add_argument("--baseline", type=Path, help="pixel-AR baseline checkpoint (control actions) for Table 1 (default: none)")
    add_config_arguments(s, EvalProtocol, OVERRIDES, default="the protocol's")
    s.add_argument("--seed", type=non_negative_int, default=0, help="seed of the window choice and the samplers")
    s.add_argument("--i3d", type=Path, help="Inception-I3D weights (safetensors) for FVD proper (default: the labelled proxy)")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.set_defaults(fn=cmd_eval)
