"""Kinematics of the bridge: state rows → world skeletons at any output rate, float64 throughout.

``world_skeletons`` decodes the state (``marionette.geometry.state_to_world``: roots integrated from
the first row's world anchors, rotations from 6D) and, when the output times differ from the
state's, resamples per entity in its own frame: the root position linearly, the root rotation by
slerp, the joints' root-local offsets linearly, then composes them again — a body turning between
two frames keeps its bone lengths, which interpolating world joints directly would shrink.
Attachments are resampled in their owner's frame. An entity is valid at an output time when both
source frames around it are valid (the one frame itself when the time falls on it).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from marionette.geometry import (
    _bracket,
    matrix_to_quat,
    quat_to_matrix,
    resample_positions,
    resample_quats,
    state_to_world,
    to_local,
    to_world,
)
from marionette.schema import Layout


@dataclass
class Skeletons:
    """World skeletons of a scene over output frames: per entity joints (M, K, 3) float64 (root first
    for articulated entities), root rotations (M, 3, 3) (an attachment's: its owner's) and validity (M,)."""

    times: np.ndarray
    joints: dict[str, np.ndarray]
    rot: dict[str, np.ndarray]
    valid: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.times)


def _valid_at(valid: np.ndarray, t_src: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    if len(t_src) == 1:
        return np.repeat(valid, len(t_dst))
    i0, i1, w = _bracket(t_src, t_dst, "linear")
    return np.where(w <= 1e-9, valid[i0], np.where(w >= 1 - 1e-9, valid[i1], valid[i0] & valid[i1]))


def world_skeletons(
    layout: Layout,
    state: np.ndarray,
    anchors_world: dict[str, np.ndarray],
    valid: dict[str, np.ndarray],
    t_src: np.ndarray,
    t_dst: np.ndarray | None = None,
) -> Skeletons:
    """World skeletons from state rows (N, D) at times ``t_src`` (N,) (seconds), resampled to ``t_dst``.

    ``anchors_world[name]``: (3,) world root of each articulated entity at row 0; ``valid[name]``: (N,)
    bool per articulated entity (attachments follow their owner).
    """
    t_src = np.asarray(t_src, np.float64)
    t_dst = t_src if t_dst is None else np.asarray(t_dst, np.float64)
    n = len(t_src)
    if n == 0:
        if len(t_dst):
            raise ValueError("cannot resample an empty state sequence")
        return Skeletons(
            t_dst,
            {e.name: np.zeros((0, e.rig.n_keep, 3)) for e in layout.entities},
            {e.name: np.zeros((0, 3, 3)) for e in layout.entities},
            {e.name: np.zeros(0, bool) for e in layout.entities},
        )
    state = np.asarray(state, np.float64)
    for e in layout.articulated:
        v = np.asarray(valid[e.name], bool)
        cols = [layout.slice(f"{e.name}.{k}") for k in ("root", "joints", "rot6d")]
        cols += [layout.slice(f"{a.name}.points") for a in layout.attachments if a.owner == e.name]
        bad = v & ~np.all([np.isfinite(state[:, c]).all(axis=1) for c in cols], axis=0)
        if bad.any():
            raise ValueError(f"state row {int(np.flatnonzero(bad)[0])}: {e.name}'s values are not finite")
    world = state_to_world(layout, np.nan_to_num(state), anchors_world)
    same = len(t_dst) == n and np.array_equal(t_dst, t_src)
    joints, rot, ok = {}, {}, {}
    for e in layout.articulated:
        v = np.asarray(valid[e.name], bool)
        J, R = world[e.name]["joints"], world[e.name]["R"]
        if same:
            joints[e.name], rot[e.name], ok[e.name] = J, R, v
            continue
        root = resample_positions(t_src, J[:, 0], t_dst)
        Rd = quat_to_matrix(resample_quats(t_src, matrix_to_quat(R), t_dst))
        local = resample_positions(t_src, to_local(J, J[:, 0], R), t_dst)
        joints[e.name], rot[e.name], ok[e.name] = to_world(local, root, Rd), Rd, _valid_at(v, t_src, t_dst)
    for e in layout.attachments:
        J = world[e.name]["joints"]
        if same:
            joints[e.name], rot[e.name] = J, world[e.owner]["R"]
        else:
            W = world[e.owner]
            local = resample_positions(t_src, to_local(J, W["joints"][:, 0], W["R"]), t_dst)
            joints[e.name], rot[e.name] = to_world(local, joints[e.owner][:, 0], rot[e.owner]), rot[e.owner]
        ok[e.name] = ok[e.owner]
    return Skeletons(t_dst, joints, rot, ok)


def bone_segments(layout: Layout, skel: Skeletons, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The capsules of frame ``i``: ends a (B, 3), b (B, 3) world metres, radii (B,) metres and render ids (B,)."""
    a, b, r, ids = [], [], [], []
    for e in layout.entities:
        if not skel.valid[e.name][i]:
            continue
        J = skel.joints[e.name][i]
        bones = np.array(e.rig.bones, np.int64).reshape(-1, 2)
        if not len(bones) or not np.isfinite(J).all():
            continue
        a.append(J[bones[:, 1]])
        b.append(J[bones[:, 0]])
        r.append(np.full(len(bones), e.rig.capsule_radius_m))
        ids.append(np.array(e.rig.bone_ids(), np.float64))
    if not a:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    return np.concatenate(a), np.concatenate(b), np.concatenate(r), np.concatenate(ids)


def bone_capsules(layout: Layout, skel: Skeletons) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """``bone_segments`` of every frame of ``skel``, in order, the bones of every entity gathered for all frames at
    once (a frame then costs a slice, not a pass over the entities)."""
    parts = []  # per entity with bones: ends a, b (T, B, 3), radii (B,), ids (B,), frames drawn (T,)
    for e in layout.entities:
        bones = np.array(e.rig.bones, np.int64).reshape(-1, 2)
        if not len(bones):
            continue
        J = skel.joints[e.name]
        drawn = np.asarray(skel.valid[e.name], bool) & np.isfinite(J).all(axis=(1, 2))
        ids = np.array(e.rig.bone_ids(), np.float64)
        parts.append((J[:, bones[:, 1]], J[:, bones[:, 0]], np.full(len(bones), e.rig.capsule_radius_m), ids, drawn))
    if not parts:
        for _ in range(len(skel)):
            yield np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0)
        return
    a, b = np.concatenate([p[0] for p in parts], 1), np.concatenate([p[1] for p in parts], 1)
    r, ids = np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts])
    drawn = np.concatenate([np.repeat(p[4][:, None], len(p[2]), 1) for p in parts], 1)  # (T, all bones)
    for i in range(len(skel)):
        if drawn[i].all():
            yield a[i], b[i], r, ids
        else:
            m = drawn[i]
            yield a[i][m], b[i][m], r[m], ids[m]
