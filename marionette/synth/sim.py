"""One recording of the synthetic game as a plan, and the plan sampled at any time.

``simulate(seed, index, n_frames, fps)`` plays one recording into a ``Plan``: each entity's roots and clip
segments, and the spans where the drake is absent and the camera invalid. What the actors decide and how they
move is ``behaviour``'s. Decisions are taken at frame boundaries, where an attack at its hit frame lands, a clip
ends (or a loop is interrupted), and an event settles into ``RECOVER`` or the actor decides; roots are integrated
at ``SUBSTEPS`` per frame and stored, so the motion is a function of continuous time: roots interpolate linearly
between the stored samples (``roots_at``), poses are functions of (clip, phase) blended over ``BLEND_FRAMES`` at
clip changes (``skeletons_at``). Everything depends only on (seed, index, n_frames, fps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from marionette.schema import load_rig

from . import terrain as ter
from .behaviour import (
    HIT_WINDOW,
    REACH,
    RECOVER,
    UNDER_EXIT_M,
    Actor,
    Segment,
    decide_hunter,
    decide_monster,
    geometry,
    level_of,
    route,
    step,
)
from .clips import CLIPS
from .controls import hunter_controls, monster_controls
from .skeletons import HUNTER_PELVIS_H, MONSTER_PELVIS_H, hunter_skeleton, monster_skeleton

SUBSTEPS = 4
BLEND_FRAMES = 12.0
DECK_Z = (ter.DECK[2] + ter.DECK[3]) / 2


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


def _land_hits(a: Actor, o: Actor, f: int) -> None:
    """When ``a``'s attack reaches its hit frame at ``f`` within reach of ``o``, ``o`` is hit."""
    c = a.clip()
    if c.cls == "attack" and f == a.seg.start + int(c.hit_at * c.length):
        d, _ = geometry(a, o)
        if d < REACH[a.name]:
            o.hit_frame = f
            o.hit_side = geometry(o, a)[1]


def _recovers(a: Actor, f: int) -> bool:
    """Whether ``a``, its clip just over at ``f``, settles into ``RECOVER`` before deciding: after every event but
    the recovery itself, unless a hit has just landed on it (then it decides, and may react) or it is still on its
    opening approach. What follows an event is then the event's to say, as in fighting games."""
    c = a.clip()
    return c.kind == "event" and c.name != RECOVER and not a.crossing and f - a.hit_frame >= HIT_WINDOW


def _interrupted(a: Actor, o: Actor, f: int) -> bool:
    """Whether ``a`` drops the loop it plays at ``f``: hit just now, or (the hunter, out of its approach) the
    other starts an attack within reach. Only a loop that has played a full cycle is dropped, so every
    loop's motion_frame wraps (ingest reads a loop from that)."""
    c = a.clip()
    if c.kind != "state" or a.crossing or f - a.seg.start <= c.length:
        return False
    if a.hit_frame == f:
        return True
    oc = o.clip()
    return a.name == "hunter" and oc.cls == "attack" and o.seg.start == f and geometry(a, o)[0] < REACH[o.name]


@lru_cache(maxsize=16)
def simulate(seed: int, index: int, n_frames: int, fps: float = 30.0) -> Plan:
    """Play recording ``index`` of ``seed`` for ``n_frames`` frames: the roots and clip segments."""
    rng = np.random.default_rng([seed, index])
    x0 = ter.DECK[1] - rng.uniform(7.0, 10.0)
    z0 = DECK_Z + rng.uniform(-0.8, 0.8)
    if index % 2:  # under the bridge: up the valley floor from the south
        hunter = Actor(
            "hunter",
            ter.VALLEY_X + (x0 - ter.DECK[1] + 10.0),
            ter.DECK[2] - 8.0 - (z0 - DECK_Z),
            0.0,
            on_deck=False,
            rng=rng,
            index=index,
        )
        hunter.crossing = hunter.under = True
    else:
        hunter = Actor("hunter", x0, z0, np.pi / 2, on_deck=True, rng=rng, index=index)
    mx, mz = ter.DECK[1] + rng.uniform(22.0, 28.0), DECK_Z + rng.uniform(-1.0, 7.0)
    monster = Actor("monster", mx, mz, float(np.arctan2(hunter.x - mx, hunter.z - mz)), on_deck=False, rng=rng, index=index)
    hunter.start(0, "run", cycles=1)
    monster.waypoint = (hunter.x + 12.0, hunter.z)
    monster.start(0, "run")  # the drake charges at the hunter as the recording opens

    F = n_frames * SUBSTEPS + 1
    store = {n: (np.zeros((F, 2)), np.zeros(F), np.zeros(F, bool)) for n in ("hunter", "monster")}
    actors = {"hunter": hunter, "monster": monster}
    dt = 1.0 / (fps * SUBSTEPS)
    for f in range(n_frames):
        _land_hits(hunter, monster, f)
        _land_hits(monster, hunter, f)
        for a, o, decide in ((hunter, monster, decide_hunter), (monster, hunter, decide_monster)):
            if f >= a.seg.start + a.seg.length or (f > a.seg.start and _interrupted(a, o, f)):
                a.seg.length = f - a.seg.start
                if _recovers(a, f):
                    a.start(f, RECOVER)
                else:
                    decide(a, o, f, rng)
        for s in range(SUBSTEPS):
            i = f * SUBSTEPS + s
            for n, a in actors.items():
                xz, yaw, deck = store[n]
                xz[i], yaw[i], deck[i] = (a.x, a.z), a.yaw, a.on_deck
            for a, o in ((hunter, monster), (monster, hunter)):
                if a is hunter:
                    target = route(a, o.x, o.z, o.level)
                    if a.crossing:
                        target = (a.x, ter.DECK[3] + 2 * UNDER_EXIT_M) if a.under else (ter.DECK[1] + 6.0, DECK_Z)
                else:
                    target = route(a, *a.waypoint, level_of(*a.waypoint))
                step(a, o, target, dt, f + s / SUBSTEPS)
    for n, a in actors.items():
        xz, yaw, deck = store[n]
        xz[-1], yaw[-1], deck[-1] = (a.x, a.z), a.yaw, a.on_deck
    n_abs = min(30, max(1, n_frames // 6))
    absent_start = _gap(actors, int(rng.uniform(0.35, 0.55) * n_frames), n_abs, n_frames)
    cam_start = _gap(actors, int(rng.uniform(0.7, 0.85) * n_frames), 4, n_frames)
    tracks = {n: Track(*store[n], segments=list(actors[n].segments)) for n in actors}
    return Plan(seed, index, n_frames, fps, tracks, (absent_start, absent_start + n_abs), (cam_start, cam_start + 4))


def _gap(actors: dict[str, Actor], start: int, n: int, n_frames: int) -> int:
    """The frame in the 6 s from ``start`` (within the recording's first 90 %) where an invalid span of ``n`` frames,
    which splits the recording into segments, cuts the fewest plays short: events first (a cut attack could lose its
    strike, and ingest classes an action by its played instances), then loops before their first wrap (ingest reads
    a loop from a wrapping motion_frame). The earliest such frame; ``start`` when the range is empty."""
    spans = []  # (first frame, last frame, cost of cutting it)
    for a in actors.values():
        for s in a.segments:
            c = a.clips[s.clip]
            if c.kind == "event":
                spans.append((s.start, s.start + s.length, 10))
            else:
                spans.append((s.start, s.start + min(s.length, c.length + 1), 1))
    best, best_cost = start, None
    for f in range(start, min(start + 180, int(0.9 * n_frames) - n)):
        cost = sum(w for a, b, w in spans if a - 1 <= f + n and f <= b + 1)
        if best_cost is None or cost < best_cost:
            best, best_cost = f, cost
        if cost == 0:
            break
    return best


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

    def pose(i: int, t: np.ndarray) -> dict[str, np.ndarray]:
        """Segment i's controls at times t (at or after its start): its clip (an event holds its last pose once it
        is over), blended over BLEND_FRAMES from the pose segment i − 1 had reached, itself blended when it was
        shorter than the blend (a recovery), so a short segment leaves no jump."""
        seg = segs[i]
        c = clips[seg.clip]
        since = t - seg.start
        cur = fn(c, np.minimum(since, c.length) if c.kind == "event" else since)
        if i == 0 or since.min() >= BLEND_FRAMES:
            return cur
        prev = pose(i - 1, t)
        w = np.clip(since / BLEND_FRAMES, 0, 1)
        w = w * w * (3 - 2 * w)
        return {key: prev[key] + w * (cur[key] - prev[key]) for key in cur}

    out: dict[str, np.ndarray] = {}
    for i in np.unique(k):
        m = k == i
        for key, v in pose(int(i), tf[m]).items():
            out.setdefault(key, np.zeros(len(tf)))[m] = v
    return out


def skeletons_at(plan: Plan, times_s, role=None) -> dict[str, np.ndarray]:
    """World source skeletons at times (s), in the first stage's frame: monster (M, 64, 3), hunter (M, 36, 3),
    weapon (M, 5, 3) — or, for a ``cast.Role``, its species', player's and weapon's."""
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
            if role is not None:
                local, weapon = role.player.derive(local), role.weapon.derive(role.player.derive(weapon))
        else:
            local, weapon = monster_skeleton(rig, ctrl, surface_local), None
            if role is not None and role.species is not None:
                local = role.species.derive(local)

        def to_world(p, root=root, c=c, s=s):
            x, y, z = p[..., 0], p[..., 1], p[..., 2]
            return np.stack([c[:, None] * x + s[:, None] * z, y, -s[:, None] * x + c[:, None] * z], -1) + root[:, None]

        out[entity] = to_world(local)
        if weapon is not None:
            out["weapon"] = to_world(weapon)
    return out
