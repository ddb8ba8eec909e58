"""Stages from the data: recordings grouped by the agreement of their scanned terrain, never by coordinates.

Two maps of one game may share world coordinates (WildWorld's stages do), so a recording's place is decided
by what it saw: its cells (each cell's best-supported observation, the one with most hits) against a
stage's observations in the same cells. A cell agrees when some observation of the stage there lies within
``AGREE_M`` of the recording's height (a layered stage: the recording may have seen the ground under a
bridge deck the stage holds; but a cell where each saw only another of its surfaces disagrees, which is why the
share asked for is well under 1). A recording joins the stage it agrees with best — at least ``MIN_SHARED`` shared
cells, of which at least ``AGREE_SHARE`` agree — and otherwise starts a stage of its own: a recording that
overlaps no stage, or conflicts with all of them, is never merged into one.

``place`` is greedy in recording order, so a rerun over the same contributions places them the same way.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from terrain_scan.layers import Observations

AGREE_M = 0.5  # a shared cell agrees when the heights lie this close (the and the merge rule's 0.5 m)
# a recording joins a stage when this share of their shared cells agree … (measured on the synthetic game: 78–100 %
# within a stage, where the rest are layered cells each saw another surface of — ground under a bridge deck the other
# saw only from above —, and 23–31 % across two overlapping stages, where flat ground happens to coincide)
AGREE_SHARE = 0.6
MIN_SHARED = 25  # … and they share at least this many cells (fewer: no evidence either way, a stage of its own)


def _keys(gx: np.ndarray, gz: np.ndarray) -> np.ndarray:
    return ((gx.astype(np.int64) + (1 << 31)) << 32) | (gz.astype(np.int64) + (1 << 31))


def best_per_cell(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """(cell keys, height) of each cell's best-supported observation (most hits; the lower on a tie), by key."""
    if not len(obs):
        return np.zeros(0, np.int64), np.zeros(0)
    k = _keys(obs.gx, obs.gz)
    order = np.lexsort((obs.h, -obs.hits, k))
    k, h = k[order], obs.h[order]
    first = np.ones(len(k), bool)
    first[1:] = k[1:] != k[:-1]
    return k[first], h[first]


def agreement(obs: Observations, stage: Observations, agree_m: float = AGREE_M) -> tuple[int, int]:
    """(shared cells, agreeing cells) of a recording's observations against a stage's."""
    ka, ha = best_per_cell(obs)
    if not len(ka) or not len(stage):
        return 0, 0
    kb = _keys(stage.gx, stage.gz)
    order = np.argsort(kb, kind="stable")
    kb, hb = kb[order], stage.h[order]
    lo, hi = np.searchsorted(kb, ka, "left"), np.searchsorted(kb, ka, "right")
    shared = hi > lo
    best = np.full(len(ka), np.inf)
    for k in range(int((hi - lo).max(initial=0))):
        at = lo + k
        ok = at < hi
        best[ok] = np.minimum(best[ok], np.abs(ha[ok] - hb[at[ok]]))
    return int(shared.sum()), int((shared & (best <= agree_m)).sum())


@dataclass
class Placement:
    """Where one recording went and the evidence: against each stage it shares cells with, (shared, agreeing)."""

    recording: str
    stage: str
    evidence: dict[str, tuple[int, int]] = field(default_factory=dict)
    new: bool = False

    def line(self) -> str:
        ev = ", ".join(f"{s}: {a}/{n} cells agree" for s, (n, a) in sorted(self.evidence.items()) if n) or "no shared cells"
        return f"{self.recording} → stage {self.stage}{' (new)' if self.new else ''} ({ev})"


def place(
    pending: list[tuple[str, Observations]],
    stages: dict[str, Callable[[Observations], Observations]],
    new_name: Callable[[set[str]], str],
    agree_m: float = AGREE_M,
    agree_share: float = AGREE_SHARE,
    min_shared: int = MIN_SHARED,
) -> list[Placement]:
    """Place recordings (in the given order) onto stages.

    ``stages`` maps each existing stage to a function giving its observations near a recording's (it may read
    only the chunks the recording touches); ``new_name(names in use)`` names a new stage. A recording placed here
    joins the observations its later ones are compared with."""
    held: dict[str, list[Observations]] = {}  # stages made or grown in this pass: their new members' observations
    out = []
    for name, obs in pending:
        evidence: dict[str, tuple[int, int]] = {}
        for st in sorted(set(stages) | set(held)):
            parts = ([stages[st](obs)] if st in stages else []) + held.get(st, [])
            evidence[st] = agreement(obs, Observations.concat(parts), agree_m)
        fits = [(a, st) for st, (n, a) in evidence.items() if n >= min_shared and a >= agree_share * n]
        if fits:
            stage, new = max(fits, key=lambda t: (t[0], t[1]))[1], False
        else:
            stage, new = new_name(set(stages) | set(held)), True
        held.setdefault(stage, []).append(obs)
        out.append(Placement(name, stage, evidence, new))
    return out
