"""Write the command reference, docs/commands.md: every ``marionette`` command's ``--help``, read from its parser.

    python scripts/command_reference.py            # write docs/commands.md
    python scripts/command_reference.py --check    # exit 1 when docs/commands.md is not what it would write

The help is wrapped at ``WIDTH`` columns whatever the terminal, so the page is the same on every machine.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Iterator
from pathlib import Path

from marionette.cli import build_parser

DOC = Path(__file__).resolve().parent.parent / "docs" / "commands.md"
WIDTH = 100  # argparse otherwise wraps at the terminal's width ($COLUMNS, or the tty's), which differs per machine
COMMAND = "python scripts/command_reference.py"


def commands(parser: argparse.ArgumentParser, help: str) -> Iterator[tuple[argparse.ArgumentParser, str]]:
    """``parser`` with its one-line ``help``, then every parser below it, depth first in the order registered."""
    yield parser, help
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help or "" for choice in action._choices_actions}
            for name, sub in action.choices.items():
                yield from commands(sub, helps[name])


def anchor(prog: str) -> str:
    """The id GitHub gives the heading ``## prog``: command names are lower case, so only the spaces change."""
    return prog.replace(" ", "-")


def reference() -> str:
    """The Markdown page: a title, how it is made, a linked list of the commands, then each one's ``--help``."""
    root = build_parser()
    found = list(commands(root, root.description or ""))
    for parser, _ in found:
        parser.formatter_class = functools.partial(parser.formatter_class, width=WIDTH)
    lines = [
        "# Command reference",
        "",
        f"Every command's `--help`, generated from the parsers by `{COMMAND}` "
        f"(`{COMMAND} --check` says whether this page is current); edit the parsers, not this page.",
        "",
    ]
    lines += [f"- [`{parser.prog}`](#{anchor(parser.prog)}): {help}" for parser, help in found]
    for parser, _ in found:
        lines += ["", f"## {parser.prog}", "", "```text", parser.format_help().rstrip(), "```"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DOC, help="the page to write or check (default: docs/commands.md)")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 when the page differs from the parsers")
    a = ap.parse_args(argv)
    text = reference()
    if a.check:
        if not a.out.is_file() or a.out.read_text(encoding="utf-8") != text:
            print(f"{a.out} differs from the parsers' help: run `{COMMAND}`", file=sys.stderr)
            return 1
        return 0
    a.out.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
