"""The commands' option types that read the project's own definitions (scene names and ``--rigs``, corpus ids,
scan knobs), each checked as it is parsed; the generic ones are ``marionette.options``."""

from __future__ import annotations

import argparse
from pathlib import Path

from marionette.options import near_ids
from terrain_scan.knobs import KNOBS, knob_ok


def scene_name(s: str) -> str:
    """An argparse type: the name of a scene, built in (``schemas/scenes/``) or among a user's (``--rigs DIR``;
    ``checked_scene`` looks it up once both options are parsed)."""
    from marionette.schema import NAME_PATTERN, SCHEMA_DIR

    if not NAME_PATTERN.fullmatch(s):
        names = sorted(f.stem for f in (SCHEMA_DIR / "scenes").glob("*.json"))
        raise argparse.ArgumentTypeError(f"{s!r} is not a scene name{near_ids(names, s)} (built-in scenes: {', '.join(names)})")
    return s


def rigs_dir(s: str) -> Path:
    """An argparse type: a directory of user rigs and scenes (``rigs/``, ``scenes/``, as ``marionette survey`` drafts)."""
    p = Path(s)
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{s}: not a directory")
    if not (p / "rigs").is_dir() and not (p / "scenes").is_dir():
        raise argparse.ArgumentTypeError(
            f"{s}: holds neither rigs/ nor scenes/ (write one with `marionette survey SOURCE --rigs-out {s}`)"
        )
    return p


def scene_missing(a: argparse.Namespace) -> str | None:
    """A parser check: why ``--scene`` names no scene, built in or under ``--rigs``, or None."""
    from marionette.schema import scene_names

    names = scene_names(rigs=getattr(a, "rigs", None))
    if a.scene in names or a.scene == "auto":
        return None
    where = "built in" + (f" or under {a.rigs}/scenes" if getattr(a, "rigs", None) is not None else "")
    return f"argument --scene: no scene {a.scene!r} {where}{near_ids(names, a.scene)} (scenes: {', '.join(names)})"


RIGS_HELP = "user rigs and scenes looked up before the built-in ones (DIR/rigs, DIR/scenes)"  # --rigs, beside --scene


def checked_scene(a: argparse.Namespace):
    """The layout of ``--scene`` with ``--rigs``; an unknown scene or a bad rig is an error naming the file."""
    from marionette.schema import load_scene

    return load_scene(a.scene, rigs=getattr(a, "rigs", None))


def scan_option(s: str) -> tuple[str, float | int]:
    """An argparse type: ``KNOB=VALUE`` for one of ``terrain_scan.scan.KNOBS``, the value checked as the knob needs."""

    name, eq, raw = s.partition("=")
    if not eq or name not in KNOBS:
        raise argparse.ArgumentTypeError(
            f"{s!r}: give KNOB=VALUE with KNOB one of {', '.join(KNOBS)}{near_ids(list(KNOBS), name)}"
        )
    check = KNOBS[name][0]
    try:
        value: float | int = int(raw) if check.startswith("an int") else float(raw)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r}: {name} must be {check}") from None
    if not knob_ok(check, value):
        raise argparse.ArgumentTypeError(f"{s!r}: {name} must be {check}")
    return name, value


def id_string(s: str) -> str:
    """An argparse type: a name of 1–200 letters, digits, '_' or '-' (a corpus id)."""
    from marionette.corpus.paths import ID_PATTERN

    if not ID_PATTERN.fullmatch(s):
        raise argparse.ArgumentTypeError(f"{s!r}: a name is 1-200 letters, digits, '_' or '-'")
    return s
