"""The ``marionette`` commands, one module per group (corpus, terrain, render, train, generate, rollout, play,
evaluate, demo): each ``register(sub)`` adds its commands' parsers, whose ``fn`` runs the command. A command's module
imports the heavy libraries only inside the function that runs it, so every ``--help`` reads without them."""

from __future__ import annotations

import argparse
import sys


def command(name: str, help: str, group) -> argparse.ArgumentParser:
    """A subcommand ``name`` of ``group`` (an argparse subparsers action), its description its help as a sentence."""
    return group.add_parser(name, help=help, description=help[0].upper() + help[1:] + ".")


def strict_status(strict: bool, failures: dict[str, int]) -> int:
    """The exit status of a build: 1 under --strict when any sample was quarantined or any scan or pose target failed."""
    if strict and any(failures.values()):
        print("--strict: " + ", ".join(f"{n} {kind}" for kind, n in failures.items() if n) + " failed", file=sys.stderr)
        return 1
    return 0
