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


def gait(phase: np.ndarray, clip: Clip, offsets: tuple[float, ...], lift_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per foot (forward offset dz, lift) of a gait cycle: stance glides back at the root speed, swing returns."""
    T = clip.length / 30.0
    d = clip.duty
    stride = clip.speed * d * T
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


# ----------------------------------------------------------------------------------------------- hunter

HUNTER_NEUTRAL = {
    "foot_l_dz": 0.05,
    "foot_l_lift": 0.0,
    "foot_r_dz": -0.05,
    "foot_r_lift": 0.0,
    "lean": 0.05,
    "twist": 0.0,
    "hand_r_x": -0.28,
    "hand_r_y": 0.0,
    "hand_r_z": 0.3,
    "blade_az": 0.0,
    "blade_el": 0.35,
    "hand_l_x": 0.25,
    "hand_l_y": -0.05,
    "hand_l_z": 0.05,
}


def hunter_controls(clip: Clip, phase: np.ndarray) -> dict[str, np.ndarray]:
    """Control curves of a hunter clip at ``phase`` (frames since the clip started, continuous)."""
    c = {k: np.full(phase.shape, v, dtype=np.float64) for k, v in HUNTER_NEUTRAL.items()}
    u = phase / clip.length
    if clip.name == "idle":
        c["lean"] += 0.03 * np.sin(2 * np.pi * u)
        c["hand_l_z"] += 0.02 * np.sin(2 * np.pi * u)
    elif clip.name in ("walk", "run"):
        (lz, ll), (rz, rl) = gait(phase, clip, (0.0, 0.5), 0.12 if clip.name == "walk" else 0.2)
        c["foot_l_dz"], c["foot_l_lift"], c["foot_r_dz"], c["foot_r_lift"] = lz, ll, rz, rl
        c["lean"] += 0.1 if clip.name == "walk" else 0.25
        c["hand_l_z"] += -0.6 * lz
        c["twist"] += 0.3 * lz
    elif clip.name in ("attack", "heavy_attack"):
        heavy = clip.name == "heavy_attack"
        up = _ramp(u, 0.0, 0.45) - _ramp(u, 0.45, 0.62)  # raised weight
        hit = _ramp(u, 0.45, 0.62) - _ramp(u, 0.75, 1.0)  # struck weight
        raised = {
            "hand_r_x": -0.15,
            "hand_r_y": 0.55,
            "hand_r_z": -0.05,
            "blade_el": 2.6 if heavy else 2.2,
            "twist": 0.6 if heavy else 0.3,
            "lean": -0.1,
        }
        struck = {"hand_r_x": -0.1, "hand_r_y": 0.0, "hand_r_z": 0.55, "blade_el": -0.45, "twist": -0.25, "lean": 0.35}
        for k in raised:
            c[k] = c[k] + up * (raised[k] - c[k]) + hit * (struck[k] - c[k])
        # The left hand joins the grip.
        for ax in "xyz":
            c[f"hand_l_{ax}"] = c[f"hand_l_{ax}"] + (up + hit) * (c[f"hand_r_{ax}"] - 0.0 - c[f"hand_l_{ax}"])
    elif clip.name == "dodge":
        w = np.sin(np.pi * np.clip(u, 0, 1))
        c["lean"] += 0.3 * w
        c["hand_l_y"] += 0.1 * w
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
        J[:, idx[f"thumb_{side}"]] = hand + 0.05 * fwd + np.array([sx * 0.03, 0.02, 0.0])

    for side, sx in (("l", 1.0), ("r", -1.0)):
        hip = np.array([sx * 0.10, -0.07, 0.0])
        J[:, idx[f"thigh_{side}"]] = hip
        dz, lift = c[f"foot_{side}_dz"], c[f"foot_{side}_lift"]
        x = np.full(M, sx * 0.11)
        ankle = np.stack([x, surface_local(x, dz) + 0.08 + lift, dz], -1)
        hip_m = np.broadcast_to(hip, (M, 3))
        knee, ankle = two_bone(hip_m, ankle, 0.55, 0.55, knee_pole(hip_m, ankle))
        J[:, idx[f"shin_{side}"]] = knee
        J[:, idx[f"thigh_twist_{side}"]] = (hip + knee) / 2
        J[:, idx[f"foot_{side}"]] = ankle
        for name, fz, h in ((f"toe_{side}", 0.12, 0.02), (f"toe_tip_{side}", 0.20, 0.0)):
            z = ankle[:, 2] + fz
            J[:, idx[name]] = np.stack([ankle[:, 0], surface_local(ankle[:, 0], z) + h + lift, z], -1)

    hand = J[:, idx["hand_r"]]
    W = np.stack([hand + f * blade for f in (0.0, 0.2, 0.3, 0.95, BLADE_M)], axis=1)
    return J, W


# ----------------------------------------------------------------------------------------------- drake

MONSTER_NEUTRAL = {
    **{f"foot_{f}_{k}": 0.0 for f in ("fl", "fr", "hl", "hr") for k in ("dz", "lift")},
    "neck": 0.0,
    "head": 0.0,
    "jaw": 0.05,
    "tail_yaw": 0.0,
    "tail_pitch": 0.0,
    "wings": 0.0,
}


def monster_controls(clip: Clip, phase: np.ndarray) -> dict[str, np.ndarray]:
    """Control curves of a drake clip at ``phase`` (frames since the clip started, continuous)."""
    c = {k: np.full(phase.shape, v, dtype=np.float64) for k, v in MONSTER_NEUTRAL.items()}
    u = phase / clip.length
    if clip.name == "idle":
        c["neck"] += 0.04 * np.sin(2 * np.pi * u)
        c["tail_yaw"] += 0.01 * np.sin(2 * np.pi * u)
    elif clip.name in ("walk", "run"):
        feet = gait(phase, clip, (0.0, 0.5, 0.25, 0.75), 0.25 if clip.name == "walk" else 0.3)
        for f, (dz, lift) in zip(("fl", "fr", "hl", "hr"), feet):
            c[f"foot_{f}_dz"], c[f"foot_{f}_lift"] = dz, lift
        c["tail_yaw"] += 0.015 * np.sin(2 * np.pi * u)
        c["neck"] += -0.1 if clip.name == "run" else 0.0
    elif clip.name == "bite":
        rear = _ramp(u, 0.0, 0.35) - _ramp(u, 0.35, 0.45)
        strike = _ramp(u, 0.35, 0.45) - _ramp(u, 0.6, 1.0)
        c["neck"] += 0.4 * rear - 0.55 * strike
        c["head"] += 0.2 * rear - 0.3 * strike
        c["jaw"] += 0.6 * rear + 0.1 * strike
    elif clip.name == "tail_swipe":
        wind = _ramp(u, 0.0, 0.4) - _ramp(u, 0.4, 0.55)
        swipe = _ramp(u, 0.4, 0.55) - _ramp(u, 0.65, 1.0)
        c["tail_yaw"] += 0.12 * wind - 0.16 * swipe
        c["tail_pitch"] += 0.05 * wind + 0.05 * swipe
    elif clip.name == "roar":
        w = _ramp(u, 0.0, 0.4) - _ramp(u, 0.65, 1.0)
        c["neck"] += 0.4 * w
        c["head"] += 0.3 * w
        c["jaw"] += 0.7 * w
        c["wings"] += 0.4 * w
    return c


def _chain(base: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, dyaw, dpitch, lengths) -> list[np.ndarray]:
    """Points (M, 3) along a chain from ``base``: segment i points at (yaw + i·dyaw, pitch + i·dpitch)."""
    pts, p = [], base
    for i, L in enumerate(lengths):
        p = p + L * _dir(yaw + i * dyaw, pitch + i * dpitch)
        pts.append(p)
    return pts


def monster_skeleton(rig, c: dict[str, np.ndarray], surface_local) -> np.ndarray:
    """Root-frame joints (M, 64, 3) of the drake."""
    M = len(c["neck"])
    idx = {n: i for i, n in enumerate(rig.source_joints)}
    J = np.zeros((M, len(rig.source_joints), 3))
    zero = np.zeros(M)
    origin = np.zeros((M, 3))
    spine = _chain(origin, zero, zero + 0.08, 0.0, 0.0, (0.5, 0.5, 0.5, 0.5))
    for n, p in zip(("spine1", "spine2", "spine3", "chest"), spine):
        J[:, idx[n]] = p
    chest = spine[-1]
    neck = _chain(chest, zero, 0.65 + c["neck"], 0.0, -0.18 + 0.0 * c["neck"], (0.6, 0.6, 0.6, 0.4))
    for n, p in zip(("neck1", "neck2", "neck3", "head"), neck):
        J[:, idx[n]] = p
    head = neck[-1]
    head_pitch = 0.65 + c["neck"] - 0.54 - 0.35 + c["head"]
    hdir = _dir(zero, head_pitch)
    hup = _dir(zero, head_pitch + np.pi / 2)
    hleft = np.array([1.0, 0.0, 0.0])

    def at(fwd, up, left):
        return head + fwd * hdir + up * hup + left * hleft

    J[:, idx["snout"]] = at(0.9, 0.0, 0.0)
    J[:, idx["eye_l"]] = at(0.35, 0.2, 0.18)
    J[:, idx["eye_r"]] = at(0.35, 0.2, -0.18)
    J[:, idx["horn_l"]] = at(-0.2, 0.35, 0.2)
    J[:, idx["horn_r"]] = at(-0.2, 0.35, -0.2)
    jaw = at(0.1, -0.15, 0.0)
    jdir = _dir(zero, head_pitch - c["jaw"])
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
        dz, lift = c[f"foot_{f}_dz"], c[f"foot_{f}_lift"]
        x, z = np.full(M, sx * 0.6), chest[:, 2] + dz
        wrist = np.stack([x, surface_local(x, z) + 0.3 + lift, z], -1)
        elbow, wrist = two_bone(sh, wrist, 0.95, 0.95, np.array([0.0, 0.0, -1.0]))
        J[:, idx[f"forearm_{f}"]] = elbow
        J[:, idx[f"upperarm_twist_{f}"]] = (sh + elbow) / 2
        J[:, idx[f"hand_{f}"]] = wrist
        _toes(J, idx, f"toe_{f}", f"claw_{f}", wrist, lift, surface_local, 0.2, 0.38)
    for f, sx in (("hl", 1.0), ("hr", -1.0)):
        hip = np.broadcast_to(np.array([sx * 0.45, -0.1, 0.0]), (M, 3))
        J[:, idx[f"thigh_{f}"]] = hip
        dz, lift = c[f"foot_{f}_dz"], c[f"foot_{f}_lift"]
        x = np.full(M, sx * 0.5)
        ankle = np.stack([x, surface_local(x, dz) + 0.35 + lift, dz], -1)
        knee, ankle = two_bone(hip, ankle, 0.85, 0.85, knee_pole(hip, ankle))
        J[:, idx[f"shin_{f}"]] = knee
        J[:, idx[f"thigh_twist_{f}"]] = (hip + knee) / 2
        J[:, idx[f"ankle_{f}"]] = ankle
        _toes(J, idx, f"toe_{f}", f"claw_{f}", ankle, lift, surface_local, 0.25, 0.4)
    return J


def _toes(J, idx, toe: str, claw: str, wrist: np.ndarray, lift: np.ndarray, surface_local, toe_z: float, claw_z: float) -> None:
    for name, fz, h in ((toe, toe_z, 0.08), (claw, claw_z, 0.0)):
        z = wrist[:, 2] + fz
        J[:, idx[name]] = np.stack([wrist[:, 0], surface_local(wrist[:, 0], z) + h + lift, z], -1)
