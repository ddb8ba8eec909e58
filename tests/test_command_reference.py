"""docs/commands.md is what scripts/command_reference.py writes from the parsers, has a section for every command
reachable from ``build_parser``, and reads the same whatever the terminal's width."""

from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path

import pytest

from marionette.cli import build_parser

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "command_reference.py"
DOC = ROOT / "docs" / "commands.md"


def load():
    spec = importlib.util.spec_from_file_location("command_reference", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def progs(parser: argparse.ArgumentParser) -> list[str]:
    """Every command's name under ``parser``, read through argparse's subparsers group (not the script's walk)."""
    if parser._subparsers is None:
        return []
    found = []
    for action in parser._subparsers._group_actions:  # the group holds the other positionals too
        if isinstance(action.choices, dict):
            for sub in action.choices.values():
                found += [sub.prog, *progs(sub)]
    return found


def test_the_reference_is_what_the_parsers_say():
    written, generated = DOC.read_text(encoding="utf-8"), load().reference()
    if written != generated:
        old, new = written.splitlines(), generated.splitlines()
        at = next((k for k, (a, b) in enumerate(zip(old, new, strict=False)) if a != b), min(len(old), len(new)))
        pytest.fail(
            f"docs/commands.md differs from the parsers' help from line {at + 1} on: "
            "run `python scripts/command_reference.py` and commit docs/commands.md"
        )


def test_every_command_has_a_section_with_its_help():
    text = DOC.read_text(encoding="utf-8")
    sections = re.findall(r"^## (.+)$", text, flags=re.MULTILINE)
    expected = ["marionette", *progs(build_parser())]
    assert sections == expected
    assert {"marionette train dynamics", "marionette terrain scan", "marionette eval"} <= set(sections)
    assert len(expected) >= 20
    for prog in expected:
        assert f"(#{prog.replace(' ', '-')})" in text, prog
        assert re.search(rf"^## {prog}\n\n```text\nusage: {prog} ", text, flags=re.MULTILINE), prog


def test_the_reference_does_not_depend_on_the_terminal(monkeypatch):
    script = load()
    monkeypatch.setenv("COLUMNS", "40")
    narrow = script.reference()
    monkeypatch.setenv("COLUMNS", "240")
    assert script.reference() == narrow
