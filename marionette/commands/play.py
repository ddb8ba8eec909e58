"""The play command: the world model (or a replay) in a browser page on 127.0.0.1."""

from __future__ import annotations

import argparse

from marionette.commands import command
from marionette.knobs import option_values, options_from_args
from marionette.play import PlayOptions, add_arguments, serve


def cmd_play(a: argparse.Namespace) -> int:
    """Serve the play page (live or replay) on 127.0.0.1 until interrupted."""
    serve(**option_values(options_from_args(PlayOptions, a)))
    return 0


def register(sub) -> None:
    """Add play to ``sub`` (the ``marionette`` subparsers)."""
    s = command(
        "play", "play the world model in a browser (keys force tokens, WASD moves a root), or replay state with no model", sub
    )
    add_arguments(s)
    s.set_defaults(fn=cmd_play)
