"""Does a forced attack token swing the weapon? The forcing measurement the control tests and the dynamics
benchmark share.

- **Held-out seeds** (``held_out_seeds``): (segment, first seed frame) every ``stride`` dynamics frames of every
  held-out segment where ``seed_frames`` seed rows and ``horizon`` predicted rows fit.
- **Tip speed** (``tip_speed``): the speed (m/s) of the weapon's last point in its owner's root frame, frame to
  frame from the last seed row on: root motion does not count, a swing does.
- **Swinging attacks** (``recorded_swingers``): the attack tokens of an entity whose plays in the train split (runs
  of one token) bring the tip above ``fast_mps`` within ``frames`` frames of their start on ≥ 80 % of ≥ 3 plays, most
  played first: the tokens a model can be asked to swing with, without asking it to learn from one example.
- **Swing rates** (``swing_rates``): per token forced over the first ``frames`` predicted frames (and None for the
  free rollout), the share of held-out seeds whose tip passes ``fast_mps`` within them (rules off, temperature 0),
  the rollouts run as batches.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from marionette.corpus import MODEL_FPS, Corpus, fixed_rows
from marionette.corpus.vocab import ActionTokens
from marionette.eval.protocol import Window, run_windows

FAST_TIP_MPS = 5.0  # the tests' train split: non-attack frames never move the weapon tip faster than 3.1 m/s


def held_out_seeds(c: Corpus, seed_frames: int, horizon: int, stride: int = 16, fps: float = MODEL_FPS) -> list[tuple[str, int]]:
    """(segment, first seed frame) every ``stride`` frames of every held-out ("test") segment that holds
    ``seed_frames`` + ``horizon`` dynamics frames from there."""
    out = []
    for s in c.segment_ids("test"):
        n = c.dynamics_segment(s, fps).num_rows
        out += [(s, k) for k in range(0, n - seed_frames - horizon + 1, stride)]
    return out


def tip_speeds(layout, state: np.ndarray, fps: float, attachment: str = "weapon") -> np.ndarray:
    """speed[f] (m/s) of an attachment's tip (its last point, in its owner's root frame) from state row f to f + 1."""
    tip = state[:, layout.slice(f"{attachment}.points")].reshape(len(state), -1, 3)[:, -1]
    return np.linalg.norm(np.diff(tip, axis=0), axis=1) * fps


def tip_speed(c: Corpus, table, seed_frames: int, fps: float = MODEL_FPS) -> np.ndarray:
    """Weapon-tip speed (m/s) in its owner's root frame of each predicted frame of a rollout table (from the last seed
    row on; the weapon's last point is its tip)."""
    return tip_speeds(c.layout, fixed_rows(table["state"], c.layout.dim)[seed_frames - 1 :], fps)


def recorded_swingers(
    c: Corpus, entity: str, frames: int, k: int, fast_mps: float = FAST_TIP_MPS, fps: float = MODEL_FPS
) -> list[int]:
    """Up to ``k`` attack tokens of ``entity`` whose train-split plays (runs of one token, ≥ 3 of them) bring the
    weapon tip above ``fast_mps`` within ``frames`` frames of their start on ≥ 80 % of plays, most played first."""
    tokens = ActionTokens.from_corpus(c)
    i = tokens.entities.index(entity)
    classes = {a["composite"]: a.get("class") for a in c.vocab["entity_types"][tokens.type_keys[i][1]]["actions"]}
    plays: dict[int, list[bool]] = {}
    for seg in c.segment_ids("train"):
        rows = c.dynamics_segment(seg, fps)
        stream = tokens.encode(c.layout, rows)[0][:, i]
        speed = tip_speeds(c.layout, fixed_rows(rows["state"], c.layout.dim), fps)
        for f in np.flatnonzero(np.r_[True, stream[1:] != stream[:-1]]):
            t = int(stream[f])
            if classes.get(int(tokens.composites[i][t])) == "attack" and f + frames <= len(speed):
                plays.setdefault(t, []).append(bool(speed[f : f + frames].max() > fast_mps))
    good = [t for t, v in plays.items() if len(v) >= 3 and np.mean(v) >= 0.8]
    return sorted(good, key=lambda t: (-len(plays[t]), t))[:k]


def swing_rates(
    ckpt: Path | str,
    c: Corpus,
    entity: str,
    attacks: Sequence[int],
    seeds: Sequence[tuple[str, int]],
    seed_frames: int,
    frames: int = 10,
    fast_mps: float = FAST_TIP_MPS,
    batch: int = 64,
) -> dict[int | None, float]:
    """Per token of ``attacks`` forced on ``entity`` for ``frames`` frames from each held-out seed (and None: not
    forced), the share of seeds whose weapon tip passes ``fast_mps`` within those frames (rules off, temperature 0).
    Every (token, seed) rollout runs in batches of ``batch`` streams (``protocol.run_windows``)."""
    windows = [Window.at(c, seg, start, seed_frames, frames) for seg, start in seeds]
    tokens: list[int | None] = [None, *attacks]
    force = [[] if t is None else [(entity, 0, frames, int(t))] for t in tokens for _ in windows]
    tables, _ = run_windows(ckpt, c, windows * len(tokens), rules="none", force=force, batch=batch)
    fast = np.array([tip_speed(c, table, seed_frames).max() > fast_mps for table in tables]).reshape(len(tokens), -1)
    return {t: float(np.mean(row)) for t, row in zip(tokens, fast)}
