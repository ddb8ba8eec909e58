"""The synthetic game's action vocabulary: per species, (bank, motion) clips with lengths, classes and variants.

Composite id = bank × 1000 + motion + 1 (0 = no valid action). "state" clips loop (their
``motion_frame`` wraps to 0), "event" clips play once. Each clip is a variant of a pose ``family``
(``controls.py`` draws it from the clip's ``params``), and carries its root motion: loops move at
``speed`` m/s in the direction ``move_dir`` (radians from the facing, + = to the character's left)
and turn at ``turn`` rad/s (+ = left); events move at up to ``speed`` m/s during the phase window
``move`` (fractions of the clip). ``duty`` is the stance fraction of a gait cycle. An attack's hit
lands at phase ``hit_at`` for ``damage`` hit points.

Speeds are bounded by the class rule's statistics: a planted foot moves through the root frame at the
root speed, and every non-attack clip keeps root-frame joint speeds at or below 5 m/s (so runs stay
at or under 4.8 m/s); attacks peak well above 7 m/s (``marionette.corpus.vocab.ATTACK_PEAK_MPS``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FPS = 30  # clip lengths are in frames at this rate


@dataclass(frozen=True)
class Clip:
    """One action clip of one species."""

    name: str
    bank: int
    motion: int
    length: int  # frames at 30 fps
    kind: str  # "state" (loops) or "event" (plays once)
    cls: str  # "stationary" | "locomotion" | "attack" | "other" (what ingest's class rule should find)
    family: str  # the pose family controls.py draws
    speed: float = 0.0  # m/s: horizontal root speed (loops) or its plateau (events)
    move_dir: float = 0.0  # rad from the facing, + = left
    turn: float = 0.0  # rad/s, + = left (turn-in-place loops)
    duty: float = 0.6  # stance fraction of a gait cycle
    move: tuple[float, float] = (0.0, 1.0)  # phase window of an event's root motion
    hit_at: float = 0.0  # phase at which an attack lands
    damage: float = 0.0  # hit points an attack takes when it lands
    params: tuple[tuple[str, float], ...] = field(default=())

    @property
    def composite(self) -> int:
        """bank × 1000 + motion + 1."""
        return self.bank * 1000 + self.motion + 1

    def p(self, key: str, default: float = 0.0) -> float:
        """The variant parameter ``key`` (its family's meaning), or ``default``."""
        return dict(self.params).get(key, default)


class _Table:
    """Builds one species' clips: motion ids are numbered per bank in the order clips are added."""

    def __init__(self):
        self.clips: dict[str, Clip] = {}
        self._next: dict[int, int] = {}

    def add(self, name: str, bank: int, length: int, kind: str, cls: str, family: str, **kw) -> None:
        if name in self.clips:
            raise ValueError(f"clip {name!r} defined twice")
        if not 0.3 * FPS <= length <= 3.0 * FPS:
            raise ValueError(f"clip {name!r}: length {length} frames is outside 0.3–3 s")
        params = tuple(sorted(kw.pop("params", {}).items()))
        motion = self._next.get(bank, 0)
        self._next[bank] = motion + 1
        self.clips[name] = Clip(name, bank, motion, length, kind, cls, family, params=params, **kw)


LEFT, RIGHT, BACK = np.pi / 2, -np.pi / 2, np.pi

# Hunter swing arcs: (hand x, y, z, blade azimuth, blade elevation, twist, lean) at the wind-up and at the strike.
SWINGS = {
    "overhead": ((-0.15, 0.55, -0.05, 0.0, 2.2, 0.3, -0.1), (-0.1, 0.0, 0.55, 0.0, -0.45, -0.25, 0.35)),
    "diag_r": ((-0.45, 0.45, 0.0, -1.2, 1.6, 0.6, -0.05), (0.25, -0.05, 0.45, 0.6, -0.4, -0.5, 0.3)),
    "diag_l": ((0.35, 0.45, 0.05, 1.3, 1.5, -0.5, -0.05), (-0.35, -0.05, 0.45, -0.6, -0.4, 0.5, 0.3)),
    "sweep_rl": ((-0.5, 0.15, -0.05, -1.8, 0.1, 0.8, 0.0), (0.4, 0.1, 0.35, 1.2, 0.05, -0.8, 0.15)),
    "sweep_lr": ((0.45, 0.15, -0.05, 1.8, 0.1, -0.8, 0.0), (-0.45, 0.1, 0.35, -1.2, 0.05, 0.8, 0.15)),
    "rising": ((-0.3, -0.35, 0.1, -0.3, -1.0, 0.3, 0.3), (-0.1, 0.5, 0.4, 0.0, 1.4, -0.2, -0.1)),
    "low": ((-0.45, -0.2, 0.0, -1.6, -0.5, 0.6, 0.35), (0.35, -0.25, 0.4, 1.0, -0.6, -0.6, 0.45)),
    "chop": ((-0.35, 0.6, -0.1, -0.6, 1.9, 0.4, -0.1), (-0.05, 0.15, 0.6, -0.2, 0.0, -0.3, 0.3)),
}
# Attack weights: (length, wind-up end, strike end, recovery start, damage, root step m/s).
WEIGHTS = {
    "light": (30, 0.35, 0.52, 0.7, 30.0, 0.0),
    "medium": (39, 0.42, 0.57, 0.72, 45.0, 1.2),
    "heavy": (51, 0.5, 0.63, 0.8, 70.0, 1.6),
}


def _hunter() -> dict[str, Clip]:
    t = _Table()
    # bank 0: stationary loops
    for i, (n, amp, sway, look, lean) in enumerate(
        ((40, 0.03, 0.0, 0.0, 0.0), (30, 0.04, 0.05, 0.0, 0.0), (45, 0.03, 0.0, 0.35, 0.15), (54, 0.05, 0.08, 0.2, -0.05))
    ):
        params = {"amp": amp, "sway": sway, "look": look, "rest": i % 2, "lean": lean}
        t.add(f"idle_{i}", 0, n, "state", "stationary", "idle", params=params)
    for name, (n, y, z, el) in {
        "guard_high": (27, 0.3, 0.3, 0.75),
        "guard_mid": (24, 0.12, 0.35, 0.5),
        "guard_low": (30, -0.12, 0.35, 0.1),
        "guard_side": (33, 0.2, 0.15, 0.7),
    }.items():
        t.add(name, 0, n, "state", "stationary", "guard", params={"y": y, "z": z, "el": el})
    for name, n, rate, lift in (
        ("turn_left", 12, 1.6, 0.08),
        ("turn_right", 12, -1.6, 0.08),
        ("turn_left_fast", 10, 2.6, 0.14),
        ("turn_right_fast", 10, -2.6, 0.14),
    ):
        t.add(name, 0, n, "state", "stationary", "turn", turn=rate, duty=0.5, params={"lift": lift, "twist": 0.1 * abs(rate)})
    t.add("ready_crouch", 0, 30, "state", "stationary", "guard", params={"y": 0.05, "z": 0.4, "el": 0.3, "lean": 0.25})
    t.add("ready_wide", 0, 36, "state", "stationary", "guard", params={"y": 0.0, "z": 0.2, "el": 0.1, "wide": 0.12})
    # bank 1: locomotion loops
    for name, n, v, duty, lift, lean in (
        ("walk_slow", 36, 1.2, 0.6, 0.1, 0.08),
        ("walk", 32, 1.6, 0.58, 0.12, 0.1),
        ("walk_fast", 28, 2.0, 0.55, 0.13, 0.14),
        ("jog", 22, 3.0, 0.45, 0.17, 0.2),
        ("run", 18, 3.9, 0.4, 0.2, 0.25),
        ("sprint", 16, 4.7, 0.36, 0.24, 0.35),
    ):
        t.add(name, 1, n, "state", "locomotion", "gait", speed=v, duty=duty, params={"lift": lift, "lean": lean})
    for side, d in (("left", LEFT), ("right", RIGHT)):
        for name, n, v, lift, lean in (
            ("strafe_slow", 24, 1.1, 0.08, 0.0),
            ("strafe", 20, 1.6, 0.1, 0.05),
            ("strafe_fast", 16, 2.3, 0.15, 0.15),
        ):
            params = {"lift": lift, "wide": 0.1, "lean": lean}
            t.add(f"{name}_{side}", 1, n, "state", "locomotion", "gait", speed=v, move_dir=d, duty=0.6, params=params)
        t.add(
            f"guard_strafe_{side}",
            1,
            24,
            "state",
            "locomotion",
            "gait",
            speed=1.3,
            move_dir=d,
            params={"lift": 0.09, "wide": 0.1, "guard": 1.0},
        )
        t.add(
            f"advance_{side}",
            1,
            22,
            "state",
            "locomotion",
            "gait",
            speed=1.8,
            move_dir=d / 2,
            params={"lift": 0.12, "wide": 0.05},
        )
        t.add(
            f"retreat_{side}",
            1,
            22,
            "state",
            "locomotion",
            "gait",
            speed=1.3,
            move_dir=BACK - d / 2,
            params={"lift": 0.1, "wide": 0.05},
        )
    t.add("back_walk", 1, 32, "state", "locomotion", "gait", speed=1.0, move_dir=BACK, params={"lift": 0.09, "lean": -0.02})
    t.add("back_jog", 1, 24, "state", "locomotion", "gait", speed=1.6, move_dir=BACK, params={"lift": 0.12, "lean": -0.05})
    # banks 2–3: attacks
    for arc in SWINGS:
        for w, (n, a, b, c, dmg, step) in WEIGHTS.items():
            t.add(
                f"{arc}_{w}",
                2,
                n,
                "event",
                "attack",
                "swing",
                speed=step,
                move=(a, b),
                hit_at=b,
                damage=dmg,
                params={"arc": list(SWINGS).index(arc), "a": a, "b": b, "c": c},
            )
    t.add("thrust", 3, 33, "event", "attack", "thrust", hit_at=0.5, damage=35.0, params={"a": 0.4, "b": 0.5, "c": 0.7})
    t.add(
        "lunge_thrust",
        3,
        42,
        "event",
        "attack",
        "thrust",
        speed=3.0,
        move=(0.3, 0.5),
        hit_at=0.5,
        damage=45.0,
        params={"a": 0.4, "b": 0.5, "c": 0.75},
    )
    t.add(
        "double_thrust",
        3,
        54,
        "event",
        "attack",
        "thrust",
        hit_at=0.62,
        damage=50.0,
        params={"a": 0.25, "b": 0.33, "c": 0.8, "double": 1.0},
    )
    t.add("spin_slash", 3, 48, "event", "attack", "spin", hit_at=0.6, damage=55.0, params={"dir": 1.0})
    t.add("spin_slash_rev", 3, 48, "event", "attack", "spin", hit_at=0.6, damage=55.0, params={"dir": -1.0})
    t.add(
        "jump_slam", 3, 54, "event", "attack", "slam", speed=2.4, move=(0.2, 0.55), hit_at=0.6, damage=80.0, params={"jump": 0.35}
    )
    t.add(
        "hop_slam", 3, 42, "event", "attack", "slam", speed=1.5, move=(0.2, 0.5), hit_at=0.55, damage=60.0, params={"jump": 0.2}
    )
    t.add(
        "charged_overhead",
        3,
        84,
        "event",
        "attack",
        "swing",
        hit_at=0.8,
        damage=110.0,
        params={"arc": 0, "a": 0.6, "b": 0.8, "c": 0.88, "hold": 1.0},
    )
    t.add(
        "charged_sweep",
        3,
        78,
        "event",
        "attack",
        "swing",
        hit_at=0.78,
        damage=100.0,
        params={"arc": 3, "a": 0.6, "b": 0.78, "c": 0.88, "hold": 1.0},
    )
    t.add("double_slash", 3, 57, "event", "attack", "double", hit_at=0.7, damage=60.0, params={"arc": 1, "arc2": 2})
    t.add("triple_combo", 3, 84, "event", "attack", "double", hit_at=0.8, damage=90.0, params={"arc": 3, "arc2": 4, "arc3": 0})
    # bank 4: other events
    for side, d in (("left", LEFT), ("right", RIGHT), ("back", BACK)):
        t.add(f"sidestep_{side}", 4, 18, "event", "other", "dodge", speed=4.5, move_dir=d, move=(0.05, 0.8), params={"dir": d})
    for side, d in (("forward", 0.0), ("left", LEFT), ("right", RIGHT), ("back", BACK)):
        t.add(f"roll_{side}", 4, 27, "event", "other", "roll", speed=4.0, move_dir=d, move=(0.1, 0.8), params={"dir": d})
    for side, d in (("front", 0.0), ("left", LEFT), ("right", RIGHT)):
        t.add(
            f"hit_{side}",
            4,
            21,
            "event",
            "other",
            "hit",
            speed=1.5,
            move_dir=BACK + d,
            move=(0.0, 0.5),
            params={"side": d, "amp": 0.3},
        )
    t.add(
        "hit_heavy", 4, 36, "event", "other", "hit", speed=3.0, move_dir=BACK, move=(0.0, 0.45), params={"side": 0.0, "amp": 0.45}
    )
    t.add(
        "stagger",
        4,
        54,
        "event",
        "other",
        "hit",
        speed=1.2,
        move_dir=BACK,
        move=(0.0, 0.7),
        params={"side": 0.0, "amp": 0.5, "slow": 1.0},
    )
    t.add("block_light", 4, 20, "event", "other", "block", speed=1.0, move_dir=BACK, move=(0.1, 0.5), params={"amp": 0.1})
    t.add("block_heavy", 4, 30, "event", "other", "block", speed=2.2, move_dir=BACK, move=(0.1, 0.5), params={"amp": 0.2})
    t.add("taunt_raise", 4, 60, "event", "other", "taunt", params={"kind": 0})
    t.add("taunt_shout", 4, 54, "event", "other", "taunt", params={"kind": 1})
    t.add("taunt_beckon", 4, 66, "event", "other", "taunt", params={"kind": 2})
    t.add("heal", 4, 75, "event", "other", "taunt", params={"kind": 3})
    t.add("shoulder_roll", 4, 45, "event", "other", "taunt", params={"kind": 4})
    # the weapon-drawn stance every event settles into before the next decision (behaviour.RECOVER)
    t.add("recover", 4, 9, "event", "other", "guard", params={"y": 0.22, "z": 0.18, "el": 0.95, "lean": 0.12})
    return t.clips


def _monster() -> dict[str, Clip]:
    t = _Table()
    # bank 0: stationary loops
    for i, (n, amp, tail, look) in enumerate(((48, 0.04, 0.01, 0.0), (40, 0.05, 0.03, 0.2), (54, 0.03, 0.05, 0.1))):
        t.add(f"idle_{i}", 0, n, "state", "stationary", "idle", params={"amp": amp, "tail": tail, "look": look})
    t.add("alert", 0, 36, "state", "stationary", "idle", params={"amp": 0.02, "tail": 0.02, "look": 0.0, "low": 0.15})
    t.add("crouch", 0, 40, "state", "stationary", "idle", params={"amp": 0.03, "tail": 0.01, "look": 0.0, "low": 0.3})
    for name, rate in (("turn_left", 0.7), ("turn_right", -0.7), ("turn_left_fast", 1.1), ("turn_right_fast", -1.1)):
        t.add(name, 0, 18, "state", "stationary", "turn", turn=rate, duty=0.6)
    # bank 1: locomotion loops
    for name, n, v, duty, lift in (
        ("walk_slow", 40, 1.2, 0.6, 0.22),
        ("walk", 36, 1.8, 0.55, 0.25),
        ("walk_fast", 30, 2.4, 0.5, 0.27),
        ("trot", 24, 3.2, 0.45, 0.28),
        ("run", 20, 4.2, 0.4, 0.3),
    ):
        t.add(name, 1, n, "state", "locomotion", "gait", speed=v, duty=duty, params={"lift": lift})
    for side, d in (("left", LEFT), ("right", RIGHT)):
        t.add(f"stalk_{side}", 1, 36, "state", "locomotion", "gait", speed=1.2, move_dir=d, params={"lift": 0.2, "low": 0.15})
        t.add(
            f"stalk_fast_{side}", 1, 30, "state", "locomotion", "gait", speed=1.8, move_dir=d, params={"lift": 0.22, "low": 0.1}
        )
    t.add("back_walk", 1, 40, "state", "locomotion", "gait", speed=1.0, move_dir=BACK, params={"lift": 0.2})
    t.add("back_walk_fast", 1, 32, "state", "locomotion", "gait", speed=1.5, move_dir=BACK, params={"lift": 0.22})
    # bank 3: attacks
    for name, n, pitch, yaw in (
        ("bite", 36, 0.0, 0.0),
        ("bite_low", 36, -0.25, 0.0),
        ("bite_high", 39, 0.25, 0.0),
        ("bite_left", 36, 0.0, 0.55),
        ("bite_right", 36, 0.0, -0.55),
    ):
        t.add(name, 3, n, "event", "attack", "bite", hit_at=0.42, damage=18.0, params={"pitch": pitch, "yaw": yaw})
    t.add(
        "double_bite",
        3,
        57,
        "event",
        "attack",
        "bite",
        hit_at=0.62,
        damage=28.0,
        params={"pitch": 0.0, "yaw": 0.0, "double": 1.0},
    )
    t.add("tail_swipe_left", 3, 45, "event", "attack", "tail", hit_at=0.5, damage=25.0, params={"dir": 1.0})
    t.add("tail_swipe_right", 3, 45, "event", "attack", "tail", hit_at=0.5, damage=25.0, params={"dir": -1.0})
    t.add("tail_slam", 3, 51, "event", "attack", "tail", hit_at=0.55, damage=32.0, params={"dir": 0.0})
    t.add("claw_left", 3, 33, "event", "attack", "claw", hit_at=0.5, damage=20.0, params={"side": 1.0})
    t.add("claw_right", 3, 33, "event", "attack", "claw", hit_at=0.5, damage=20.0, params={"side": -1.0})
    t.add("stomp", 3, 42, "event", "attack", "claw", hit_at=0.55, damage=24.0, params={"side": 0.0})
    t.add(
        "lunge",
        3,
        45,
        "event",
        "attack",
        "bite",
        speed=5.0,
        move=(0.3, 0.55),
        hit_at=0.5,
        damage=30.0,
        params={"pitch": -0.1, "yaw": 0.0},
    )
    t.add(
        "charge",
        3,
        66,
        "event",
        "attack",
        "bite",
        speed=6.0,
        move=(0.2, 0.6),
        hit_at=0.55,
        damage=40.0,
        params={"pitch": -0.3, "yaw": 0.0, "slow": 1.0},
    )
    t.add("wing_buffet", 3, 48, "event", "attack", "wings", hit_at=0.5, damage=15.0)
    t.add(
        "headbutt", 3, 39, "event", "attack", "bite", hit_at=0.45, damage=22.0, params={"pitch": -0.45, "yaw": 0.0, "closed": 1.0}
    )
    # bank 4: other events
    for name, n, amp in (("roar", 75, 0.4), ("roar_short", 45, 0.3), ("roar_sky", 90, 0.6)):
        t.add(name, 4, n, "event", "other", "roar", params={"amp": amp})
    for side, d in (("front", 0.0), ("left", LEFT), ("right", RIGHT)):
        t.add(
            f"flinch_{side}", 4, 30, "event", "other", "flinch", speed=0.8, move_dir=BACK + d, move=(0.0, 0.5), params={"side": d}
        )
    t.add(
        "stagger", 4, 60, "event", "other", "flinch", speed=1.2, move_dir=BACK, move=(0.0, 0.7), params={"side": 0.0, "slow": 1.0}
    )
    for side, d, v in (("back", BACK, 3.5), ("left", LEFT, 3.0), ("right", RIGHT, 3.0)):
        t.add(f"hop_{side}", 4, 30, "event", "other", "hop", speed=v, move_dir=d, move=(0.15, 0.75), params={"dir": d})
    t.add("shake_head", 4, 45, "event", "other", "shake")
    t.add("sniff", 4, 60, "event", "other", "sniff")
    # the stance every event settles into before the next decision (behaviour.RECOVER)
    t.add("recover", 4, 9, "event", "other", "idle", params={"amp": 0.01, "tail": 0.01, "look": 0.0, "low": 0.1})
    return t.clips


HUNTER_CLIPS: dict[str, Clip] = _hunter()
MONSTER_CLIPS: dict[str, Clip] = _monster()
CLIPS = {"hunter": HUNTER_CLIPS, "monster": MONSTER_CLIPS}


def clip_table(entity: str) -> dict[int, dict]:
    """Composite id → {name, bank, motion, length, kind, class} for one entity type."""
    return {
        c.composite: {"name": c.name, "bank": c.bank, "motion": c.motion, "length": c.length, "kind": c.kind, "class": c.cls}
        for c in CLIPS[entity].values()
    }
