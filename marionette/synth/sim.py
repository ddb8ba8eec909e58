"""The synthetic game's behaviour and its continuous-time motion.

``simulate(seed, index, n_frames, fps)`` plays one recording: the hunter starts on the bridge deck
and runs (or walks) off its east end (even ``index``), or starts in the valley south of the bridge
and runs under it to the north (odd ``index``: the follow camera, lower than the deck, then sees the
valley floor beneath it), then fights the drake, which roams, charges and attacks.
Decisions are taken at frame boundaries; roots are integrated at ``SUBSTEPS`` per frame and stored,
so the motion is a function of continuous time: roots interpolate linearly between the stored
samples, poses are functions of (clip, phase) blended over ``BLEND_FRAMES`` at clip changes.
Everything depends only on (seed, index, n_frames, fps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from marionette.schema import load_rig

from . import terrain as ter
from .clips import CLIPS, Clip
from .poses import HUNTER_PELVIS_H, MONSTER_PELVIS_H, hunter_controls, hunter_skeleton, monster_controls, monster_skeleton

SUBSTEPS = 4
BLEND_FRAMES = 10.0
RADIUS = {"hunter": 0.8, "monster": 3.0}  # keep-out margins around obstacles (m)
YAW_RATE = {"hunter": 1.8, "monster": 0.5, "monster_run": 0.3}  # rad/s while in a loop clip
MIN_SEP = 3.5  # the two roots never get closer (m)
DODGE_SPEED = 4.5  # m/s plateau of the dodge's root speed profile
DECK_Z = (ter.DECK[2] + ter.DECK[3]) / 2
UNDER_EXIT_M = 6.0  # an under-bridge crossing ends this far north of the deck


@dataclass
class Segment:
    start: int  # frame
    clip: str
    length: int  # frames
    dodge_yaw: float = 0.0  # world direction of a dodge's motion


@dataclass
class Track:
    """One entity's simulated motion: roots at SUBSTEPS per frame and its clip segments."""

    xz: np.ndarray  # (F, 2)
    yaw: np.ndarray  # (F,) unwrapped, radians, forward = (sin yaw, 0, cos yaw)
    on_deck: np.ndarray  # (F,) bool
    segments: list[Segment] = field(default_factory=list)


@dataclass
class Plan:
    seed: int
    index: int
    n_frames: int
    fps: float
    tracks: dict[str, Track]
    absent: tuple[int, int]  # monster absent frames [a, b)
    camera_invalid: tuple[int, int]  # camera invalid frames [a, b)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


class _Actor:
    def __init__(self, name: str, x: float, z: float, yaw: float, on_deck: bool):
        self.name, self.x, self.z, self.yaw, self.on_deck = name, x, z, yaw, on_deck
        self.clips = CLIPS[name]
        self.segments: list[Segment] = []
        self.waypoint = (x, z)
        self.crossing = on_deck  # running off the deck (or, with ``under``, through the valley beneath it)
        self.under = False

    @property
    def seg(self) -> Segment:
        return self.segments[-1]

    def clip(self) -> Clip:
        return self.clips[self.seg.clip]

    def start(self, frame: int, name: str, cycles: int = 2, dodge_yaw: float = 0.0) -> None:
        c = self.clips[name]
        if self.segments and self.seg.clip == name and c.kind == "state":
            self.seg.length += c.length  # a loop continues: its phase runs on
            return
        n = c.length * cycles if c.kind == "state" else c.length
        self.segments.append(Segment(frame, name, n, dodge_yaw))


def _push_out(x: float, z: float, rect, margin: float) -> tuple[float, float]:
    x0, x1, z0, z1 = rect[0] - margin, rect[1] + margin, rect[2] - margin, rect[3] + margin
    if not (x0 < x < x1 and z0 < z < z1):
        return x, z
    d = [x - x0, x1 - x, z - z0, z1 - z]
    k = int(np.argmin(d))
    return [(x0, z), (x1, z), (x, z0), (x, z1)][k]


def _avoid_dir(a: _Actor, tx: float, tz: float) -> float:
    """Heading toward (tx, tz), bent around the wall and the deck by a repulsive field."""
    vx, vz = tx - a.x, tz - a.z
    n = np.hypot(vx, vz) + 1e-9
    vx, vz = vx / n, vz / n
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


def _decide_hunter(a: _Actor, m: _Actor, f: int, rng: np.random.Generator) -> None:
    prev = a.seg.clip if a.segments else None
    if a.crossing:
        a.start(f, prev if prev in ("walk", "run") else "run", cycles=1)
        return
    d = np.hypot(m.x - a.x, m.z - a.z)
    m_attacking = m.clips[m.seg.clip].cls == "attack"
    if m_attacking and d < 9.0 and prev != "dodge" and rng.random() < 0.8:
        away = np.arctan2(a.x - m.x, a.z - m.z) + rng.uniform(-0.9, 0.9)
        a.start(f, "dodge", dodge_yaw=float(away))
    elif d > 14.0:
        a.start(f, "run")
    elif d > 5.0:
        a.start(f, "walk")
    elif rng.random() < 0.15 and prev != "idle":
        a.start(f, "idle")
    else:
        options = [c for c in ("attack", "heavy_attack") if c != prev]
        a.start(f, options[int(rng.integers(len(options)))])


def _decide_monster(a: _Actor, h: _Actor, f: int, rng: np.random.Generator) -> None:
    prev = a.seg.clip if a.segments else None
    d = np.hypot(h.x - a.x, h.z - a.z)
    r = rng.random()
    if d < 7.0 and r < 0.7:
        options = [c for c in ("bite", "tail_swipe") if c != prev]
        a.start(f, options[int(rng.integers(len(options)))])
    elif d > 18.0 and r < 0.6:
        a.waypoint = (h.x, h.z)
        a.start(f, "run")
    elif r < 0.1 and prev != "roar":
        a.start(f, "roar")
    elif r < 0.25 and prev != "idle":
        a.start(f, "idle")
    else:
        if rng.random() < 0.5:
            cx, cz = ter.ARENA_CENTER
            a.waypoint = (cx + rng.uniform(-40, 40), cz + rng.uniform(-40, 40))
        else:
            a.waypoint = (h.x, h.z)
        a.start(f, "walk")


def _step(a: _Actor, other: _Actor, target: tuple[float, float], dt: float, f_sub: float) -> None:
    c = a.clip()
    if c.kind == "state":
        want = _avoid_dir(a, *target) if c.speed > 0 else float(np.arctan2(other.x - a.x, other.z - a.z))
        if a.on_deck:
            want = np.pi / 2  # along the deck, toward its east end
        rate = YAW_RATE["monster_run" if a.name == "monster" and c.name == "run" else a.name]
        a.yaw += float(np.clip(_wrap(want - a.yaw), -rate * dt, rate * dt))
        vx, vz = c.speed * np.sin(a.yaw), c.speed * np.cos(a.yaw)
    elif c.name == "dodge":
        u = (f_sub - a.seg.start) / c.length
        v = DODGE_SPEED * min(1.0, u / 0.15, (1 - u) / 0.15) if 0 <= u <= 1 else 0.0
        vx, vz = v * np.sin(a.seg.dodge_yaw), v * np.cos(a.seg.dodge_yaw)
    else:
        vx = vz = 0.0
    # Separation: drop the part of the velocity that closes in on the other entity.
    ox, oz = other.x - a.x, other.z - a.z
    d = np.hypot(ox, oz) + 1e-9
    if d < MIN_SEP:
        closing = (vx * ox + vz * oz) / d
        if closing > 0:
            vx, vz = vx - closing * ox / d, vz - closing * oz / d
    x, z = a.x + vx * dt, a.z + vz * dt
    if a.on_deck:
        z = float(np.clip(z, ter.DECK[2] + 0.6, ter.DECK[3] - 0.6))
    elif not a.under:
        x, z = _push_out(x, z, _DECK_OBSTACLE, RADIUS[a.name])
    x, z = _push_out(x, z, ter.WALL, RADIUS[a.name])
    cx, cz = ter.ARENA_CENTER
    lim = ter.ARENA_HALF - RADIUS[a.name] - 2.0
    a.x, a.z = float(np.clip(x, cx - lim, cx + lim)), float(np.clip(z, cz - lim, cz + lim))
    if a.on_deck and not ter.in_deck(a.x, a.z):
        a.on_deck = False
    if a.crossing and (a.z > ter.DECK[3] + UNDER_EXIT_M if a.under else a.x > ter.DECK[1] + 3.0):
        a.crossing = a.under = False


@lru_cache(maxsize=16)
def simulate(seed: int, index: int, n_frames: int, fps: float = 30.0) -> Plan:
    """Play recording ``index`` of ``seed`` for ``n_frames`` frames: the roots and clip segments."""
    rng = np.random.default_rng([seed, index])
    x0 = ter.DECK[1] - rng.uniform(8.0, 12.0)
    z0 = DECK_Z + rng.uniform(-0.8, 0.8)
    if index % 2:  # under the bridge: up the valley floor from the south
        hunter = _Actor(
            "hunter", ter.VALLEY_X + (x0 - ter.DECK[1] + 10.0), ter.DECK[2] - 12.0 - (z0 - DECK_Z), 0.0, on_deck=False
        )
        hunter.crossing = hunter.under = True
    else:
        hunter = _Actor("hunter", x0, z0, np.pi / 2, on_deck=True)
    mx, mz = ter.DECK[1] + rng.uniform(22.0, 30.0), DECK_Z + rng.uniform(-10.0, 6.0)
    monster = _Actor("monster", mx, mz, float(np.arctan2(hunter.x - mx, hunter.z - mz)), on_deck=False)
    hunter.start(0, "run", cycles=1)
    monster.waypoint = (hunter.x + 12.0, hunter.z)
    monster.start(0, "run")  # the drake charges at the hunter as the recording opens

    F = n_frames * SUBSTEPS + 1
    store = {n: (np.zeros((F, 2)), np.zeros(F), np.zeros(F, bool)) for n in ("hunter", "monster")}
    actors = {"hunter": hunter, "monster": monster}
    dt = 1.0 / (fps * SUBSTEPS)
    for f in range(n_frames):
        for a, o, decide in ((hunter, monster, _decide_hunter), (monster, hunter, _decide_monster)):
            if f >= a.seg.start + a.seg.length:
                decide(a, o, f, rng)
        for s in range(SUBSTEPS):
            i = f * SUBSTEPS + s
            for n, a in actors.items():
                xz, yaw, deck = store[n]
                xz[i], yaw[i], deck[i] = (a.x, a.z), a.yaw, a.on_deck
            for a, o in ((hunter, monster), (monster, hunter)):
                target = a.waypoint
                if a is hunter:
                    target = (o.x, o.z)
                    if a.crossing:
                        target = (a.x, ter.DECK[3] + 2 * UNDER_EXIT_M) if a.under else (ter.DECK[1] + 6.0, DECK_Z)
                _step(a, o, target, dt, f + s / SUBSTEPS)
    for n, a in actors.items():
        xz, yaw, deck = store[n]
        xz[-1], yaw[-1], deck[-1] = (a.x, a.z), a.yaw, a.on_deck
    absent_start = int(rng.uniform(0.35, 0.55) * n_frames)
    cam_start = int(rng.uniform(0.7, 0.85) * n_frames)
    n_abs = min(30, max(1, n_frames // 6))
    tracks = {n: Track(*store[n], segments=list(actors[n].segments)) for n in actors}
    return Plan(seed, index, n_frames, fps, tracks, (absent_start, absent_start + n_abs), (cam_start, cam_start + 4))


# ------------------------------------------------------------------------------------- evaluation


def _layer_height(x: np.ndarray, z: np.ndarray, deck: np.ndarray) -> np.ndarray:
    """Height of the surface an entity walks on: the deck where it is on the deck and over it, else the ground."""
    return np.where(deck & ter.in_deck(x, z), ter.deck_height(x, z), ter.ground_height(x, z))


def roots_at(plan: Plan, entity: str, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World root positions (M, 3), yaws (M,) and on-deck flags (M,) at times (s since frame 0)."""
    tr = plan.tracks[entity]
    s = np.clip(np.asarray(times_s, dtype=np.float64) * plan.fps * SUBSTEPS, 0, len(tr.yaw) - 1)
    i0 = np.minimum(np.floor(s).astype(int), len(tr.yaw) - 2)
    w = s - i0
    xz = tr.xz[i0] * (1 - w)[:, None] + tr.xz[i0 + 1] * w[:, None]
    yaw = tr.yaw[i0] * (1 - w) + tr.yaw[i0 + 1] * w
    deck = tr.on_deck[np.minimum(np.round(s).astype(int), len(tr.yaw) - 1)] & tr.on_deck[i0]
    layer = _layer_height(xz[:, 0], xz[:, 1], deck)
    h = HUNTER_PELVIS_H if entity == "hunter" else MONSTER_PELVIS_H
    return np.stack([xz[:, 0], layer + h, xz[:, 1]], -1), yaw, deck


def clip_at_frames(plan: Plan, entity: str, frames: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Clip name and motion_frame at integer frames."""
    segs = plan.tracks[entity].segments
    starts = np.array([s.start for s in segs])
    k = np.searchsorted(starts, frames, side="right") - 1
    names = [segs[i].clip for i in k]
    lengths = np.array([CLIPS[entity][n].length for n in names])
    return names, (frames - starts[k]) % lengths


def _controls(plan: Plan, entity: str, tf: np.ndarray) -> dict[str, np.ndarray]:
    segs = plan.tracks[entity].segments
    fn = hunter_controls if entity == "hunter" else monster_controls
    clips = CLIPS[entity]
    starts = np.array([s.start for s in segs])
    k = np.searchsorted(starts, tf, side="right") - 1
    out: dict[str, np.ndarray] = {}
    for i in np.unique(k):
        m = k == i
        seg = segs[i]
        cur = fn(clips[seg.clip], tf[m] - seg.start)
        since = tf[m] - seg.start
        if i > 0:
            p = segs[i - 1]
            pc = clips[p.clip]
            pphase = tf[m] - p.start
            if pc.kind == "event":
                pphase = np.minimum(pphase, pc.length)
            prev = fn(pc, pphase)
            w = np.clip(since / BLEND_FRAMES, 0, 1)
            w = w * w * (3 - 2 * w)
            cur = {key: prev[key] + w * (cur[key] - prev[key]) for key in cur}
        for key, v in cur.items():
            out.setdefault(key, np.zeros(len(tf)))[m] = v
    return out


def skeletons_at(plan: Plan, times_s) -> dict[str, np.ndarray]:
    """World source skeletons at times (s): monster (M, 64, 3), hunter (M, 36, 3), weapon (M, 5, 3)."""
    t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
    tf = t * plan.fps
    out = {}
    for entity, rig_name in (("monster", "drake"), ("hunter", "hunter")):
        rig = load_rig(rig_name)
        root, yaw, deck = roots_at(plan, entity, t)
        c, s = np.cos(yaw), np.sin(yaw)

        def surface_local(xl, zl, root=root, c=c, s=s, deck=deck):
            wx = root[:, 0] + c * xl + s * zl
            wz = root[:, 2] - s * xl + c * zl
            return _layer_height(wx, wz, deck) - root[:, 1]

        ctrl = _controls(plan, entity, tf)
        if entity == "hunter":
            local, weapon = hunter_skeleton(rig, ctrl, surface_local)
        else:
            local, weapon = monster_skeleton(rig, ctrl, surface_local), None

        def to_world(p, root=root, c=c, s=s):
            x, y, z = p[..., 0], p[..., 1], p[..., 2]
            return np.stack([c[:, None] * x + s[:, None] * z, y, -s[:, None] * x + c[:, None] * z], -1) + root[:, None]

        out[entity] = to_world(local)
        if weapon is not None:
            out["weapon"] = to_world(weapon)
    return out
