"""Checks of what the page and scripts send: a message's fields are checked where they are read, and a bad one is a
``ValueError`` naming the field, its value and what it may be (the server answers it as one line)."""

from __future__ import annotations

import re
from typing import Any

import numpy as np

MAX_CONTROL_FRAMES = 100_000
MAX_SPEED_MPS = 50.0
MAX_TURN_DPS = 720.0
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def checked_name(name: Any) -> str:
    """A recording name: letters, digits, ``_ . -``, at most 64 characters, not starting with a dot (never a path)."""
    if not isinstance(name, str) or not NAME_RE.fullmatch(name) or ".." in name:
        raise ValueError(f"recording name {name!r}: 1–64 letters, digits, '_', '.' or '-', starting with a letter or digit")
    return name


def int_field(msg: dict, key: str, lo: int, hi: int, default: int | None = None) -> int | None:
    v = msg.get(key, default)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"{key} {v!r} is not an integer in {lo}..{hi}")
    return int(v)


def checked_root(v: Any) -> np.ndarray:
    """A root velocity [vx, vy, vz] (m/s in the entity's own frame; null: the model's) as an array with NaN for the
    model's; each given speed at most ``MAX_SPEED_MPS``."""
    if (
        not isinstance(v, list)
        or len(v) != 3
        or not all(x is None or (isinstance(x, int | float) and not isinstance(x, bool)) for x in v)
    ):
        raise ValueError(f"root {v!r} is not [vx, vy, vz] (numbers in m/s, or null for the model's)")
    vel = np.array([np.nan if x is None else float(x) for x in v])
    if not np.all(np.isnan(vel) | (np.abs(np.nan_to_num(vel)) <= MAX_SPEED_MPS)):
        raise ValueError(f"root {v!r}: speeds are finite and at most {MAX_SPEED_MPS:g} m/s")
    return vel


def checked_turn(turn: Any) -> float:
    """A turn in degrees/s about the vertical, within ±``MAX_TURN_DPS``."""
    if isinstance(turn, bool) or not isinstance(turn, int | float) or not abs(turn) <= MAX_TURN_DPS:
        raise ValueError(f"turn {turn!r} is not a number of degrees/s within ±{MAX_TURN_DPS:g}")
    return float(turn)
