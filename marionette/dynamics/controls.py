"""The controls a rollout takes from a command line, parsed and checked as they are read: forced tokens
(``ENTITY:START:END:TOKEN``), scripted roots (``ENTITY:START:END:VX,VY,VZ`` or ``ENTITY:FILE.npy``), the rules, and
the rollout command's options; and their form per predicted frame (``forced_at``, ``force_windows``,
``script_roots``). Importable without torch: ``marionette rollout --help`` and ``play`` read it."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import MISSING, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from marionette.bridge.rules import RULES
from marionette.knobs import add_options, option
from marionette.options import HelpFormatter, gbuffer_path, non_negative_float, non_negative_int, positive_int, size_hxw

Force = tuple[str, int, int, int]  # (entity, start, end exclusive, token), predicted-frame indices


def frames_arg(flag: str, s: str, start: str, end: str) -> tuple[int, int]:
    """(START, END) predicted frames of a ``flag`` value ``s``: integers with 0 ≤ START < END."""
    try:
        a, b = int(start), int(end)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{flag} {s!r}: START and END are integers") from None
    if not 0 <= a < b:
        raise argparse.ArgumentTypeError(f"{flag} {s!r}: frames [{a}, {b}) are empty or negative (0 ≤ START < END)")
    return a, b


def parse_force(s: str) -> Force:
    """``ENTITY:START:END:TOKEN`` (predicted frames, END exclusive; TOKEN ≥ 1, 0 being "no valid action")."""
    parts = s.rsplit(":", 3)
    if len(parts) != 4 or not parts[0]:
        raise argparse.ArgumentTypeError(f"--force {s!r}: expected ENTITY:START:END:TOKEN")
    start, end = frames_arg("--force", s, parts[1], parts[2])
    try:
        token = int(parts[3])
    except ValueError:
        raise argparse.ArgumentTypeError(f"--force {s!r}: TOKEN is an integer") from None
    if token < 1:
        raise argparse.ArgumentTypeError(f"--force {s!r}: TOKEN is at least 1 (0 is 'no valid action')")
    return parts[0], start, end, token


def parse_script(s: str) -> tuple[str, Any]:
    """``ENTITY:START:END:VX,VY,VZ`` (a constant root velocity in the entity's own frame, m/s; END
    exclusive) or ``ENTITY:FILE.npy`` (a (horizon, 9) array of E.root then E.rot6d, NaN = the model's)."""
    name, _, rest = s.partition(":")
    if not name:
        raise argparse.ArgumentTypeError(f"--script-root {s!r}: expected ENTITY:START:END:VX,VY,VZ or ENTITY:FILE.npy")
    if rest.endswith(".npy"):
        return name, Path(rest)
    parts = rest.split(":")
    if len(parts) != 3 or len(parts[2].split(",")) != 3:
        raise argparse.ArgumentTypeError(f"--script-root {s!r}: expected ENTITY:START:END:VX,VY,VZ or ENTITY:FILE.npy")
    start, end = frames_arg("--script-root", s, parts[0], parts[1])
    try:
        velocity = tuple(float(v) for v in parts[2].split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--script-root {s!r}: VX,VY,VZ are numbers (m/s)") from None
    if not all(np.isfinite(velocity)):
        raise argparse.ArgumentTypeError(f"--script-root {s!r}: VX,VY,VZ are finite")
    return name, (start, end, velocity)


def parse_rules(s: str) -> str:
    """``auto``, ``none`` or a comma list of known rules (returned as given; ``run`` splits it)."""
    if s in ("auto", "none"):
        return s
    unknown = [r for r in s.split(",") if r not in RULES]
    if unknown or not s:
        raise argparse.ArgumentTypeError(f"--rules {s!r}: expected auto, none or a comma list of {','.join(RULES)}")
    return s


@dataclass(frozen=True, kw_only=True)
class RolloutOptions:
    """The rollout command's options (``marionette rollout`` and ``python -m marionette.dynamics.rollout``), each
    checked as it is parsed; ``rollout.write_rollout`` takes them as keyword arguments."""

    ckpt: Path = option(MISSING, "a checkpoint directory or a training output directory", parse=Path, positional=True)
    corpus: Path = option(MISSING, "the corpus the segment comes from", parse=Path, positional=True)
    segment: str = option(MISSING, "the recorded segment whose first frames seed the rollout")
    seed_frames: int = option(64, "recorded frames fed before the first predicted one", parse=positive_int)
    horizon: int = option(MISSING, "predicted frames", parse=positive_int)
    temperature: float = option(0.0, "sampling temperature; 0: argmax, deterministic", parse=non_negative_float)
    seed: int = option(0, "the sampler's seed", parse=non_negative_int)
    force: tuple[Force, ...] = option(
        (),
        "ENTITY:START:END:TOKEN, predicted frames, END exclusive (repeatable; default: no forced tokens)",
        parse=parse_force,
        many=True,
    )
    script_root: tuple[tuple[str, Any], ...] = option(
        (),
        "ENTITY:START:END:VX,VY,VZ (m/s, own frame) or ENTITY:FILE.npy ((horizon, 9) root channels; default: none)",
        parse=parse_script,
        many=True,
    )
    rules: str = option("auto", f"auto, none, or a comma list of {','.join(RULES)}", parse=parse_rules)
    out: Path = option(MISSING, "STATES.arrow (the corpus state schema)", parse=Path)
    render: Path | None = option(None, "also render the rollout (follow camera) to this .mkv or .gbz", parse=gbuffer_path)
    size: tuple[int, int] = option((352, 640), "render size, HxW", parse=size_hxw, metavar="HxW")


def add_rollout_arguments(ap: argparse.ArgumentParser) -> None:
    """The rollout command's arguments (``RolloutOptions``), under either entry point."""
    ap.formatter_class = HelpFormatter  # every option's default in --help, under either entry point
    add_options(ap, RolloutOptions)


def forced_at(force: Sequence[Force], t: int, names: Sequence[str]) -> tuple[dict[int, int], list[int]]:
    """At predicted frame ``t``: the forced token per entity index, and the entities whose action replays from
    progress 0 although its token is unchanged: a window that starts where a window of the same entity and
    token ends (back-to-back windows play the action twice). A lone window forcing the token already playing
    continues it; one forcing another token restarts at 0 because the token changed."""
    forced, restart = {}, []
    for name, first, end, token in force:
        if int(first) <= t < int(end):
            forced[names.index(name)] = int(token)
            if t == int(first) and any(n == name and int(e) == t and int(k) == int(token) for n, _, e, k in force):
                restart.append(names.index(name))
    return forced, restart


def force_windows(entity: str, tokens: Sequence[int]) -> list[Force]:
    """A token stream (one per predicted frame) as force windows, one per run of equal tokens; token 0
    ("no valid action") is left to the model. Forcing the recorded stream this way is Force-GT."""
    out, k = [], 0
    while k < len(tokens):
        end = k + 1
        while end < len(tokens) and tokens[end] == tokens[k]:
            end += 1
        if tokens[k] != 0:
            out.append((entity, k, end, int(tokens[k])))
        k = end
    return out


def script_roots(script_root: Any, horizon: int, layout, root_dim: int) -> np.ndarray | None:
    """A (horizon, root_dim) override with NaN = no override, from an array or a dict entity → (horizon, 9)."""
    if script_root is None:
        return None
    if isinstance(script_root, dict):
        out = np.full((horizon, root_dim), np.nan)
        unknown = sorted(set(script_root) - {e.name for e in layout.articulated})
        if unknown:
            raise ValueError(f"script_root: unknown entities {unknown}")
        for i, e in enumerate(layout.articulated):
            if e.name in script_root:
                a = np.asarray(script_root[e.name], np.float64)
                if a.ndim != 2 or a.shape[1] != 9 or len(a) < horizon:
                    raise ValueError(f"script_root[{e.name!r}] has shape {a.shape}; expected ({horizon}, 9) or longer")
                out[:, 9 * i : 9 * i + 9] = a[:horizon]
        return out
    a = np.asarray(script_root, np.float64)
    if a.shape != (horizon, root_dim):
        raise ValueError(f"script_root has shape {a.shape}; expected ({horizon}, {root_dim})")
    return a


def script_from_args(scripts: Sequence[tuple[str, Any]], horizon: int, fps: float, layout) -> dict[str, np.ndarray] | None:
    """Parsed ``--script-root`` values → the dict form of ``rollout``'s ``script_root`` (entity → (horizon, 9))."""
    if not scripts:
        return None
    names = [e.name for e in layout.articulated]
    out: dict[str, np.ndarray] = {}
    for name, spec in scripts:
        if name not in names:
            raise ValueError(f"--script-root: unknown entity {name!r}; the scene has {names}")
        arr = out.setdefault(name, np.full((horizon, 9), np.nan))
        if isinstance(spec, Path):
            a = np.load(spec, allow_pickle=False)
            if a.ndim != 2 or a.shape[1] != 9 or len(a) < horizon:
                raise ValueError(f"{spec}: a root script is ({horizon}, 9) or longer (E.root then E.rot6d), not {a.shape}")
            arr[:] = np.where(np.isfinite(a[:horizon]), a[:horizon], arr)
        else:
            start, end, velocity = spec
            if not 0 <= start < end or start >= horizon:
                raise ValueError(
                    f"--script-root {name}: frames [{start}, {end}) are empty, negative or past the horizon {horizon}"
                )
            arr[start : min(end, horizon), 0:3] = np.asarray(velocity) / fps  # metres per model frame
    return out
