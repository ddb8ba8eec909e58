"""The synthetic game's action vocabulary: per species, (bank, motion) clips with lengths and classes.

Composite id = bank × 1000 + motion + 1 (0 = no valid action). "state" clips loop (their
``motion_frame`` wraps to 0), "event" clips play once. ``speed`` is the clip's horizontal root
speed (m/s) for locomotion; ``duty`` the stance fraction of the gait cycle.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Clip:
    """One action clip of one species."""

    name: str
    bank: int
    motion: int
    length: int  # frames at 30 fps
    kind: str  # "state" (loops) or "event" (plays once)
    cls: str  # "stationary" | "locomotion" | "attack" | "other"
    speed: float = 0.0  # m/s, horizontal root speed (locomotion)
    duty: float = 0.6  # stance fraction of a gait cycle

    @property
    def composite(self) -> int:
        """bank × 1000 + motion + 1."""
        return self.bank * 1000 + self.motion + 1


HUNTER_CLIPS: dict[str, Clip] = {
    c.name: c
    for c in (
        Clip("idle", 0, 0, 30, "state", "stationary"),
        Clip("walk", 0, 1, 30, "state", "locomotion", speed=1.5, duty=0.5),
        Clip("run", 0, 2, 18, "state", "locomotion", speed=4.0, duty=0.4),
        Clip("attack", 1, 0, 30, "event", "attack"),
        Clip("heavy_attack", 1, 1, 45, "event", "attack"),
        Clip("dodge", 1, 2, 18, "event", "other"),
    )
}

# The drake's run is 4.2 m/s, not faster: a planted foot moves through the root frame at the root
# speed, and every non-attack clip keeps root-frame joint speeds at or below 5 m/s.
MONSTER_CLIPS: dict[str, Clip] = {
    c.name: c
    for c in (
        Clip("idle", 0, 0, 36, "state", "stationary"),
        Clip("walk", 0, 1, 36, "state", "locomotion", speed=2.0, duty=0.5),
        Clip("run", 0, 2, 20, "state", "locomotion", speed=4.2, duty=0.4),
        Clip("bite", 3, 0, 36, "event", "attack"),
        Clip("tail_swipe", 3, 1, 45, "event", "attack"),
        Clip("roar", 3, 2, 75, "event", "other"),
    )
}

CLIPS = {"hunter": HUNTER_CLIPS, "monster": MONSTER_CLIPS}
TYPE_IDS = {"hunter": 0, "monster": 25, "weapon": 3}


def clip_table(entity: str) -> dict[int, dict]:
    """Composite id → {name, bank, motion, length, kind, class} for one entity type."""
    return {
        c.composite: {"name": c.name, "bank": c.bank, "motion": c.motion, "length": c.length, "kind": c.kind, "class": c.cls}
        for c in CLIPS[entity].values()
    }
