"""Command-line option types and help formatting, shared by every entry point (``marionette`` and the
modules' ``python -m`` commands): each type checks its value as it is parsed, so a bad option exits 2
with a message naming it, before any work starts."""

from __future__ import annotations

import argparse
import difflib
from collections.abc import Callable
from pathlib import Path

from marionette.chunks import is_clip_length

X264_CRF = (0, 51)  # libx264's constant-rate-factor range for 8-bit video


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help with every option's default, written as it is typed (``176x320``); flags without a value
    (switches) and defaults of None (their help says what happens) are left as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if "%(default)" in text or not action.option_strings or action.nargs == 0 or d is None or d is argparse.SUPPRESS:
            return text
        if isinstance(d, list | tuple) and not d:
            return text
        shown = "x".join(str(v) for v in d) if isinstance(d, tuple) else str(d)
        return f"{text} (default: {shown.replace('%', '%%')})"


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose help shows defaults (``HelpFormatter``) and which checks options that only
    make sense together (``add_check``) once they are parsed; its subparsers are Parsers too."""

    def __init__(self, *args, formatter_class: type = HelpFormatter, **kwargs) -> None:
        super().__init__(*args, formatter_class=formatter_class, **kwargs)
        self.checks: list[Callable[[argparse.Namespace], str | None]] = []

    def add_check(self, check: Callable[[argparse.Namespace], str | None]) -> None:
        """After parsing, ``check(namespace)`` says what is wrong with the options together (exit 2 with
        that message, as a bad option's type would), or None."""
        self.checks.append(check)

    def parse_known_args(self, args=None, namespace=None):
        namespace, rest = super().parse_known_args(args, namespace)
        for check in self.checks:
            if (why := check(namespace)) is not None:
                self.error(why)
        return namespace, rest


def _integer(s: str) -> int:
    try:
        return int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, not {s!r}") from None


def _number(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, not {s!r}") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, not {s!r}")
    return v


def int_at_least(lo: int) -> Callable[[str], int]:
    """An argparse type: an integer ≥ ``lo``."""

    def parse(s: str) -> int:
        v = _integer(s)
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be at least {lo}, not {v}")
        return v

    parse.__name__ = f"integer ≥ {lo}"
    return parse


def int_in(lo: int, hi: int) -> Callable[[str], int]:
    """An argparse type: an integer in [``lo``, ``hi``]."""

    def parse(s: str) -> int:
        v = _integer(s)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be in {lo}..{hi}, not {v}")
        return v

    parse.__name__ = f"integer in {lo}..{hi}"
    return parse


positive_int = int_at_least(1)
non_negative_int = int_at_least(0)


def positive_float(s: str) -> float:
    """An argparse type: a finite number > 0."""
    v = _number(s)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be greater than 0, not {s}")
    return v


def non_negative_float(s: str) -> float:
    """An argparse type: a finite number ≥ 0."""
    v = _number(s)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, not {s}")
    return v


def x264_crf(s: str) -> int:
    """An argparse type: an x264 constant rate factor, 0 (lossless) to 51."""
    v = _integer(s)
    lo, hi = X264_CRF
    if not lo <= v <= hi:
        raise argparse.ArgumentTypeError(f"x264's crf runs from {lo} to {hi} (lower is better), not {v}")
    return v


def chunk_frames(s: str) -> int:
    """An argparse type: frames per video chunk, 4k + 1 and at least 5 (the video models' temporal stride is 4)."""
    v = _integer(s)
    if not is_clip_length(v):
        raise argparse.ArgumentTypeError(f"chunk frames are 4k + 1 and at least 5 (e.g. 41, 81), not {v}")
    return v


def gbuffer_path(s: str) -> Path:
    """An argparse type: a G-buffer file to write, ``.mkv`` (FFV1, for players) or ``.gbz`` (the corpus's encoding)."""
    path = Path(s)
    if path.suffix not in (".mkv", ".gbz"):
        raise argparse.ArgumentTypeError(f"{s!r}: a G-buffer file ends in .mkv (FFV1, for players) or .gbz (zstd)")
    return path


def size_hxw(s: str) -> tuple[int, int]:
    """An argparse type: ``HxW`` with both sides > 0."""
    try:
        h, w = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HxW, e.g. 176x320, not {s!r}") from None
    if h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"size {s!r}: height and width must both be greater than 0")
    return h, w


def even_size_hxw(s: str) -> tuple[int, int]:
    """An argparse type: ``HxW`` with both sides > 0 and even (H.264 in yuv420p halves the chroma planes)."""
    h, w = size_hxw(s)
    if h % 2 or w % 2:
        raise argparse.ArgumentTypeError(f"size {s!r}: H.264 video needs an even height and width")
    return h, w


def even_int(s: str) -> int:
    """An argparse type: an even integer > 0 (a side of an H.264 video)."""
    v = _integer(s)
    if v <= 0 or v % 2:
        raise argparse.ArgumentTypeError(f"an H.264 video side is an even number greater than 0, not {v}")
    return v


def near_ids(ids: list[str], wrong: str) -> str:
    """``; did you mean a, b?`` naming the ids closest to ``wrong``, or nothing when none is close."""
    near = difflib.get_close_matches(wrong, ids, n=3, cutoff=0.6)
    return f"; did you mean {', '.join(near)}?" if near else ""


def png_path(s: str) -> Path:
    """An argparse type: an output path ending in .png."""
    if Path(s).suffix.lower() != ".png":
        raise argparse.ArgumentTypeError(f"{s!r}: a plot is written as .png")
    return Path(s)


def mesh_path(s: str) -> Path:
    """An argparse type: an output path ending in .ply or .glb."""
    if Path(s).suffix.lower() not in (".ply", ".glb"):
        raise argparse.ArgumentTypeError(f"{s!r}: a mesh is written as .ply or .glb")
    return Path(s)
