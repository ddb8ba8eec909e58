"""The ``marionette`` command: its parser (each group's commands registered by ``marionette.commands``) and ``main``."""

from __future__ import annotations

import os
import sys

from marionette.commands import corpus, demo, evaluate, generate, play, render, rollout, terrain, train
from marionette.options import Parser

DESCRIPTION = (
    "Game recordings into a corpus, terrain and pose-control targets; dynamics and observation models trained, rolled out, "
    "painted and evaluated. `marionette COMMAND --help` lists a command's options and their defaults."
)


def build_parser() -> Parser:
    """The ``marionette`` command line: every subcommand, each option validated as it is parsed and its default shown.
    It imports no heavy library (torch, open3d, prefect, diffusers, moderngl): each command imports what it runs."""
    p = Parser(prog="marionette", description=DESCRIPTION)
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for group in (corpus, terrain, render, train, generate, rollout, play, evaluate, demo):
        group.register(sub)
    return p


def error_message(exc: BaseException) -> str | None:
    """What the command prints for an error it expects (bad input, a file it cannot read or write), or None
    for one it does not (a bug: its traceback is shown)."""
    if isinstance(exc, OSError):
        if exc.filename is None:
            return str(exc)
        where = f"{exc.filename}" + (f" -> {exc.filename2}" if exc.filename2 is not None else "")
        return f"{where}: {exc.strerror or exc}"
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        return exc.args[0]  # str(KeyError) would quote the message
    if isinstance(exc, ValueError | RuntimeError | KeyError):
        return str(exc)
    safetensors = sys.modules.get("safetensors")  # an error of it can only come once it was imported
    if safetensors is not None and isinstance(exc, safetensors.SafetensorError):
        return f"not a readable safetensors file: {exc}"
    return None


def main(argv: list[str] | None = None) -> int:
    """Run one command; an expected error is one line on stderr and exit status 2 (MARIONETTE_DEBUG=1 raises it instead)."""
    args = build_parser().parse_args(argv)
    name = " ".join(n for n in (args.cmd, getattr(args, "terrain_cmd", None), getattr(args, "train_cmd", None)) if n)
    try:
        return args.fn(args)
    except BrokenPipeError:  # the reader of stdout left (`| head`): nothing to say, and no one to say it to
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE
    except KeyboardInterrupt:
        if os.environ.get("MARIONETTE_DEBUG") == "1":
            raise
        print(f"marionette {name}: interrupted", file=sys.stderr)
        return 130  # 128 + SIGINT, as a shell reports it
    except Exception as exc:
        message = error_message(exc)
        if message is None or os.environ.get("MARIONETTE_DEBUG") == "1":
            raise
        print(f"marionette {name}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
