"""The synthetic game's behaviour: what the hunter and the drake decide, and how they move.

A recording opens with a short approach: the hunter starts on the bridge deck and runs off its east end (even
``index``), or starts in the valley south of the bridge and runs under it to the north (odd ``index``: the follow
camera, lower than the deck, then sees the valley floor beneath it), while the drake charges. Then they fight at
close range: the hunter keeps a preferred distance (3.7–4.8 m), circles the drake with strafes, attacks with a swing
chosen by distance, dodges or blocks the drake's attacks, reacts to hits, backs off and closes in again; the drake
turns in place to face it, attacks (bites, claws, tail, lunges), stalks sideways, hops back, roars, and now and then
walks off to another spot of the fight ground, often up a terrace ramp, where the hunter follows. Variants are
picked by distance, angle and the recording's random generator, so a few minutes of play use most of the clip table.
Every event (an attack, a dodge, a hit reaction, a roar) settles into a short recovery stance (``RECOVER``, a third
of a second) before the next decision, unless a hit has just landed, as fighting games play: what follows an event
is the event's to say, so a model that knows when an event ends can call the change.

An ``Actor`` plays clip ``Segment``s: ``decide_hunter`` and ``decide_monster`` start its next clip, and ``step``
moves its root toward a target (``route``: by a terrace's ramp), bent around the wall, the deck, the ledges and the
other entity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import terrain as ter
from .clips import CLIPS, Clip

RADIUS = {"hunter": 0.8, "monster": 3.0}  # keep-out margins around obstacles and ledges (m)
YAW_RATE = {"hunter": 2.2, "monster": 0.6, "monster_run": 0.35}  # rad/s while moving in a loop clip
STAND_YAW_RATE = {"hunter": 0.0, "monster": 0.0}  # rad/s while standing: both turn with turn clips (feet stay planted)
MIN_SEP = 3.5  # the two roots never get closer (m)
REACH = {"hunter": 6.0, "monster": 7.5}  # an attack lands when the roots are closer at its hit frame (m)
UNDER_EXIT_M = 6.0  # an under-bridge crossing ends this far north of the deck
FIGHT_CENTER = (-944.0, 846.0)  # the drake's spots to fight from lie around here (m)
RECOVER = "recover"  # the short stance every event settles into before the next decision
HIT_WINDOW = 12  # frames after a hit lands in which its target reacts


@dataclass
class Segment:
    start: int  # frame
    clip: str
    length: int  # frames
    move_yaw: float = 0.0  # world heading of an event's root motion


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


class Actor:
    def __init__(self, name: str, x: float, z: float, yaw: float, on_deck: bool, rng: np.random.Generator, index: int):
        self.name, self.x, self.z, self.yaw, self.on_deck = name, x, z, yaw, on_deck
        self.clips = CLIPS[name]
        self.segments: list[Segment] = []
        self.waypoint = (x, z)
        self.crossing = on_deck  # running off the deck (or, with ``under``, through the valley beneath it)
        self.under = False
        self.level = -1  # index of the terrace it stands on, -1 on the ground
        self.hit_frame = -(10**6)  # the last frame an attack of the other landed on it
        self.hit_side = 0.0  # where that attack came from, radians from its facing (+ = left)
        self.pref = float(rng.uniform(3.7, 4.8))  # preferred distance to the other (m)
        self.circle = 1.0 if rng.random() < 0.5 else -1.0  # strafing direction (+ = left)
        self.wandering = False  # walking to a spot of the fight ground (the drake)
        self.wander_start = 0  # frame
        self.climbed = False  # the drake has taken the fight up a terrace
        # clip name → times started; each recording starts with two thirds of the variants "played" (another third
        # fresh in each), so the recordings of a seed favour different variants and a few minutes of play use most of them
        self.plays: dict[str, int] = {n: int((c.composite + index) % 3 != 0) for n, c in self.clips.items()}

    @property
    def seg(self) -> Segment:
        return self.segments[-1]

    def clip(self) -> Clip:
        return self.clips[self.seg.clip]

    def prev(self) -> str | None:
        return self.seg.clip if self.segments else None

    def start(self, frame: int, name: str, cycles: int = 2) -> None:
        c = self.clips[name]
        if self.segments and self.seg.clip == name:
            if c.kind == "event":  # a replayed event would read as a loop (its motion_frame wraps)
                raise ValueError(f"{self.name}: event clip {name!r} started twice in a row at frame {frame}")
            self.seg.length += c.length  # a loop continues: its phase runs on
            return
        n = c.length * cycles if c.kind == "state" else c.length
        self.plays[name] = self.plays.get(name, 0) + 1
        self.segments.append(Segment(frame, name, n, float(self.yaw + c.move_dir)))

    def pick(self, rng: np.random.Generator, names: list[str]) -> str:
        """One of ``names`` at random, the less played ones likelier (weight 1 / (1 + plays)³), never the
        event that just played."""
        prev = self.prev()
        options = [n for n in names if not (n == prev and self.clips[n].kind == "event")]
        w = np.array([1.0 / (1.0 + self.plays.get(n, 0)) ** 3 for n in options])
        return options[int(rng.choice(len(options), p=w / w.sum()))]


def _push_out(x: float, z: float, rect, margin: float) -> tuple[float, float]:
    x0, x1, z0, z1 = rect[0] - margin, rect[1] + margin, rect[2] - margin, rect[3] + margin
    if not (x0 < x < x1 and z0 < z < z1):
        return x, z
    d = [x - x0, x1 - x, z - z0, z1 - z]
    k = int(np.argmin(d))
    return [(x0, z), (x1, z), (x, z0), (x, z1)][k]


def _lane(t: ter.Terrace, margin: float) -> tuple[float, float]:
    return t.x0 + margin, t.x1 - margin


def _ledges(t: ter.Terrace) -> tuple[tuple[float, float, float, float], ...]:
    """A terrace's ledges as segments (x0, z0, x1, z1): its west, east and south sides (the north side is
    the ramp's foot, level with the ground)."""
    return ((t.x0, t.z0, t.x0, t.z1), (t.x1, t.z0, t.x1, t.z1), (t.x0, t.z0, t.x1, t.z0))


def _closest_on(x: float, z: float, seg: tuple[float, float, float, float]) -> tuple[float, float]:
    ax, az, bx, bz = seg
    dx, dz = bx - ax, bz - az
    s = float(np.clip(((x - ax) * dx + (z - az) * dz) / (dx * dx + dz * dz), 0.0, 1.0))
    return ax + s * dx, az + s * dz


def _terraces(a: Actor, x: float, z: float) -> tuple[float, float]:
    """(x, z) kept clear of the terraces' ledges: on a terrace inside its lane and plateau, off it at least
    ``RADIUS`` from every ledge; the ramp's foot is the only way up or down. Updates ``a.level``."""
    m = RADIUS[a.name]
    for i, t in enumerate(ter.TERRACES):
        lo, hi = _lane(t, m)
        if a.level == i:
            x, z = float(np.clip(x, lo, hi)), max(z, t.z0 + m)
            if z > t.z1:
                a.level = -1
            continue
        if t.x0 <= x < t.x1 and z < t.z1 and a.z >= t.z1:
            a.level = i  # stepped onto the ramp's foot
            x = float(np.clip(x, lo, hi))
            continue
        for seg in _ledges(t):
            cx, cz = _closest_on(x, z, seg)
            d = float(np.hypot(x - cx, z - cz))
            if d < m:
                if d < 1e-9:
                    raise ValueError(f"{a.name}: root on a ledge of {t} at ({x:.3f}, {z:.3f})")
                x, z = cx + (x - cx) * m / d, cz + (z - cz) * m / d
    return x, z


def level_of(x: float, z: float) -> int:
    for i, t in enumerate(ter.TERRACES):
        if t.x0 <= x < t.x1 and t.z0 <= z < t.z1:
            return i
    return -1


def route(a: Actor, tx: float, tz: float, level: int) -> tuple[float, float]:
    """The point to head for on the way to (tx, tz) on terrace ``level`` (-1: the ground): a ramp's foot
    when the way there leads on or off a terrace, else the target itself."""
    m = RADIUS[a.name]
    if a.level >= 0 and level != a.level:  # down the ramp first
        t = ter.TERRACES[a.level]
        return float(np.clip(a.x, *_lane(t, m))), t.z1 + m + 1.0
    if level >= 0 and a.level != level:
        t = ter.TERRACES[level]
        lo, hi = _lane(t, m)
        gx = float(np.clip(tx, lo + 0.5, hi - 0.5))
        if lo <= a.x <= hi and t.z1 < a.z < t.z1 + m + 2.0:
            return gx, t.z1 - 2.0  # at the foot: walk up
        return gx, t.z1 + m + 1.0
    return tx, tz


def _avoid_dir(a: Actor, tx: float, tz: float, other: Actor | None = None) -> float:
    """Heading toward (tx, tz), bent around the wall and the deck by a repulsive field (and around ``other``
    when given: walking past it rather than into it)."""
    vx, vz = tx - a.x, tz - a.z
    n = np.hypot(vx, vz) + 1e-9
    vx, vz = vx / n, vz / n
    if other is not None:
        ox, oz = a.x - other.x, a.z - other.z
        d = np.hypot(ox, oz) + 1e-9
        reach = MIN_SEP + 3.0
        if d < reach and (ox * vx + oz * vz) < 0:  # the other stands ahead: go round it on the nearer side
            side = 1.0 if (vx * oz - vz * ox) > 0 else -1.0
            w = 1.5 * (reach - d) / reach
            vx, vz = vx + w * (ox / d + side * oz / d), vz + w * (oz / d - side * ox / d)
    rects = [ter.WALL] + ([] if a.on_deck or a.under else [_DECK_OBSTACLE])
    for r in rects:
        cx, cz = np.clip(a.x, r[0], r[1]), np.clip(a.z, r[2], r[3])
        dx, dz = a.x - cx, a.z - cz
        d = np.hypot(dx, dz) + 1e-9
        reach = RADIUS[a.name] + 6.0
        if d < reach:
            w = 2.0 * (reach - d) / reach
            vx, vz = vx + w * dx / d, vz + w * dz / d
    return float(np.arctan2(vx, vz))


# The part of the deck that stands high above the valley: the drake goes round it; the hunter passes beneath it
# only on an under-bridge crossing.
_DECK_OBSTACLE = (ter.DECK[0] + 2.0, ter.DECK[1] - 2.0, ter.DECK[2], ter.DECK[3])


def geometry(a: Actor, o: Actor) -> tuple[float, float]:
    """(distance m, bearing of ``o`` from ``a``'s facing in radians, + = left)."""
    d = float(np.hypot(o.x - a.x, o.z - a.z))
    return d, float(_wrap(np.arctan2(o.x - a.x, o.z - a.z) - a.yaw))


def _names(a: Actor, *prefixes: str, cls: str | None = None) -> list[str]:
    return [n for n, c in a.clips.items() if n.startswith(prefixes) and (cls is None or c.cls == cls)]


def _settled(a: Actor) -> bool:
    """Whether ``a`` may react now: its last clip was not a reaction of its own (a hit, a dodge, ...) unless it
    was the recovery after one."""
    prev = a.prev()
    return a.clips[prev].cls != "other" or prev == RECOVER


def _side(angle: float) -> str:
    """The hit-reaction side of an attack from ``angle`` (radians from the facing, + = left)."""
    return "front" if abs(angle) < 0.8 else ("left" if angle > 0 else "right")


def decide_hunter(a: Actor, m: Actor, f: int, rng: np.random.Generator) -> None:
    prev = a.prev()
    if a.crossing:
        a.start(f, prev if prev in ("walk", "run", "jog") else "run", cycles=1)
        return
    d, ang = geometry(a, m)
    mc = m.clip()
    m_attacking = mc.cls == "attack" and f < m.seg.start + mc.hit_at * mc.length
    r = rng.random()
    if f - a.hit_frame < HIT_WINDOW and _settled(a):
        side = "left" if a.hit_side > 0 else "right"
        a.start(
            f,
            a.pick(
                rng,
                ["hit_heavy", "stagger"]
                if r < 0.25
                else ["hit_front", f"hit_{side}"]
                if abs(a.hit_side) < 0.8
                else [f"hit_{side}"],
            ),
        )
    elif m_attacking and d < REACH["monster"] + 0.5 and _settled(a) and r < 0.75:
        if r < 0.2:
            a.start(f, a.pick(rng, ["block_light", "block_heavy"]))
        else:
            away = "back" if abs(ang) < 0.6 and rng.random() < 0.4 else ("left" if rng.random() < 0.5 else "right")
            a.start(f, a.pick(rng, [f"sidestep_{away}", f"roll_{away}"] + (["roll_forward"] if d > 5.0 else [])))
    elif d > 13.0:
        a.start(f, a.pick(rng, ["run", "sprint"]))
    elif d > a.pref + 2.5:
        if d > a.pref + 5.0:
            a.start(f, a.pick(rng, ["jog", "run", "sprint"]))
        elif r < 0.3:  # closing the gap with a lunge, a leap or a roll
            a.start(f, a.pick(rng, ["lunge_thrust", "jump_slam", "hop_slam", "roll_forward", "charged_overhead"]))
        else:
            a.start(f, a.pick(rng, ["walk_fast", "jog", "walk"] + [f"advance_{s}" for s in ("left", "right")]))
    elif abs(ang) > 0.5:
        a.start(f, f"turn_{'left' if ang > 0 else 'right'}{'_fast' if abs(ang) > 1.2 else ''}", cycles=2)
    elif d < MIN_SEP + 0.4 and r < 0.6:
        a.start(f, a.pick(rng, ["back_walk", "back_jog", "retreat_left", "retreat_right", "sidestep_back", "roll_back"]))
    elif r < 0.5:
        if d > a.pref + 0.8:
            options = ["lunge_thrust", "jump_slam", "hop_slam", "thrust"]
        else:
            options = _names(a, "overhead", "diag", "sweep", "rising", "low", "chop")
            options += ["thrust", "double_thrust", "spin_slash", "spin_slash_rev", "double_slash", "triple_combo"]
            if rng.random() < 0.15:
                options = ["charged_overhead", "charged_sweep"]
        a.start(f, a.pick(rng, options))
    elif r < 0.74:
        if rng.random() < 0.15:
            a.circle = -a.circle
        side = "left" if a.circle > 0 else "right"
        a.start(f, a.pick(rng, [f"strafe_slow_{side}", f"strafe_{side}", f"strafe_fast_{side}", f"guard_strafe_{side}"]))
    elif r < 0.82:
        if d < a.pref:
            a.start(f, a.pick(rng, ["back_walk", "retreat_left", "retreat_right"]))
        else:
            a.start(f, a.pick(rng, ["walk_slow", "advance_left", "advance_right"]))
    elif r < 0.91:
        a.start(f, a.pick(rng, _names(a, "guard_", cls="stationary") + ["ready_crouch", "ready_wide"]))
    elif r < 0.94:
        a.start(f, a.pick(rng, _names(a, "idle_")))
    else:
        a.start(f, a.pick(rng, ["taunt_raise", "taunt_shout", "taunt_beckon", "heal", "shoulder_roll"]))


def _fight_spot(a: Actor, rng: np.random.Generator, terrace: bool = False) -> tuple[float, float]:
    """A spot of the fight ground for the drake to walk to: up a terrace (always when ``terrace``, else often),
    or near the fight's centre."""
    m = RADIUS[a.name]
    if terrace or rng.random() < 0.65:
        near = int(np.argmin([np.hypot((t.x0 + t.x1) / 2 - a.x, t.z1 - a.z) for t in ter.TERRACES]))
        t = ter.TERRACES[near if rng.random() < 0.8 else int(rng.integers(len(ter.TERRACES)))]
        return float(rng.uniform(*_lane(t, m + 0.5))), float(rng.uniform(t.z0 + m + 0.5, t.z1 - 1.0))
    cx, cz = FIGHT_CENTER
    return cx + float(rng.uniform(-12, 12)), cz + float(rng.uniform(-6, 8))


def _walk_to(a: Actor, f: int, rng: np.random.Generator, gait: str | None = None) -> None:
    """Head for ``a.waypoint``: turn in place toward the way there first when it lies off to a side, else walk
    (``gait`` when given, a walk picked by the distance otherwise)."""
    tx, tz = route(a, *a.waypoint, level_of(*a.waypoint))
    bearing = float(_wrap(np.arctan2(tx - a.x, tz - a.z) - a.yaw))
    if abs(bearing) > 0.9:
        a.start(f, f"turn_{'left' if bearing > 0 else 'right'}_fast", cycles=2)
    else:
        far = np.hypot(a.waypoint[0] - a.x, a.waypoint[1] - a.z) > 10.0
        a.start(f, gait or a.pick(rng, ["walk_fast", "trot"] if far else ["walk_slow", "walk", "walk_fast"]))


def decide_monster(a: Actor, h: Actor, f: int, rng: np.random.Generator) -> None:
    prev = a.prev()
    d, ang = geometry(a, h)
    r = rng.random()
    wandering, a.wandering = a.wandering, False
    if f - a.hit_frame < HIT_WINDOW and _settled(a) and r < 0.5:
        a.start(f, a.pick(rng, ["stagger"] if r < 0.1 else [f"flinch_{_side(a.hit_side)}"]))
    elif wandering and np.hypot(a.waypoint[0] - a.x, a.waypoint[1] - a.z) > 2.0 and f - a.wander_start < 240:
        a.wandering = True
        _walk_to(a, f, rng, prev if a.clips[prev].cls == "locomotion" else None)  # on the way to a new spot
    elif not a.climbed and not h.crossing and d < 9.0 and r < 0.6:
        # once the fight has begun, the drake takes it up a terrace
        a.waypoint, a.wandering, a.wander_start, a.climbed = _fight_spot(a, rng, terrace=True), True, f, True
        _walk_to(a, f, rng)
    elif d > 14.0 and r < 0.7:
        a.waypoint = (h.x, h.z)
        a.start(f, a.pick(rng, ["run", "trot"]))
    elif d > 9.0:
        a.waypoint = (h.x, h.z)
        if r < 0.8:
            a.start(f, a.pick(rng, ["walk", "walk_fast", "trot"]))
        else:
            a.start(f, a.pick(rng, ["lunge", "charge"] if abs(ang) < 0.3 else ["roar_short", "roar"]))
    elif abs(ang) > 0.5:
        a.start(f, f"turn_{'left' if ang > 0 else 'right'}{'_fast' if abs(ang) > 1.2 else ''}", cycles=2)
    elif r < 0.45 and d < 8.0:
        if d > 6.5:
            options = ["lunge", "charge"]
        elif d < 4.5:
            options = [
                "claw_left",
                "claw_right",
                "stomp",
                "bite_low",
                "headbutt",
                "wing_buffet",
                "tail_swipe_left",
                "tail_swipe_right",
            ]
        else:
            options = _names(a, "bite") + ["double_bite", "headbutt", "tail_slam", "claw_left", "claw_right", "wing_buffet"]
        a.start(f, a.pick(rng, options))
    elif r < 0.54:
        a.start(f, a.pick(rng, ["stalk_left", "stalk_right", "stalk_fast_left", "stalk_fast_right"]))
    elif r < 0.62:
        a.start(f, a.pick(rng, ["back_walk", "back_walk_fast", "hop_back", "hop_left", "hop_right"]))
    elif r < 0.7:
        a.waypoint, a.wandering, a.wander_start = _fight_spot(a, rng), True, f
        _walk_to(a, f, rng)
    elif r < 0.83:
        a.start(f, a.pick(rng, ["roar", "roar_short", "roar_sky"]))
    elif r < 0.88:
        a.start(f, a.pick(rng, ["shake_head", "sniff"]))
    else:
        a.start(f, a.pick(rng, _names(a, "idle_") + ["alert", "crouch"]))


def _event_speed(c: Clip, u: float) -> float:
    """An event's root speed (m/s) at phase u: a trapezoid over its ``move`` window."""
    u0, u1 = c.move
    r = (u - u0) / (u1 - u0)
    return c.speed * min(1.0, r / 0.2, (1 - r) / 0.2) if 0 <= r <= 1 else 0.0


def step(a: Actor, other: Actor, target: tuple[float, float], dt: float, f_sub: float) -> None:
    c = a.clip()
    face = float(np.arctan2(other.x - a.x, other.z - a.z))
    if c.kind == "state":
        if c.turn:
            a.yaw += c.turn * dt  # a turning step turns at the clip's own rate
            want = None
        elif c.speed > 0 and c.move_dir == 0.0:
            going_elsewhere = np.hypot(target[0] - other.x, target[1] - other.z) > 2.0
            want = _avoid_dir(a, *target, other if going_elsewhere else None)
        else:
            want = face  # standing, strafing or backing off: facing the other
        if a.on_deck:
            want = np.pi / 2  # along the deck, toward its east end
        if want is not None:
            rate = (
                YAW_RATE["monster_run" if a.name == "monster" and c.speed > 3.0 else a.name]
                if c.speed > 0
                else STAND_YAW_RATE[a.name]
            )
            a.yaw += float(np.clip(_wrap(want - a.yaw), -rate * dt, rate * dt))
        heading = a.yaw + c.move_dir
        if c.speed > 0 and c.move_dir != 0.0:
            heading = _avoid_dir(a, a.x + np.sin(heading), a.z + np.cos(heading))
        vx, vz = c.speed * np.sin(heading), c.speed * np.cos(heading)
        if c.speed > 0 and abs(np.sin(c.move_dir)) > 0.9:  # circling: hold the preferred distance
            d = np.hypot(other.x - a.x, other.z - a.z) + 1e-9
            k = float(np.clip(0.8 * (d - a.pref), -0.8, 0.8))
            vx, vz = vx + k * (other.x - a.x) / d, vz + k * (other.z - a.z) / d
    else:
        v = _event_speed(c, (f_sub - a.seg.start) / c.length)
        vx, vz = v * np.sin(a.seg.move_yaw), v * np.cos(a.seg.move_yaw)
    # Separation: drop the part of the velocity that closes in on the other entity.
    ox, oz = other.x - a.x, other.z - a.z
    d = np.hypot(ox, oz) + 1e-9
    if d < MIN_SEP:
        closing = (vx * ox + vz * oz) / d
        if closing > 0:
            vx, vz = vx - closing * ox / d, vz - closing * oz / d
    x, z = a.x + vx * dt, a.z + vz * dt
    ox, oz = x - other.x, z - other.z
    d = np.hypot(ox, oz) + 1e-9
    if d < MIN_SEP:  # pushed (by a ledge, a wall) or sliding into the other: held at MIN_SEP
        x, z = other.x + ox * MIN_SEP / d, other.z + oz * MIN_SEP / d
    if a.on_deck:
        z = float(np.clip(z, ter.DECK[2] + 0.6, ter.DECK[3] - 0.6))
    elif not a.under:
        x, z = _push_out(x, z, _DECK_OBSTACLE, RADIUS[a.name])
    x, z = _push_out(x, z, ter.WALL, RADIUS[a.name])
    x, z = _terraces(a, x, z)
    cx, cz = ter.ARENA_CENTER
    lim = ter.ARENA_HALF - RADIUS[a.name] - 2.0
    a.x, a.z = float(np.clip(x, cx - lim, cx + lim)), float(np.clip(z, cz - lim, cz + lim))
    if a.on_deck and not ter.in_deck(a.x, a.z):
        a.on_deck = False
    if a.crossing and (a.z > ter.DECK[3] + UNDER_EXIT_M if a.under else a.x > ter.DECK[1] + 3.0):
        a.crossing = a.under = False
