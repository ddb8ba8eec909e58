"""The eval command: the paper's three tables, long-horizon curves and state metrics of a checkpoint."""

from __future__ import annotations

import argparse
from pathlib import Path

from marionette.commands import command
from marionette.eval.config import PROTOCOLS
from marionette.options import (
    int_at_least,
    non_negative_int,
    positive_float,
    positive_int,
)
from marionette.progress import ProgressBars


def cmd_eval(a: argparse.Namespace) -> int:
    """Run the evaluation protocol on a dynamics checkpoint (and an observation model) and write the report."""
    from marionette.eval.report import evaluate

    bars = None if a.quiet else ProgressBars()
    fields = ("probe_windows", "seed_frames", "horizon", "rollouts", "rollout_seconds", "state_rollouts", "state_seconds")
    fields += ("fvd_steps",)
    overrides = {k: getattr(a, k) for k in fields if getattr(a, k) is not None}
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

    at_least_two = int_at_least(2)
    s.add_argument("dynamics", type=Path, help="a dynamics checkpoint or training directory")
    s.add_argument("corpus", type=Path, help="a corpus directory (its test split, else train, gives the windows)")
    s.add_argument("--out", type=Path, required=True, help="the report directory")
    s.add_argument("--protocol", choices=sorted(PROTOCOLS), default="paper", help="counts and lengths (quick: the demo's)")
    s.add_argument("--observation", type=Path, help="observation checkpoint or training directory (default: no FVD columns)")
    s.add_argument("--baseline", type=Path, help="pixel-AR baseline checkpoint (control actions) for Table 1 (default: none)")
    s.add_argument(
        "--segments", dest="probe_windows", type=positive_int, metavar="N", help="probe windows (default: the protocol's)"
    )
    s.add_argument("--seed-frames", type=positive_int, help="recorded frames seeding every rollout (default: the protocol's)")
    s.add_argument("--horizon", type=positive_int, help="predicted frames of each probe window (default: the protocol's)")
    s.add_argument("--rollouts", type=at_least_two, help="long rollouts of Tables 1 and 3 (default: the protocol's)")
    s.add_argument("--rollout-seconds", type=positive_float, help="length of each long rollout, s (default: the protocol's)")
    s.add_argument(
        "--state-rollouts",
        type=at_least_two,
        help="long rollouts of Table 3's state columns, ≥ --rollouts; the first are painted (default: the protocol's)",
    )
    s.add_argument("--state-seconds", type=positive_float, help="their length, s, ≥ --rollout-seconds (default: the protocol's)")
    s.add_argument("--fvd-steps", type=positive_int, help="sampling steps of the observation models (default: the protocol's)")
    s.add_argument("--seed", type=non_negative_int, default=0, help="seed of the window choice and the samplers")
    s.add_argument("--i3d", type=Path, help="Inception-I3D weights (safetensors) for FVD proper (default: the labelled proxy)")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.set_defaults(fn=cmd_eval)
