"""Procedural poses as control curves: per clip a few curves over the clip's phase.

A pose is a dict of control arrays, each (M,) over M time samples, in the entity's root frame (root (pelvis) at
the origin, +Z forward, +Y up, +X to the character's left): the feet's offsets, lifts and turns, the lean, twist
and look, the hands and the blade for the hunter; the neck, head, jaw, tail, wings and crouch for the drake. Loops
are periodic curves (``gait`` for the feet), events key poses joined by smoothsteps that start and end at the
neutral pose; clips are blended by blending controls, and ``skeletons`` turns controls into joints.
"""

from __future__ import annotations

import numpy as np

from .clips import SWINGS, Clip


def smooth(u: np.ndarray) -> np.ndarray:
    """Smoothstep on [0, 1], clamped."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def _ramp(u, a, b) -> np.ndarray:
    return smooth((u - a) / (b - a))


def _keys(c: dict[str, np.ndarray], u: np.ndarray, keys: list[tuple[float, dict[str, float]]]) -> None:
    """Key-framed controls in place: at phase u_k the controls named in key k take its values (the rest
    their ``c`` values), smoothstep between consecutive keys; keys run from u = 0 to u = 1."""
    base = {k: v.copy() for k, v in c.items()}
    names = sorted({n for _, kv in keys for n in kv})
    for (u0, k0), (u1, k1) in zip(keys[:-1], keys[1:]):
        m = (u >= u0) & (u <= u1) if u1 >= 1.0 else (u >= u0) & (u < u1)
        if not m.any():
            continue
        w = smooth((u[m] - u0) / max(u1 - u0, 1e-9))
        for n in names:
            a = k0.get(n, base[n][m])
            b = k1.get(n, base[n][m])
            c[n][m] = a + w * (np.asarray(b) - a)
    for n in names:  # past the last key (an event held after its end) the last key's value
        last = keys[-1][1].get(n)
        if last is not None:
            c[n][u > 1.0] = last


def gait(
    phase: np.ndarray, clip: Clip, offsets: tuple[float, ...], lift_m: float, rate: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per foot (offset along the motion, lift) of a gait cycle: stance glides back at ``rate`` (m/s, or rad/s
    for a turn: the offset is then an angle), swing returns."""
    T = clip.length / 30.0
    d = clip.duty
    stride = rate * d * T
    out = []
    for off in offsets:
        p = np.mod(phase / clip.length + off, 1.0)
        s_st = p / d
        s_sw = (p - d) / (1 - d)
        # Swing: mostly constant speed with a little easing (peak 1.17× the mean), so that a
        # swinging foot stays well under 5 m/s in the root frame.
        ease = 0.7 * s_sw + 0.3 * (1 - np.cos(np.pi * s_sw)) / 2
        dz = np.where(p < d, stride / 2 - stride * s_st, -stride / 2 + stride * ease)
        lift = np.where(p < d, 0.0, lift_m * np.sin(np.pi * np.clip(s_sw, 0, 1)))
        out.append((dz, lift))
    return out


def _feet(
    c: dict[str, np.ndarray], clip: Clip, phase: np.ndarray, feet: tuple[str, ...], offsets: tuple[float, ...], lift_m: float
) -> None:
    """Gait controls of ``feet``: translation along the clip's move_dir, or rotation for a turn clip."""
    if clip.turn:
        for f, (a, lift) in zip(feet, gait(phase, clip, offsets, lift_m, clip.turn)):
            c[f"foot_{f}_rot"], c[f"foot_{f}_lift"] = a, lift
        return
    cs, sn = np.cos(clip.move_dir), np.sin(clip.move_dir)
    for f, (off, lift) in zip(feet, gait(phase, clip, offsets, lift_m, clip.speed)):
        c[f"foot_{f}_dz"], c[f"foot_{f}_dx"], c[f"foot_{f}_lift"] = (
            c[f"foot_{f}_dz"] + cs * off,
            c[f"foot_{f}_dx"] + sn * off,
            lift,
        )


# ----------------------------------------------------------------------------------------------- hunter

HUNTER_NEUTRAL = {
    "foot_l_dz": 0.05,
    "foot_l_dx": 0.0,
    "foot_l_lift": 0.0,
    "foot_l_rot": 0.0,
    "foot_r_dz": -0.05,
    "foot_r_dx": 0.0,
    "foot_r_lift": 0.0,
    "foot_r_rot": 0.0,
    "lean": 0.05,
    "twist": 0.0,
    "look": 0.0,
    "hand_r_x": -0.28,
    "hand_r_y": 0.0,
    "hand_r_z": 0.3,
    "blade_az": 0.0,
    "blade_el": 0.35,
    "hand_l_x": 0.25,
    "hand_l_y": -0.05,
    "hand_l_z": 0.05,
}
_SWING_KEYS = ("hand_r_x", "hand_r_y", "hand_r_z", "blade_az", "blade_el", "twist", "lean")


def _grip(p: tuple[float, ...]) -> dict[str, float]:
    """A two-handed sword pose: the swing controls plus the left hand beside the right."""
    k = dict(zip(_SWING_KEYS, p))
    return {**k, "hand_l_x": k["hand_r_x"] + 0.08, "hand_l_y": k["hand_r_y"] - 0.06, "hand_l_z": k["hand_r_z"] - 0.02}


def _guard(y: float, z: float, el: float) -> dict[str, float]:
    return _grip((-0.12, y, z, 0.0, el, 0.05, 0.1))


def hunter_controls(clip: Clip, phase: np.ndarray) -> dict[str, np.ndarray]:
    """Control curves of a hunter clip at ``phase`` (frames since the clip started, continuous)."""
    c = {k: np.full(phase.shape, v, dtype=np.float64) for k, v in HUNTER_NEUTRAL.items()}
    u = phase / clip.length
    cyc = np.sin(2 * np.pi * u)
    fam, p = clip.family, clip.p
    arcs = list(SWINGS.values())
    if fam == "idle":
        c["lean"] += p("lean") + p("amp") * cyc
        c["hand_l_z"] += 0.02 * cyc
        c["twist"] += p("sway") * np.sin(2 * np.pi * u + 1.0)
        c["look"] += p("look") * np.sin(2 * np.pi * u)
        if p("rest"):
            c["hand_r_y"] -= 0.12
            c["blade_el"] -= 0.3
    elif fam == "guard":
        for k, v in _guard(p("y"), p("z"), p("el")).items():
            c[k] += v - c[k]
        c["lean"] += p("lean") + 0.02 * cyc
        c["hand_r_y"] += 0.015 * cyc
        c["foot_l_dx"] += p("wide")
        c["foot_r_dx"] -= p("wide")
    elif fam == "turn":
        _feet(c, clip, phase, ("l", "r"), (0.0, 0.5), p("lift"))
        c["twist"] += p("twist") * np.sign(clip.turn)
        c["look"] += 0.2 * np.sign(clip.turn)
    elif fam == "gait":
        if p("guard"):
            for k, v in _guard(0.15, 0.35, 0.6).items():
                c[k] += v - c[k]
        c["foot_l_dx"] += p("wide")
        c["foot_r_dx"] -= p("wide")
        _feet(c, clip, phase, ("l", "r"), (0.0, 0.5), p("lift"))
        c["lean"] += p("lean")
        if not p("guard"):
            c["hand_l_z"] += -0.6 * c["foot_l_dz"] * np.cos(clip.move_dir)
        c["twist"] += 0.3 * (c["foot_l_dz"] - 0.05) * np.cos(clip.move_dir)
    elif fam == "swing":
        wind, strike = (_grip(x) for x in arcs[int(p("arc"))])
        a, b, k = p("a"), p("b"), p("c")
        held = [(0.35, wind), (a, wind)] if p("hold") else [(a, wind)]
        _keys(c, u, [(0.0, {}), *held, (b, strike), (k, strike), (1.0, dict(HUNTER_NEUTRAL))])
    elif fam == "double":
        seq = [arcs[int(p(n))] for n in ("arc", "arc2", "arc3") if p(n, -1.0) >= 0]
        keys: list[tuple[float, dict]] = [(0.0, {})]
        span = 0.85 / len(seq)
        for i, (w, s_) in enumerate(seq):
            u0 = 0.05 + i * span
            keys += [(u0 + 0.45 * span, _grip(w)), (u0 + 0.7 * span, _grip(s_))]
        keys += [(0.9, keys[-1][1]), (1.0, dict(HUNTER_NEUTRAL))]
        _keys(c, u, keys)
    elif fam == "thrust":
        pull = _grip((-0.25, 0.2, -0.35, 0.0, 0.1, 0.3, -0.05))
        stab = _grip((0.0, 0.3, 0.62, 0.0, 0.05, -0.2, 0.3))
        a, b, k = p("a"), p("b"), p("c")
        keys = [(0.0, {}), (a, pull), (b, stab)]
        if p("double"):
            keys += [(b + 0.12, pull), (b + 0.2, stab)]
        _keys(c, u, [*keys, (k, stab), (1.0, dict(HUNTER_NEUTRAL))])
    elif fam == "spin":
        d = p("dir")
        w = _ramp(u, 0.45, 0.7)
        az = d * (-1.9 + 2 * np.pi * w)
        wind = smooth(u / 0.4) * (1 - _ramp(u, 0.75, 1.0))
        c["blade_az"] = wind * az
        c["blade_el"] = c["blade_el"] + wind * (0.05 - c["blade_el"])
        c["hand_r_x"] = c["hand_r_x"] + wind * (0.45 * np.sin(az) - c["hand_r_x"])
        c["hand_r_z"] = c["hand_r_z"] + wind * (0.45 * np.cos(az) - c["hand_r_z"])
        c["hand_r_y"] = c["hand_r_y"] + wind * 0.2
        c["twist"] += wind * 0.5 * np.sin(az)
        for ax in "xyz":
            c[f"hand_l_{ax}"] = c[f"hand_l_{ax}"] + wind * (c[f"hand_r_{ax}"] - c[f"hand_l_{ax}"])
    elif fam == "slam":
        up = _grip((-0.15, 0.6, -0.05, 0.0, 2.3, 0.2, -0.15))
        down = _grip((-0.1, -0.1, 0.55, 0.0, -0.6, -0.2, 0.45))
        jump = {"foot_l_lift": p("jump"), "foot_r_lift": p("jump")}
        _keys(
            c,
            u,
            [
                (0.0, {}),
                (0.3, {**up, **jump}),
                (0.55, {**down, "foot_l_lift": 0.0, "foot_r_lift": 0.0}),
                (0.75, down),
                (1.0, dict(HUNTER_NEUTRAL)),
            ],
        )
    elif fam == "dodge":
        d = p("dir")
        pose = {"lean": 0.05 + 0.25 * np.cos(d), "twist": 0.25 * np.sin(d), "foot_l_lift": 0.12, "foot_r_lift": 0.12}
        _keys(c, u, [(0.0, {}), (0.4, pose), (1.0, dict(HUNTER_NEUTRAL))])
    elif fam == "roll":
        d = p("dir")
        tuck = {
            "lean": 0.75 if abs(d) < 3.0 else -0.45,
            "twist": 0.3 * np.sin(d),
            "foot_l_lift": 0.3,
            "foot_r_lift": 0.3,
            "foot_l_dz": 0.2,
            "foot_r_dz": 0.1,
            "hand_r_y": -0.1,
            "hand_r_z": 0.2,
        }
        _keys(c, u, [(0.0, {}), (0.3, tuck), (0.6, tuck), (1.0, dict(HUNTER_NEUTRAL))])
    elif fam == "hit":
        side = p("side")
        recoil = {
            "lean": 0.05 - p("amp") * np.cos(side),
            "twist": 0.4 * np.sin(side),
            "look": -0.3 * np.sin(side),
            "hand_l_y": 0.1,
        }
        hit_u = 0.35 if p("slow") else 0.22
        _keys(c, u, [(0.0, {}), (hit_u, recoil), (0.6, recoil), (1.0, dict(HUNTER_NEUTRAL))])
    elif fam == "block":
        g = _guard(0.15, 0.35, 0.6)
        pushed = {**g, "lean": -p("amp"), "hand_r_z": 0.25}
        _keys(c, u, [(0.0, {}), (0.35, g), (0.55, pushed), (0.75, g), (1.0, dict(HUNTER_NEUTRAL))])
    elif fam == "taunt":
        kind = int(p("kind"))
        if kind == 0:  # the blade raised overhead
            pose = {"hand_r_x": -0.2, "hand_r_y": 0.35, "hand_r_z": 0.2, "blade_el": 1.0, "lean": -0.1}
        elif kind == 1:  # a shout, arms out
            pose = {"lean": -0.2, "hand_l_x": 0.5, "hand_l_y": 0.2, "hand_l_z": 0.1, "look": 0.0}
        elif kind == 2:  # beckoning with the free hand
            pose = {"hand_l_x": 0.3, "hand_l_y": 0.3, "hand_l_z": 0.4, "twist": -0.15}
        elif kind == 3:  # drinking a potion
            pose = {"hand_l_x": 0.05, "hand_l_y": 0.55, "hand_l_z": 0.15, "lean": -0.12}
        else:  # rolling the shoulders
            pose = {"twist": 0.3, "lean": 0.12}
        _keys(c, u, [(0.0, {}), (0.35, pose), (0.7, pose), (1.0, dict(HUNTER_NEUTRAL))])
        if kind == 2:
            c["hand_l_z"] += 0.08 * np.sin(6 * np.pi * u) * _ramp(u, 0.3, 0.4) * (1 - _ramp(u, 0.65, 0.7))
        if kind == 4:
            c["twist"] -= 0.3 * np.sin(2 * np.pi * u) * np.sin(np.pi * u)
    else:
        raise ValueError(f"hunter clip {clip.name!r}: unknown pose family {fam!r}")
    return c


# ----------------------------------------------------------------------------------------------- drake

MONSTER_NEUTRAL = {
    **{f"foot_{f}_{k}": 0.0 for f in ("fl", "fr", "hl", "hr") for k in ("dz", "dx", "lift", "rot")},
    "neck": 0.0,
    "neck_yaw": 0.0,
    "head": 0.0,
    "jaw": 0.05,
    "tail_yaw": 0.0,
    "tail_pitch": 0.0,
    "wings": 0.0,
    "low": 0.0,
}
_FEET = ("fl", "fr", "hl", "hr")
_END = dict(MONSTER_NEUTRAL)


def monster_controls(clip: Clip, phase: np.ndarray) -> dict[str, np.ndarray]:
    """Control curves of a drake clip at ``phase`` (frames since the clip started, continuous)."""
    c = {k: np.full(phase.shape, v, dtype=np.float64) for k, v in MONSTER_NEUTRAL.items()}
    u = phase / clip.length
    cyc = np.sin(2 * np.pi * u)
    fam, p = clip.family, clip.p
    if fam == "idle":
        c["neck"] += p("amp") * cyc
        c["tail_yaw"] += p("tail") * np.sin(2 * np.pi * u + 0.7)
        c["neck_yaw"] += p("look") * np.sin(2 * np.pi * u)
        c["low"] += p("low")
        c["neck"] -= 0.5 * p("low")
    elif fam == "turn":
        _feet(c, clip, phase, _FEET, (0.0, 0.5, 0.25, 0.75), 0.2)
        c["neck_yaw"] += 0.15 * np.sign(clip.turn)
    elif fam == "gait":
        _feet(c, clip, phase, _FEET, (0.0, 0.5, 0.25, 0.75), p("lift"))
        c["tail_yaw"] += 0.015 * cyc
        c["neck"] += -0.1 if clip.speed > 3.0 else 0.0
        c["low"] += p("low")
    elif fam == "bite":
        pitch, yaw = p("pitch"), p("yaw")
        rear = {"neck": 0.4 + pitch, "head": 0.2, "jaw": 0.05 if p("closed") else 0.65, "neck_yaw": 0.6 * yaw}
        strike = {"neck": -0.55 + pitch, "head": -0.3 + 0.5 * pitch, "jaw": 0.15, "neck_yaw": yaw}
        if p("double"):
            keys = [(0.0, {}), (0.3, rear), (0.38, strike), (0.52, rear), (0.62, strike), (0.72, strike), (1.0, _END)]
        elif p("slow"):  # a charge: head lowered through the run, the bite at its end
            keys = [
                (0.0, {}),
                (0.25, {**rear, "neck": 0.1 + pitch}),
                (0.45, {**rear, "neck": pitch}),
                (0.55, strike),
                (0.7, strike),
                (1.0, _END),
            ]
        else:
            a = clip.hit_at
            keys = [(0.0, {}), (a - 0.1, rear), (a, strike), (a + 0.2, strike), (1.0, _END)]
        _keys(c, u, keys)
    elif fam == "tail":
        d = p("dir")
        if d:
            wind, swipe = {"tail_yaw": 0.12 * d, "tail_pitch": 0.05}, {"tail_yaw": -0.16 * d, "tail_pitch": 0.05}
        else:
            wind, swipe = {"tail_pitch": 0.35, "neck": 0.1}, {"tail_pitch": -0.12, "neck": -0.05}
        _keys(c, u, [(0.0, {}), (0.4, wind), (0.5 if d else 0.55, swipe), (0.65, swipe), (1.0, _END)])
    elif fam == "claw":
        side = p("side")
        if side:  # one front foot swipes across
            f = "fl" if side > 0 else "fr"
            raised = {f"foot_{f}_lift": 0.7, f"foot_{f}_dz": 0.3, f"foot_{f}_dx": 0.35 * side, "neck_yaw": 0.2 * side}
            swiped = {f"foot_{f}_lift": 0.2, f"foot_{f}_dz": 0.8, f"foot_{f}_dx": -0.6 * side, "neck_yaw": -0.2 * side}
            # the paw swings back through the air (a paw held still off the ground would read as a planted foot)
            after = {**swiped, f"foot_{f}_lift": 0.3, f"foot_{f}_dz": 0.45, f"foot_{f}_dx": -0.3 * side}
        else:  # rear up on the hind legs and stamp both front feet
            raised = {"foot_fl_lift": 0.8, "foot_fr_lift": 0.8, "neck": 0.3, "low": -0.12}
            swiped = after = {"foot_fl_lift": 0.0, "foot_fr_lift": 0.0, "neck": -0.2, "low": 0.05}
        _keys(c, u, [(0.0, {}), (clip.hit_at - 0.12, raised), (clip.hit_at, swiped), (clip.hit_at + 0.15, after), (1.0, _END)])
    elif fam == "wings":
        fold = {"wings": -0.1, "neck": 0.15}
        spread = {"wings": 1.0, "neck": 0.0, "jaw": 0.4}
        _keys(c, u, [(0.0, {}), (0.38, fold), (0.5, spread), (0.7, spread), (1.0, _END)])
    elif fam == "roar":
        w = _ramp(u, 0.0, 0.4) - _ramp(u, 0.65, 1.0)
        a = p("amp")
        c["neck"] += a * w
        c["head"] += 0.75 * a * w
        c["jaw"] += min(0.8, 1.75 * a) * w
        c["wings"] += a * w
    elif fam == "flinch":
        side = p("side")
        pose = {"neck": 0.2 * np.cos(side), "neck_yaw": -0.2 * np.sin(side), "head": 0.1, "jaw": 0.3, "low": 0.05}
        _keys(c, u, [(0.0, {}), (0.35 if p("slow") else 0.25, pose), (0.6, pose), (1.0, _END)])
    elif fam == "hop":
        crouch = {"low": 0.08, **{f"foot_{f}_lift": 0.0 for f in _FEET}}
        d = p("dir")
        air = {
            "low": -0.02,
            **{f"foot_{f}_lift": 0.3 for f in _FEET},
            "wings": 0.3,
            "neck_yaw": 0.15 * np.sin(d),
            "neck": 0.1 * np.cos(d),
        }
        _keys(c, u, [(0.0, {}), (0.15, crouch), (0.45, air), (0.75, crouch), (1.0, _END)])
    elif fam == "shake":
        env = np.sin(np.pi * np.clip(u, 0, 1))
        c["neck_yaw"] += 0.12 * env * np.sin(4 * np.pi * u)
        c["neck"] += 0.1 * env
    elif fam == "sniff":
        pose = {"neck": -0.35, "head": -0.15, "low": 0.1}
        _keys(c, u, [(0.0, {}), (0.4, pose), (0.65, pose), (1.0, _END)])
        c["jaw"] += 0.03 * np.sin(8 * np.pi * u)
    else:
        raise ValueError(f"drake clip {clip.name!r}: unknown pose family {fam!r}")
    return c
