"""Procedural poses: per clip a few control curves over the clip's phase, and skeleton builders.

Local frame of an entity = its root frame: root (pelvis) at the origin, +Z forward, +Y up, +X to
the character's left. A pose is a dict of control arrays, each (M,) over M time samples; clips are
blended by blending controls, and the builders turn controls into (M, J, 3) root-frame joints in
the rig's source order (fixed bone lengths come from chains and two-bone IK).
"""

from __future__ import annotations

import numpy as np

from .clips import Clip

HUNTER_PELVIS_H = 0.95  # pelvis height above the surface (m)
MONSTER_PELVIS_H = 1.5
BLADE_M = 1.6  # weapon base (hand) to tip


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
    from .clips import SWINGS

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


def _rot_x(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Rotate (M, K, 3) by angle (M,) about +X (positive tips +Y toward +Z)."""
    ca, sa = np.cos(a)[:, None], np.sin(a)[:, None]
    y, z = v[..., 1], v[..., 2]
    return np.stack([v[..., 0], y * ca - z * sa, y * sa + z * ca], -1)


def _rot_y(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Rotate (M, K, 3) by angle (M,) about +Y (positive turns +Z toward +X)."""
    ca, sa = np.cos(a)[:, None], np.sin(a)[:, None]
    x, z = v[..., 0], v[..., 2]
    return np.stack([x * ca + z * sa, v[..., 1], -x * sa + z * ca], -1)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


REACH = 0.96


def two_bone(root: np.ndarray, target: np.ndarray, a: float, b: float, pole: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two-bone IK (M, 3): (middle joint, end joint) with bone lengths a, b bending toward ``pole``.

    The reach stops at ``REACH`` of a + b: near full extension the middle joint's position changes
    without bound for a small change of the target, so an over-stretched trailing leg would snap its
    knee straight within a frame; short of it the end joint falls short of the target instead.
    """
    d = target - root
    L = np.linalg.norm(d, axis=-1, keepdims=True)
    dh = d / np.maximum(L, 1e-9)
    L = np.clip(L, abs(a - b) + 1e-4, REACH * (a + b))
    cos_a = (a * a + L * L - b * b) / (2 * a * L)
    sin_a = np.sqrt(np.clip(1 - cos_a**2, 0, 1))
    n = _unit(pole - np.sum(pole * dh, -1, keepdims=True) * dh)
    mid = root + a * (cos_a * dh + sin_a * n)
    return mid, root + L * dh


def knee_pole(root: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Pole (M, 3) bending a knee forward: the leg's direction turned 90° about the x axis (down → forward,
    forward → up). For a leg reaching down it equals the fixed pole +z; unlike +z it never lines up with a
    foot planted high and ahead (running uphill), where a fixed pole flips the knee from frame to frame."""
    d = np.broadcast_to(target - root, np.broadcast_shapes(np.shape(root), np.shape(target)))
    return np.stack([np.zeros(d.shape[:-1]), d[..., 2], -d[..., 1]], -1)


def _dir(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Unit vector (M, 3) at azimuth az (from +Z toward +X) and elevation el (from horizontal)."""
    return np.stack([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)], -1)


_HUNTER_TORSO = {  # torso-frame offsets from the pelvis, before lean and twist
    "spine1": (0, 0.12, 0),
    "spine2": (0, 0.25, 0),
    "chest": (0, 0.40, 0),
    "neck": (0, 0.55, 0),
    "head": (0, 0.65, 0.02),
    "head_top": (0, 0.85, 0.0),
    "jaw": (0, 0.58, 0.10),
    "back_mount": (0, 0.45, -0.15),
    "clavicle_l": (0.08, 0.50, 0),
    "upperarm_l": (0.20, 0.48, 0),
    "clavicle_r": (-0.08, 0.50, 0),
    "upperarm_r": (-0.20, 0.48, 0),
}


def hunter_skeleton(rig, c: dict[str, np.ndarray], surface_local) -> tuple[np.ndarray, np.ndarray]:
    """Root-frame joints (M, 36, 3) of the hunter and its weapon's points (M, 5, 3).

    ``surface_local(x_local, z_local)`` gives the walkable surface's height in the root frame.
    """
    M = len(c["lean"])
    idx = {n: i for i, n in enumerate(rig.source_joints)}
    J = np.zeros((M, len(rig.source_joints), 3))
    names = list(_HUNTER_TORSO)
    torso = np.broadcast_to(np.array([_HUNTER_TORSO[n] for n in names], dtype=np.float64), (M, len(names), 3))
    torso = _rot_y(_rot_x(torso, c["lean"]), c["twist"])
    for i, n in enumerate(names):
        J[:, idx[n]] = torso[:, i]
    neck = J[:, idx["neck"]]
    for n in ("head", "head_top", "jaw"):  # the head turns on the neck by ``look``
        J[:, idx[n]] = neck + _rot_y((J[:, idx[n]] - neck)[:, None], c["look"])[:, 0]
    J[:, idx["hip_holster"]] = (-0.18, 0.0, -0.05)

    blade = _dir(c["blade_az"], c["blade_el"])
    down_back = np.array([0.0, -1.0, -0.6])
    for side, sx in (("l", 1.0), ("r", -1.0)):
        sh = J[:, idx[f"upperarm_{side}"]]
        target = np.stack([c[f"hand_{side}_x"], c[f"hand_{side}_y"], c[f"hand_{side}_z"]], -1)
        elbow, hand = two_bone(sh, target, 0.30, 0.30, down_back + np.array([sx * 0.5, 0, 0]))
        J[:, idx[f"forearm_{side}"]] = elbow
        J[:, idx[f"forearm_twist_{side}"]] = (elbow + hand) / 2
        J[:, idx[f"hand_{side}"]] = hand
        fwd = blade if side == "r" else _unit(hand - elbow)
        J[:, idx[f"fingers_{side}"]] = hand + 0.08 * fwd
        # the thumb: along the hand and off it, at right angles, toward the side (or up when the hand points sideways)
        side_dir = np.where(np.abs(fwd[:, :1]) < 0.8, np.array([sx, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
        off = _unit(side_dir - np.sum(side_dir * fwd, -1, keepdims=True) * fwd)
        J[:, idx[f"thumb_{side}"]] = hand + 0.05 * fwd + 0.036 * off

    for side, sx in (("l", 1.0), ("r", -1.0)):
        hip = np.array([sx * 0.10, -0.07, 0.0])
        J[:, idx[f"thigh_{side}"]] = hip
        lift, rot = c[f"foot_{side}_lift"], c[f"foot_{side}_rot"]
        x0, z0 = sx * 0.11 + c[f"foot_{side}_dx"], c[f"foot_{side}_dz"]
        ca, sa = np.cos(rot), np.sin(rot)
        x, dz = x0 * ca + z0 * sa, -x0 * sa + z0 * ca  # a turning step rotates the foot about the root
        ankle = np.stack([x, surface_local(x, dz) + 0.08 + lift, dz], -1)
        hip_m = np.broadcast_to(hip, (M, 3))
        knee, ankle = two_bone(hip_m, ankle, 0.55, 0.55, knee_pole(hip_m, ankle))
        J[:, idx[f"shin_{side}"]] = knee
        J[:, idx[f"thigh_twist_{side}"]] = (hip + knee) / 2
        J[:, idx[f"foot_{side}"]] = ankle
        toe, tip = _foot_chain(ankle, sa, ca, lift, surface_local, 0.08, ((0.12, 0.02), (0.20, 0.0)))
        J[:, idx[f"toe_{side}"]], J[:, idx[f"toe_tip_{side}"]] = toe, tip

    hand = J[:, idx["hand_r"]]
    W = np.stack([hand + f * blade for f in (0.0, 0.2, 0.3, 0.95, BLADE_M)], axis=1)
    return J, W


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


def _chain(base: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, dyaw, dpitch, lengths) -> list[np.ndarray]:
    """Points (M, 3) along a chain from ``base``: segment i points at (yaw + i·dyaw, pitch + i·dpitch)."""
    pts, p = [], base
    for i, L in enumerate(lengths):
        p = p + L * _dir(yaw + i * dyaw, pitch + i * dpitch)
        pts.append(p)
    return pts


def monster_skeleton(rig, c: dict[str, np.ndarray], surface_local) -> np.ndarray:
    """Root-frame joints (M, 64, 3) of the drake; the spine pitches with the ground between its hind and front feet."""
    M = len(c["neck"])
    idx = {n: i for i, n in enumerate(rig.source_joints)}
    J = np.zeros((M, len(rig.source_joints), 3))
    zero = np.zeros(M)
    origin = np.zeros((M, 3))
    slope = np.arctan((surface_local(zero, zero + 2.0) - surface_local(zero, zero)) / 2.0)
    body_pitch = np.clip(slope, -0.4, 0.4) - 0.3 * c["low"]
    spine = _chain(origin, zero, 0.08 + body_pitch, 0.0, 0.0, (0.5, 0.5, 0.5, 0.5))
    for n, p in zip(("spine1", "spine2", "spine3", "chest"), spine):
        J[:, idx[n]] = p
    chest = spine[-1]
    yaw = c["neck_yaw"]
    neck = _chain(chest, yaw, 0.65 + c["neck"] + body_pitch, 0.0, -0.18, (0.6, 0.6, 0.6, 0.4))
    for n, p in zip(("neck1", "neck2", "neck3", "head"), neck):
        J[:, idx[n]] = p
    head = neck[-1]
    head_pitch = 0.65 + c["neck"] - 0.54 - 0.35 + c["head"] + body_pitch
    hdir = _dir(yaw, head_pitch)
    hup = _dir(yaw, head_pitch + np.pi / 2)
    hleft = np.stack([np.cos(yaw), zero, -np.sin(yaw)], -1)

    def at(fwd, up, left):
        return head + fwd * hdir + up * hup + left * hleft

    J[:, idx["snout"]] = at(0.9, 0.0, 0.0)
    J[:, idx["eye_l"]] = at(0.35, 0.2, 0.18)
    J[:, idx["eye_r"]] = at(0.35, 0.2, -0.18)
    J[:, idx["horn_l"]] = at(-0.2, 0.35, 0.2)
    J[:, idx["horn_r"]] = at(-0.2, 0.35, -0.2)
    jaw = at(0.1, -0.15, 0.0)
    jdir = _dir(yaw, head_pitch - c["jaw"])
    J[:, idx["jaw"]] = jaw
    J[:, idx["jaw_tip"]] = jaw + 0.8 * jdir
    J[:, idx["tongue1"]] = jaw + 0.3 * jdir
    J[:, idx["tongue2"]] = jaw + 0.55 * jdir

    tail = _chain(origin, np.pi + c["tail_yaw"], -0.15 + c["tail_pitch"], c["tail_yaw"], 0.015, (0.45,) * 10)
    for i, p in enumerate(tail):
        J[:, idx[f"tail{i + 1}"]] = p

    for side, sx in (("l", 1.0), ("r", -1.0)):
        w1 = chest + np.array([sx * 0.4, 0.3, -0.1])
        spread = c["wings"]
        w2 = w1 + 1.1 * _unit(np.stack([sx * np.ones(M), 0.5 + 0.6 * spread, -0.3 * (1 - spread)], -1))
        w3 = w2 + 1.1 * _unit(np.stack([sx * (0.3 + 1.2 * spread), 0.1 + 0.3 * spread, -(1 - spread)], -1))
        tip = w3 + 0.9 * _unit(np.stack([sx * (0.2 + 1.0 * spread), -0.2 + 0.0 * spread, -(1 - 0.8 * spread)], -1))
        J[:, idx[f"wing1_{side}"]] = w1
        J[:, idx[f"wing_twist_{side}"]] = (w1 + w2) / 2
        J[:, idx[f"wing2_{side}"]] = w2
        J[:, idx[f"wing3_{side}"]] = w3
        J[:, idx[f"wing_tip_{side}"]] = tip

    for f, sx in (("fl", 1.0), ("fr", -1.0)):
        J[:, idx[f"clavicle_{f}"]] = chest + np.array([sx * 0.3, -0.1, 0.0])
        sh = chest + np.array([sx * 0.55, -0.2, 0.0])
        J[:, idx[f"upperarm_{f}"]] = sh
        lift, rot = c[f"foot_{f}_lift"], c[f"foot_{f}_rot"]
        x, z = _turned(sx * 0.6 + c[f"foot_{f}_dx"], chest[:, 2] + c[f"foot_{f}_dz"], rot)
        wrist = np.stack([x, surface_local(x, z) + 0.3 + lift, z], -1)
        elbow, wrist = two_bone(sh, wrist, 0.95, 0.95, np.array([0.0, 0.0, -1.0]))
        J[:, idx[f"forearm_{f}"]] = elbow
        J[:, idx[f"upperarm_twist_{f}"]] = (sh + elbow) / 2
        J[:, idx[f"hand_{f}"]] = wrist
        _toes(J, idx, f"toe_{f}", f"claw_{f}", wrist, lift, rot, surface_local, 0.2, 0.38, 0.3)
    for f, sx in (("hl", 1.0), ("hr", -1.0)):
        hip = np.broadcast_to(np.array([sx * 0.45, -0.1, 0.0]), (M, 3))
        J[:, idx[f"thigh_{f}"]] = hip
        lift, rot = c[f"foot_{f}_lift"], c[f"foot_{f}_rot"]
        x, z = _turned(sx * 0.5 + c[f"foot_{f}_dx"], c[f"foot_{f}_dz"], rot)
        ankle = np.stack([x, surface_local(x, z) + 0.35 + lift, z], -1)
        knee, ankle = two_bone(hip, ankle, 0.85, 0.85, knee_pole(hip, ankle))
        J[:, idx[f"shin_{f}"]] = knee
        J[:, idx[f"thigh_twist_{f}"]] = (hip + knee) / 2
        J[:, idx[f"ankle_{f}"]] = ankle
        _toes(J, idx, f"toe_{f}", f"claw_{f}", ankle, lift, rot, surface_local, 0.25, 0.4, 0.35)
    return J


def _turned(x, z, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root-frame (x, z) rotated about the root's vertical axis by ``rot`` (a turning step), metres."""
    ca, sa = np.cos(rot), np.sin(rot)
    return x * ca + z * sa, -x * sa + z * ca


def _foot_chain(start: np.ndarray, sa, ca, lift: np.ndarray, surface_local, start_h: float, points) -> list[np.ndarray]:
    """Toe points (M, 3) ahead of an ankle along the heading (sin, cos) = (sa, ca): each at its nominal distance
    ahead and height over the surface (``points``: (distance from the ankle, height) pairs, m), but placed at its
    fixed bone length from the point before, so a slope under the foot tilts the toes without stretching them."""
    out, prev, prev_d, prev_h = [], start, 0.0, start_h
    for d, h in points:
        step, length = d - prev_d, float(np.hypot(d - prev_d, h - prev_h))
        x, z = prev[:, 0] + step * sa, prev[:, 2] + step * ca
        v = np.stack([x - prev[:, 0], surface_local(x, z) + h + lift - prev[:, 1], z - prev[:, 2]], -1)
        prev = prev + length * _unit(v)
        out.append(prev)
        prev_d, prev_h = d, h
    return out


def _toes(
    J,
    idx,
    toe: str,
    claw: str,
    wrist: np.ndarray,
    lift: np.ndarray,
    rot: np.ndarray,
    surface_local,
    toe_z: float,
    claw_z: float,
    wrist_h: float,
) -> None:
    J[:, idx[toe]], J[:, idx[claw]] = _foot_chain(
        wrist, np.sin(rot), np.cos(rot), lift, surface_local, wrist_h, ((toe_z, 0.08), (claw_z, 0.0))
    )
