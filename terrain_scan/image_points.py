"""One depth frame's pixels as world points, in whole-array numpy: back-projection through the recorded pinhole
camera, image-space normals, the subsampled grid, and ``grid_points_reference`` (the definition
``_points_kernel.grid_points`` follows)."""

from __future__ import annotations

import numpy as np

from marionette.geometry import quat_to_matrix

from .depth import depth_edges


def backproject(z: np.ndarray, K: np.ndarray, pos: np.ndarray, rot_xyzw: np.ndarray) -> np.ndarray:
    """z-depth (H, W) → world points (H, W, 3) (NaN where z is NaN); OpenGL camera, pixel centres at +½."""
    H, W = z.shape
    fx, fy, cx, cy = (float(k) for k in K)
    u = np.arange(W) + 0.5
    v = np.arange(H) + 0.5
    z = z.astype(np.float64)
    p_cam = np.stack([((u[None, :] - cx) / fx) * z, (-(v[:, None] - cy) / fy) * z, -z], axis=-1)  # (H, W, 3)
    R = quat_to_matrix(np.asarray(rot_xyzw, dtype=np.float64))  # camera-to-world (3, 3)
    return p_cam @ R.T + np.asarray(pos, dtype=np.float64)


def image_normals(G: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of an organised point grid (H, W, 3) by central differences along the row
    and the column, turned to face the camera at ``eye``; NaN on the border and wherever a neighbour is
    missing."""
    a = np.full_like(G, np.nan)
    b = np.full_like(G, np.nan)
    a[:, 1:-1] = G[:, 2:] - G[:, :-2]
    b[1:-1] = G[2:] - G[:-2]
    n = np.cross(a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        return np.where((np.sum(n * (eye - G), axis=-1) < 0)[..., None], -n, n)


def subsampled(codes: np.ndarray, K: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    """(codes, K (fx, fy, cx, cy)) with every ``f``-th pixel of every ``f``-th row kept, from offset o = f // 2,
    and the intrinsics of that image: a kept pixel's centre j + ½ sits at source pixel f·j + o + ½, so
    fx' = fx / f, fy' = fy / f, cx' = (cx − o − ½) / f + ½ (cy' likewise). f = 1 returns both unchanged."""
    if f < 1:
        raise ValueError(f"depth subsample must be at least 1, not {f}")
    if f == 1:
        return codes, np.asarray(K, np.float64)
    o = f // 2
    fx, fy, cx, cy = (float(k) for k in K)
    return codes[o::f, o::f], np.array([fx / f, fy / f, (cx - o - 0.5) / f + 0.5, (cy - o - 0.5) / f + 0.5])


def grid_points_reference(
    z: np.ndarray,
    z_raw: np.ndarray,
    K: np.ndarray,
    pos: np.ndarray,
    rot_xyzw: np.ndarray,
    max_depth_m: float = 20.0,
    edge_rel: float = 0.1,
    image_normal_y: float = 0.8,
) -> np.ndarray:
    """``_points_kernel.grid_points`` in whole-array numpy passes: the definition the compiled kernel follows.

    Pixels next to a depth edge of ``z_raw`` and depths of ``z`` beyond ``max_depth_m`` are dropped, the rest
    back-projected, and those whose image normal has ny < ``image_normal_y`` dropped; the points in row-major
    pixel order."""
    z = z.copy()
    z[depth_edges(z_raw, edge_rel)] = np.nan
    z[~(z <= max_depth_m)] = np.nan  # NaN stays NaN
    G = backproject(z, K, pos, rot_xyzw)
    if image_normal_y > 0:
        eye = np.asarray(pos, dtype=np.float64)
        steep = ~(image_normals(G, eye)[..., 1] >= image_normal_y)  # NaN normals (borders, holes) count as steep
        G[steep] = np.nan
    P = G.reshape(-1, 3)
    return P[np.isfinite(P).all(1)]
