"""A command's options as a dataclass (``knobs.option``): the flags ``add_options`` makes, each checked as it is
parsed, read back by ``options_from_args`` as the keyword arguments of the function they feed."""

from __future__ import annotations

import argparse
from dataclasses import MISSING, dataclass
from pathlib import Path

import pytest

from marionette.knobs import add_options, option, option_values, options_from_args
from marionette.options import Parser, positive_int


@dataclass(frozen=True, kw_only=True)
class Opts:
    src: Path = option(MISSING, "where from", parse=Path, positional=True)
    extra: Path | None = option(None, "an optional second", parse=Path, positional=True, optional=True)
    horizon: int = option(MISSING, "frames", parse=positive_int)
    steps: int = option(4, "steps", parse=positive_int, metavar="N")
    tags: tuple[str, ...] = option((), "repeatable", many=True)
    fast: bool = option(False, "go fast", switch=True)
    name: str = option("x", "a name", flag="--called")


def parser() -> Parser:
    ap = Parser(prog="t")
    add_options(ap, Opts)
    return ap


def test_options_are_parsed_checked_and_read_back_as_the_dataclass():
    args = parser().parse_args(["a", "--horizon", "3", "--tags", "p", "q", "--tags", "r", "--fast", "--called", "y"])
    opts = options_from_args(Opts, args)
    assert opts == Opts(src=Path("a"), horizon=3, tags=("p", "q", "r"), fast=True, name="y")
    assert option_values(opts) == {
        "src": Path("a"),
        "extra": None,
        "horizon": 3,
        "steps": 4,
        "tags": ("p", "q", "r"),
        "fast": True,
        "name": "y",
    }


def test_help_shows_each_default_and_a_bad_or_missing_option_exits_2(capsys):
    text = parser().format_help()
    assert "steps (default: 4)" in text and "--steps N" in text
    assert "a name (default: x)" in text and "--called" in text and "repeatable" in text
    for argv, why in ((["a", "--horizon", "0"], "at least 1"), (["a"], "--horizon")):
        with pytest.raises(SystemExit) as exc:
            parser().parse_args(argv)
        assert exc.value.code == 2 and why in capsys.readouterr().err


def test_an_option_without_its_kind_is_refused():
    @dataclass(frozen=True)
    class Bad:
        x: int = 1

    with pytest.raises(TypeError, match="Bad.x is not an option"):
        add_options(argparse.ArgumentParser(), Bad)
