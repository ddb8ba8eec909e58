"""Procedural poses as skeletons: the hunter's (and its weapon's) and the drake's joints from control curves.

Local frame of an entity = its root frame: root (pelvis) at the origin, +Z forward, +Y up, +X to the character's
left. ``hunter_skeleton`` and ``monster_skeleton`` turn a pose's controls (``controls``) into (M, J, 3) root-frame
joints in the rig's source order: fixed bone lengths come from chains and two-bone IK (``two_bone``, its knees
bent by ``knee_pole``), feet and toes are placed on the walkable surface (``surface_local``).
"""

from __future__ import annotations

import numpy as np

HUNTER_PELVIS_H = 0.95  # pelvis height above the surface (m)
MONSTER_PELVIS_H = 1.5
BLADE_M = 1.6  # weapon base (hand) to tip


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
