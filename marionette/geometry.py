"""Rotations, root integration, world reconstruction and time resampling.

Conventions (DESIGN "The world state"):
- quaternions are (x, y, z, w), unit, active rotations; R rotates local vectors into the world;
- 6D = the first two columns of R concatenated: [R00, R10, R20, R01, R11, R21] (Zhou et al., "On the
  Continuity of Rotation Representations in Neural Networks", CVPR 2019); back to R by Gram–Schmidt;
- root displacement δ_t = R_tᵀ (x_t − x_{t−1}) with δ_0 = 0; joints p_{t,k} = R_tᵀ (X_{t,k} − x_t);
- reconstruction x_t = x_0 + Σ_{τ≤t} R_τ δ_τ and X_{t,k} = x_t + R_t p_{t,k}, accumulated in float64.

Rotation functions take numpy arrays or torch tensors with any leading batch shape (``...``) and
return the same kind; numpy and torch give the same numbers (tested).
"""

from __future__ import annotations

from typing import Any

import numpy as np

Array = Any  # np.ndarray or torch.Tensor

_EPS = 1e-12


def _is_torch(x: Array) -> bool:
    return type(x).__module__.startswith("torch")


def _stack(xs: list, axis: int, like: Array) -> Array:
    if _is_torch(like):
        import torch

        return torch.stack(xs, dim=axis)
    return np.stack(xs, axis=axis)


def _norm(x: Array) -> Array:
    if _is_torch(x):
        return x.norm(dim=-1, keepdim=True)
    return np.linalg.norm(x, axis=-1, keepdims=True)


def _cross(a: Array, b: Array) -> Array:
    if _is_torch(a):
        import torch

        return torch.linalg.cross(a, b, dim=-1)
    return np.cross(a, b)


def _where(c: Array, a: Array, b: Array) -> Array:
    if _is_torch(c):
        import torch

        return torch.where(c, a, b)
    return np.where(c, a, b)


def _sum(x: Array, keep: bool = True) -> Array:
    if _is_torch(x):
        return x.sum(dim=-1, keepdim=keep)
    return x.sum(axis=-1, keepdims=keep)


def _clip_min(x: Array, lo: float) -> Array:
    return x.clamp_min(lo) if _is_torch(x) else np.maximum(x, lo)


def transpose(R: Array) -> Array:
    """Swap the last two axes of a (..., 3, 3) batch."""
    return R.transpose(-1, -2) if _is_torch(R) else np.swapaxes(R, -1, -2)


def quat_normalize(q: Array) -> Array:
    """Unit quaternions (..., 4); a zero quaternion becomes the identity."""
    n = _norm(q)
    ident = q * 0
    ident[..., 3] = 1
    return _where(n > _EPS, q / _clip_min(n, _EPS), ident)


def quat_to_matrix(q: Array) -> Array:
    """(x, y, z, w) quaternion (..., 4) → rotation matrix (..., 3, 3); normalises first."""
    q = quat_normalize(q)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        _stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1, q),
        _stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1, q),
        _stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1, q),
    ]
    return _stack(rows, -2, q)


def matrix_to_quat(R: Array) -> Array:
    """Rotation matrix (..., 3, 3) → (x, y, z, w) quaternion with w ≥ 0 (Shepperd's method)."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate solutions, each well conditioned where its pivot is largest.
    cands = [
        _stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1], 1 + trace], -1, R),
        _stack(
            [1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 2, 1] - R[..., 1, 2]], -1, R
        ),
        _stack(
            [R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1], R[..., 0, 2] - R[..., 2, 0]], -1, R
        ),
        _stack(
            [R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22, R[..., 1, 0] - R[..., 0, 1]], -1, R
        ),
    ]
    pivots = _stack([trace, m00, m11, m22], -1, R)
    if _is_torch(R):
        import torch

        best = pivots.argmax(dim=-1)
        allc = torch.stack(cands, dim=-2)  # (..., 4, 4)
        q = torch.gather(allc, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(_EPS)
        return torch.where(q[..., 3:4] < 0, -q, q)
    best = np.argmax(pivots, axis=-1)
    allc = np.stack(cands, axis=-2)
    q = np.take_along_axis(allc, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)
    return np.where(q[..., 3:4] < 0, -q, q)


def matrix_to_rot6d(R: Array) -> Array:
    """Rotation matrix (..., 3, 3) → 6D [R00, R10, R20, R01, R11, R21] (first two columns)."""
    if _is_torch(R):
        import torch

        return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def rot6d_to_matrix(d6: Array) -> Array:
    """6D (..., 6) → rotation matrix (..., 3, 3) by Gram–Schmidt: b1 = a1/|a1|,
    b2 = normalise(a2 − (b1·a2) b1), b3 = b1 × b2, R = [b1 b2 b3].

    Degenerate inputs still give a proper rotation: a zero a1 is taken as +X, and an a2 parallel to
    a1 is replaced by the world axis least aligned with b1.
    """
    a1, a2 = d6[..., 0:3], d6[..., 3:6]
    ex = a1 * 0
    ex[..., 0] = 1
    n1 = _norm(a1)
    b1 = _where(n1 > _EPS, a1 / _clip_min(n1, _EPS), ex)
    u = a2 - _sum(b1 * a2) * b1
    nu = _norm(u)
    # Fallback direction: the coordinate axis least aligned with b1, orthogonalised.
    absb = b1.abs() if _is_torch(b1) else np.abs(b1)
    if _is_torch(b1):
        axis = absb.argmin(dim=-1, keepdim=True)
        e = (b1 * 0).scatter(-1, axis, 1.0)
    else:
        e = np.zeros_like(b1)
        np.put_along_axis(e, np.argmin(absb, axis=-1)[..., None], 1.0, axis=-1)
    f = e - _sum(b1 * e) * b1
    f = f / _clip_min(_norm(f), _EPS)
    rel = nu / _clip_min(_norm(a2), _EPS)
    b2 = _where((nu > _EPS) & (rel > 1e-7), u / _clip_min(nu, _EPS), f)
    b3 = _cross(b1, b2)
    return _stack([b1, b2, b3], -1, d6)


def quat_to_rot6d(q: Array) -> Array:
    """(x, y, z, w) quaternion (..., 4) → 6D (..., 6)."""
    return matrix_to_rot6d(quat_to_matrix(q))


def yaw_quat(yaw: Array) -> np.ndarray:
    """Rotation by ``yaw`` radians about world +Y as (x, y, z, w) quaternions (numpy)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    return np.stack([np.zeros_like(yaw), np.sin(yaw / 2), np.zeros_like(yaw), np.cos(yaw / 2)], axis=-1)


def quat_continuity(q: np.ndarray, axis: int = 0) -> np.ndarray:
    """Flip signs along ``axis`` so consecutive quaternions have a non-negative dot product."""
    q = np.moveaxis(np.array(q, dtype=np.float64, copy=True), axis, 0)
    if len(q) > 1:
        dots = np.sum(q[1:] * q[:-1], axis=-1)
        flips = np.cumsum(dots < 0, axis=0) % 2  # a sign flip persists to every later sample
        q[1:] = np.where(flips[..., None] == 1, -q[1:], q[1:])
    return np.moveaxis(q, 0, axis)


def quat_slerp(q0: Array, q1: Array, t: Array) -> Array:
    """Spherical interpolation between unit quaternions (..., 4) at fraction t (...), shortest arc."""
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    dot = _sum(q0 * q1)
    q1 = _where(dot < 0, -q1, q1)
    dot = dot.abs() if _is_torch(dot) else np.abs(dot)
    dot = dot.clamp(max=1.0) if _is_torch(dot) else np.minimum(dot, 1.0)
    t = t[..., None]
    if _is_torch(dot):
        import torch

        theta = torch.arccos(dot)
        s = torch.sin(theta)
    else:
        theta = np.arccos(dot)
        s = np.sin(theta)
    small = s < 1e-6  # nearly equal: fall back to normalised lerp
    s_safe = _where(small, s * 0 + 1, s)
    sin = (lambda v: v.sin()) if _is_torch(dot) else np.sin
    w0 = _where(small, 1 - t, sin((1 - t) * theta) / s_safe)
    w1 = _where(small, t, sin(t * theta) / s_safe)
    return quat_normalize(w0 * q0 + w1 * q1)


# ----------------------------------------------------------------------------------------------
# World skeletons ↔ state (numpy, float64 inside)


def root_deltas_local(roots_world: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Root displacement in the local frame, δ_t = R_tᵀ (x_t − x_{t−1}), δ_0 = 0. (N,3),(N,3,3) → (N,3)."""
    x = np.asarray(roots_world, dtype=np.float64)
    d = np.zeros_like(x)
    d[1:] = x[1:] - x[:-1]
    return np.einsum("nji,nj->ni", R, d)


def integrate_roots(anchor_world: np.ndarray, deltas_local: np.ndarray, R: np.ndarray) -> np.ndarray:
    """World roots x_t = x_0 + Σ_{1≤τ≤t} R_τ δ_τ, float64. (3,), (N,3), (N,3,3) → (N,3)."""
    steps = np.einsum("nij,nj->ni", np.asarray(R, np.float64), np.asarray(deltas_local, np.float64))
    steps[:1] = 0.0  # δ_0 is 0 by definition; tolerate an empty sequence
    return np.asarray(anchor_world, np.float64) + np.cumsum(steps, axis=0)


def to_local(points_world: np.ndarray, origin_world: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Points in an entity's root frame, R_tᵀ (X − x_t). (N,K,3), (N,3), (N,3,3) → (N,K,3)."""
    rel = np.asarray(points_world, np.float64) - np.asarray(origin_world, np.float64)[:, None, :]
    return rel @ np.asarray(R, np.float64)  # row vectors: (Rᵀ v)ᵀ = vᵀ R; matmul is ~3× faster than einsum here


def to_world(points_local: np.ndarray, origin_world: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Inverse of ``to_local``: X = x_t + R_t p. (N,K,3), (N,3), (N,3,3) → (N,K,3) float64."""
    return np.asarray(origin_world, np.float64)[:, None, :] + np.asarray(points_local, np.float64) @ transpose(
        np.asarray(R, np.float64)
    )


def world_to_state(layout, joints_world: dict[str, np.ndarray], rot_world: dict[str, np.ndarray]) -> np.ndarray:
    """Encode one segment's world skeletons as state rows (N, D) float32.

    ``joints_world[name]``: (N, K, 3) kept joints in world metres (for articulated entities the root
    first); ``rot_world[name]``: (N, 4) root quaternion (x, y, z, w) of each articulated entity.
    """
    n = next(iter(joints_world.values())).shape[0]
    state = np.zeros((n, layout.dim), dtype=np.float64)
    frames = {}
    for e in layout.articulated:
        X = np.asarray(joints_world[e.name], np.float64)
        R = quat_to_matrix(np.asarray(rot_world[e.name], np.float64))
        root = X[:, 0, :]
        frames[e.name] = (root, R)
        state[:, layout.slice(f"{e.name}.root")] = root_deltas_local(root, R)
        state[:, layout.slice(f"{e.name}.joints")] = to_local(X[:, 1:], root, R).reshape(n, 3 * (e.rig.n_keep - 1))
        state[:, layout.slice(f"{e.name}.rot6d")] = matrix_to_rot6d(R)
    for e in layout.attachments:
        root, R = frames[e.owner]
        state[:, layout.slice(f"{e.name}.points")] = to_local(joints_world[e.name], root, R).reshape(n, 3 * e.rig.n_keep)
    return state.astype(np.float32)


def state_to_world(layout, state: np.ndarray, anchors_world: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """Reconstruct world skeletons from state rows (the bridge's first step), float64.

    ``anchors_world[name]``: (3,) world root of each articulated entity at the first row. Returns per
    entity {"joints": (N, K, 3) world joints (root first for articulated), "R": (N, 3, 3)} — for an
    attachment "R" is its owner's.
    """
    s = np.asarray(state, np.float64)
    n = s.shape[0]
    out: dict[str, dict[str, np.ndarray]] = {}
    for e in layout.articulated:
        R = rot6d_to_matrix(s[:, layout.slice(f"{e.name}.rot6d")])
        root = integrate_roots(anchors_world[e.name], s[:, layout.slice(f"{e.name}.root")], R)
        local = s[:, layout.slice(f"{e.name}.joints")].reshape(n, e.rig.n_keep - 1, 3)
        joints = np.concatenate([root[:, None, :], to_world(local, root, R)], axis=1)
        out[e.name] = {"joints": joints, "R": R}
    for e in layout.attachments:
        owner = out[e.owner]
        local = s[:, layout.slice(f"{e.name}.points")].reshape(n, e.rig.n_keep, 3)
        out[e.name] = {"joints": to_world(local, owner["joints"][:, 0], owner["R"]), "R": owner["R"]}
    return out


# ----------------------------------------------------------------------------------------------
# Time resampling


def _bracket(t_src: np.ndarray, t_dst: np.ndarray, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bracketing source indices (i0, i1) and the fraction w ∈ [0, 1] of each destination time;
    times outside [t_src[0], t_src[-1]] clamp to the ends. Needs at least two source samples."""
    if method not in ("linear", "nearest"):
        raise ValueError(f"unknown resampling method {method!r}; use 'linear' or 'nearest'")
    t_src = np.asarray(t_src, np.float64)
    t_dst = np.clip(np.asarray(t_dst, np.float64), t_src[0], t_src[-1])
    i1 = np.clip(np.searchsorted(t_src, t_dst, side="right"), 1, len(t_src) - 1)
    i0 = i1 - 1
    span = t_src[i1] - t_src[i0]
    w = np.clip((t_dst - t_src[i0]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    return i0, i1, w


def resample_positions(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray, method: str = "linear") -> np.ndarray:
    """Resample values (N, ...) sampled at increasing times t_src (N,) to t_dst (M,), float64.

    ``linear`` interpolates between the bracketing samples; ``nearest`` takes the closest one.
    """
    v = np.asarray(values, np.float64)
    if len(v) == 1:
        return np.repeat(v, len(t_dst), axis=0)
    i0, i1, w = _bracket(t_src, t_dst, method)
    if method == "nearest":
        return v[np.where(w < 0.5, i0, i1)]
    w = w.reshape((-1,) + (1,) * (v.ndim - 1))
    return (1 - w) * v[i0] + w * v[i1]


def resample_quats(t_src: np.ndarray, q: np.ndarray, t_dst: np.ndarray, method: str = "linear") -> np.ndarray:
    """Resample (x, y, z, w) quaternions (N, 4) by slerp (``linear``) or ``nearest``, with sign continuity."""
    q = quat_continuity(np.asarray(q, np.float64))
    if len(q) == 1:
        return np.repeat(q, len(t_dst), axis=0)
    i0, i1, w = _bracket(t_src, t_dst, method)
    if method == "nearest":
        return q[np.where(w < 0.5, i0, i1)]
    return quat_slerp(q[i0], q[i1], w)


def index_at_or_before(t_src: np.ndarray, t_dst: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Index of the source sample at or before each destination time (for discrete fields)."""
    i = np.searchsorted(np.asarray(t_src, np.float64), np.asarray(t_dst, np.float64) + tol, side="right") - 1
    return np.clip(i, 0, len(t_src) - 1)
