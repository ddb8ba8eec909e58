"""The rollout command: a trained dynamics model rolled out from a recorded segment."""

from __future__ import annotations

import argparse

from marionette.commands import command
from marionette.commands.summary import segment_row
from marionette.corpus import Corpus
from marionette.dynamics.controls import RolloutOptions, add_rollout_arguments
from marionette.knobs import option_values, options_from_args


def cmd_rollout(a: argparse.Namespace) -> int:
    """Roll a trained dynamics model out from a recorded segment's first frames."""
    from marionette.dynamics.rollout import write_rollout

    options = options_from_args(RolloutOptions, a)
    segment_row(Corpus(options.corpus), options.segment)
    write_rollout(**option_values(options))
    return 0


def register(sub) -> None:
    """Add rollout to ``sub`` (the ``marionette`` subparsers)."""
    s = command(
        "rollout", "roll a trained dynamics model out from a recorded segment, with forced tokens and scripted roots", sub
    )
    add_rollout_arguments(s)
    s.set_defaults(fn=cmd_rollout)
