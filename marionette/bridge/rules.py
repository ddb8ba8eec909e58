"""Rules of the bridge: the terrain collider and the separation cap, applied to predicted world skeletons.

The rules sit between the dynamics model and the renderer: they correct the predicted world state and
the corrected state is fed back. A skeleton sequence is a dict entity name → (N, K, 3) float64 world
joints (m, Y up); an articulated entity's joint 0 is its root. Frames where an entity is absent hold
NaN; an entity with any non-finite joint at frame t is skipped at t (its output stays NaN) and its
previous frame for the next step is its last valid corrected one.

Rigid: every correction is one translation per articulated entity and frame, applied to all its joints
and to the joints of the attachments it owns (the weapon rides with the hunter). Nothing is rotated and
no bone length changes. The output at frame t is the input at t plus the entity's *accumulated* offset:
a correction made at t carries to every later frame (feedback), so the proposed frame t is the input
frame t translated by the offset accumulated up to t − 1. Frame 0 (an entity's first valid frame) is
taken as given. Per frame t ≥ 1, in this order:

1. Collider (per articulated entity; needs a ``LayeredField``). p0 = corrected root at t − 1,
   p1 = proposed root at t.
   a. Wall: h0 = ``cell_height(p0.x, p0.z, ref_y = lowest joint y of the corrected frame t − 1)``,
      h1 = ``cell_height(p1.x, p1.z, ref_y = h0)``. If both are finite, h1 − h0 > ``max_step_m`` and the
      root's vertical speed (p1.y − p0.y)·fps ≤ ``jump_speed_mps``, the horizontal motion is cancelled:
      the offset gains (p0.x − p1.x, 0, p0.z − p1.z). The wall is judged on cell-level heights, not on
      the bilinear surface, which would turn a wall into a ramp.
   b. Ground: the lowest joint (x, y, z) of the (wall-corrected) frame, s = ``query(x, z, ref_y = y)``
      (the layer nearest the foot: a body on a deck picks the deck, one under it the floor), d = s − y.
      A surface more than ``max_step_m`` above the foot is out of reach (a wall the foot pokes into, a
      deck above a hop) and changes nothing. Otherwise the vertical offset becomes
      max(0, off_y + clip(d, −max_lift_m, +max_lift_m)): a sinking body is lifted by at most
      ``max_lift_m`` per frame, the lift decays back to zero once the body is above the ground (jumps
      pass), and a body never goes below the model's own trajectory. NaN surface: no change.
2. Cap (scenes with exactly two articulated entities, both present at t). d0 = horizontal (x, z)
   root distance of the corrected frames at t − 1 (after a gap: at the last frame where both were
   present, so that an absence never loosens the cap), d1 = that of the proposed frames t (after the
   collider). L = max(``max_separation_m``, d0). If d1 > L both move horizontally toward each other by
   (d1 − L)/2 along the line joining their roots, so that the distance becomes L: a pair drifting apart
   is held at the cap from the frame it would cross it; a pair already farther apart is never moved
   farther apart, nor pulled together. A frame where either is absent is not capped.

Everything is float64 numpy and deterministic (bit-identical on repeat); the sequence form equals the
per-step form bit for bit. The collider moves only on the articulated entity's own joints (an
attachment dipping into the ground does not lift its owner).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from marionette.schema import Layout

if TYPE_CHECKING:
    from terrain_scan.field import LayeredField

RULES = ("collider", "cap")  # the order they are applied in


@dataclass(frozen=True)
class RuleParams:
    """Parameters of the rules (metres, seconds)."""

    max_step_m: float = 1.5  # a cell-level step up taller than this (m) is a wall and blocks
    jump_speed_mps: float = 2.5  # root vertical speed (m/s) above which moving into a wall is a jump and passes
    max_lift_m: float = 0.04  # the collider's vertical correction per frame (m)
    max_separation_m: float = 6.0  # horizontal root distance (m) the cap holds a two-entity scene within
    fps: float = 30.0  # frame rate of the sequence (frames/s), for speeds


def enabled_rules(layout: Layout, field: LayeredField | None) -> tuple[str, ...]:
    """The rules that apply to a scene, in order: "collider" with a terrain field, "cap" with exactly two articulated entities."""
    return tuple(r for r, ok in zip(RULES, (field is not None, len(layout.articulated) == 2)) if ok)


class Rules:
    """The rules over one scene, stateful per rollout: ``reset`` then ``step`` frame by frame, or ``apply`` a sequence."""

    def __init__(
        self,
        layout: Layout,
        field: LayeredField | None = None,
        params: RuleParams = RuleParams(),
        enabled: Iterable[str] | None = None,
    ):
        asked = set(enabled_rules(layout, field) if enabled is None else enabled)
        if unknown := asked - set(RULES):
            raise ValueError(f"unknown rules {sorted(unknown)}; known: {list(RULES)}")
        if "collider" in asked and field is None:
            raise ValueError("the collider needs a terrain field (field=None given)")
        if "cap" in asked and len(layout.articulated) != 2:
            raise ValueError(f"the cap needs two articulated entities; scene {layout.scene!r} has {len(layout.articulated)}")
        self.layout, self.field, self.params = layout, field, params
        self.enabled = tuple(r for r in RULES if r in asked)
        self._bodies = tuple(e.name for e in layout.articulated)
        self._owner = {e.name: e.owner for e in layout.attachments}
        self.reset()

    def reset(self) -> None:
        """Start a new rollout: no accumulated offsets, no previous frame."""
        self._offset = {n: np.zeros(3) for n in self._bodies}  # accumulated translation (m) per articulated entity
        self._prev: dict[str, np.ndarray | None] = dict.fromkeys(self._bodies)  # last valid corrected frame (K, 3)
        self._pair_distance: float | None = None  # horizontal root distance (m) when the pair was last both present

    @property
    def offsets(self) -> dict[str, np.ndarray]:
        """Accumulated translation (3,) (m) of each articulated entity (and its attachments) after the last step."""
        return {n: o.copy() for n, o in self._offset.items()}

    def step(self, frame: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Correct one frame: name → (K, 3) world joints (m) → a corrected copy; attachments are optional."""
        if unknown := set(frame) - set(self._bodies) - set(self._owner):
            raise ValueError(f"entities {sorted(unknown)} are not in scene {self.layout.scene!r}")
        if missing := [n for n in self._bodies if n not in frame]:
            raise ValueError(f"frame lacks articulated entities {missing}")
        cur = {n: np.asarray(frame[n], np.float64) for n in self._bodies}
        present = [n for n in self._bodies if np.isfinite(cur[n]).all()]
        if "collider" in self.enabled:
            for n in present:
                if self._prev[n] is not None:
                    self._collide(n, cur[n])
        if "cap" in self.enabled and len(present) == 2 and self._pair_distance is not None:
            self._cap(*present, cur)
        out = {n: self._moved(np.asarray(x, np.float64), self._offset[self._owner.get(n, n)]) for n, x in frame.items()}
        for n in present:
            self._prev[n] = out[n]
        if "cap" in self.enabled and len(present) == 2:
            a, b = (out[n][0] for n in present)
            self._pair_distance = math.hypot(b[0] - a[0], b[2] - a[2])
        return out

    def apply(self, seq: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Correct a whole sequence: name → (N, K, 3) world joints (m) → corrected copies (reset, then step per frame)."""
        seq = {n: np.asarray(x, np.float64) for n, x in seq.items()}
        if bad := [n for n, x in seq.items() if x.ndim != 3 or x.shape[2] != 3]:
            raise ValueError(f"entities {bad} are not (N, K, 3) joint sequences")
        if len(set((counts := {n: len(x) for n, x in seq.items()}).values())) > 1:
            raise ValueError(f"entities have different frame counts {counts}")
        self.reset()
        steps = [self.step({n: x[t] for n, x in seq.items()}) for t in range(len(next(iter(seq.values()), ())))]
        return {n: np.stack([s[n] for s in steps]) if steps else x.copy() for n, x in seq.items()}

    # -- the rules -----------------------------------------------------------------------------------

    @staticmethod
    def _moved(x: np.ndarray, offset: np.ndarray) -> np.ndarray:
        return x + offset if offset.any() else x.copy()

    def _collide(self, name: str, frame: np.ndarray) -> None:
        """Update ``name``'s offset for input frame (K, 3): the wall, then the ground."""
        p, field, off, prev = self.params, self.field, self._offset[name], self._prev[name]
        p0, p1 = prev[0], frame[0] + off
        h0 = field.cell_height(p0[0], p0[2], prev[:, 1].min())
        h1 = field.cell_height(p1[0], p1[2], h0)
        if np.isfinite(h0) and np.isfinite(h1) and h1 - h0 > p.max_step_m and (p1[1] - p0[1]) * p.fps <= p.jump_speed_mps:
            off[0] += p0[0] - p1[0]
            off[2] += p0[2] - p1[2]
        moved = frame + off  # the wall-corrected frame
        low = moved[np.argmin(moved[:, 1])]
        d = field.query(low[0], low[2], low[1]) - low[1]
        if np.isfinite(d) and d <= p.max_step_m:
            off[1] = max(0.0, off[1] + min(max(float(d), -p.max_lift_m), p.max_lift_m))

    def _cap(self, a: str, b: str, cur: Mapping[str, np.ndarray]) -> None:
        """Update the offsets of the pair (a, b) so that their horizontal root distance is ≤ max(cap, previous distance)."""
        ra, rb = cur[a][0] + self._offset[a], cur[b][0] + self._offset[b]
        dx, dz = rb[0] - ra[0], rb[2] - ra[2]
        d1 = math.hypot(dx, dz)
        limit = max(self.params.max_separation_m, self._pair_distance)
        if d1 > limit:
            k = 0.5 * (d1 - limit) / d1  # each moves half the excess along the line joining the roots
            self._offset[a][[0, 2]] += (k * dx, k * dz)
            self._offset[b][[0, 2]] -= (k * dx, k * dz)


def apply_rules(
    layout: Layout,
    seq: Mapping[str, np.ndarray],
    field: LayeredField | None = None,
    params: RuleParams = RuleParams(),
    enabled: Iterable[str] | None = None,
) -> dict[str, np.ndarray]:
    """Apply the rules to a skeleton sequence: name → (N, K, 3) world joints (m) → corrected copies."""
    return Rules(layout, field, params, enabled).apply(seq)
