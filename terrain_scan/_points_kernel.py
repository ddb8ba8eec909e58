"""The scan's per-frame point steps compiled with numba: one pass each over a frame's pixels or points.

``grid_points`` does, pixel by pixel, what ``image_points.grid_points_reference`` does with whole-array numpy
passes (``depth.depth_edges``, ``image_points.backproject``, ``image_points.image_normals``): the same float32
edge test and the same float64 arithmetic, term by term, except that the camera rotation is applied as three
explicit dot products where numpy's matmul leaves the order of a dot product's terms to BLAS (points agree
to ~1e-12 m; tests compare the two). ``voxel_add`` sums points per voxel in point order, as ``np.bincount`` sums them
(``accumulate.VoxelMeans``); ``character_hits`` makes
``accumulate.character_mask``'s test with its arithmetic, its dot products summed left to right (numpy's
``einsum`` may order the three terms otherwise: a decision could differ only for a point within a rounding
error of a capsule's surface).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, inline="always")
def _jump(a, b, rel):  # pragma: no cover - compiled
    """``depth_edges``' test of two float32 depths (+inf where invalid): not within ``rel`` · the nearer one."""
    return not (abs(a - b) <= rel * min(a, b))


@numba.njit(nogil=True, inline="always")
def _edge(zz, i, j, rel):  # pragma: no cover - compiled
    """Whether pixel (i, j) of ``zz`` jumps against one of its 4-neighbours (``depth.depth_edges``)."""
    H, W = zz.shape
    c = zz[i, j]
    return (
        (i > 0 and _jump(zz[i - 1, j], c, rel))
        or (i + 1 < H and _jump(zz[i + 1, j], c, rel))
        or (j > 0 and _jump(zz[i, j - 1], c, rel))
        or (j + 1 < W and _jump(zz[i, j + 1], c, rel))
    )


@numba.njit(cache=True, nogil=True, error_model="numpy")
def grid_points(z, z_raw, K, R, pos, max_depth_m, edge_rel, image_normal_y):  # pragma: no cover - compiled
    """A frame's kept world points (P, 3) float64, in row-major pixel order.

    ``z`` (H, W) float32 smoothed z-depth and ``z_raw`` the unsmoothed one (NaN: no depth); ``K`` (fx, fy, cx,
    cy); ``R`` (3, 3) camera-to-world; ``pos`` (3,) the camera. A pixel is kept when its ``z`` is at most
    ``max_depth_m``, no 4-neighbour of ``z_raw`` jumps against it by more than ``edge_rel`` · the nearer depth,
    and (``image_normal_y`` > 0) its image normal (central differences of the back-projected grid, turned to
    face the camera) has ny ≥ ``image_normal_y``; a pixel on the border or beside a dropped one has no normal."""
    H, W = z.shape
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    rel = np.float32(edge_rel)
    far = np.float32(max_depth_m)
    zz = np.empty((H, W), np.float32)  # z_raw with +inf where it has no depth, as ``depth_edges`` reads it
    for i in range(H):
        for j in range(W):
            zz[i, j] = z_raw[i, j] if np.isfinite(z_raw[i, j]) else np.inf
    G = np.full((H, W, 3), np.nan)
    for i in range(H):
        v = i + 0.5
        for j in range(W):
            if not (z[i, j] <= far) or _edge(zz, i, j, rel):
                continue
            d = np.float64(z[i, j])
            p0 = ((j + 0.5 - cx) / fx) * d
            p1 = (-(v - cy) / fy) * d
            p2 = -d
            for k in range(3):
                G[i, j, k] = ((p0 * R[k, 0] + p1 * R[k, 1]) + p2 * R[k, 2]) + pos[k]
    keep = np.zeros((H, W), np.bool_)
    n = 0
    for i in range(H):
        for j in range(W):
            if np.isnan(G[i, j, 0]):
                continue
            if image_normal_y > 0 and not _faces_up(G, pos, i, j, image_normal_y):
                continue
            keep[i, j] = True
            n += 1
    out = np.empty((n, 3))
    m = 0
    for i in range(H):
        for j in range(W):
            if keep[i, j]:
                out[m] = G[i, j]
                m += 1
    return out


@numba.njit(nogil=True, inline="always")
def _faces_up(G, eye, i, j, min_ny):  # pragma: no cover - compiled
    """``image_points.image_normals``' ny at (i, j) (facing ``eye``) is at least ``min_ny``; False where it is NaN."""
    H, W = G.shape[0], G.shape[1]
    if i == 0 or j == 0 or i == H - 1 or j == W - 1:
        return False
    a0 = G[i, j + 1, 0] - G[i, j - 1, 0]
    a1 = G[i, j + 1, 1] - G[i, j - 1, 1]
    a2 = G[i, j + 1, 2] - G[i, j - 1, 2]
    b0 = G[i + 1, j, 0] - G[i - 1, j, 0]
    b1 = G[i + 1, j, 1] - G[i - 1, j, 1]
    b2 = G[i + 1, j, 2] - G[i - 1, j, 2]
    n0 = a1 * b2 - a2 * b1
    n1 = a2 * b0 - a0 * b2
    n2 = a0 * b1 - a1 * b0
    norm = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
    n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
    facing = (n0 * (eye[0] - G[i, j, 0]) + n1 * (eye[1] - G[i, j, 1])) + n2 * (eye[2] - G[i, j, 2])
    ny = -n1 if facing < 0 else n1
    return ny >= min_ny


GRID_CELLS = 32  # a bone set's box is cut into at most this many cells a side for ``character_hits``


@numba.njit(cache=True, nogil=True, error_model="numpy")
def character_hits(points, a, b, r, lo, hi, first):  # pragma: no cover - compiled
    """(P,) bool: points within ``r[s]`` of a bone of set s. Set s holds bones ``first[s]`` … ``first[s + 1]`` − 1
    (segments ``a`` → ``b``, (S, 3)) in its box ``lo[s]`` … ``hi[s]`` grown by ``r[s]``; a point is tested against
    the bones whose own grown box holds it, with ``accumulate.character_mask``'s arithmetic.

    The set's box is cut into a grid of cells (``GRID_CELLS`` a side at most, none narrower than 2 r) listing the
    bones whose grown box overlaps them: a point reads only its cell's list. A point lies in a cell of every box
    that holds it (one monotone floor maps both), so every bone that can hold it is on the list."""
    hit = np.zeros(len(points), np.bool_)
    for s in range(len(r)):
        rs = r[s]
        bones = np.arange(first[s], first[s + 1])
        blo = np.empty((len(bones), 3))  # each bone's grown box
        bhi = np.empty((len(bones), 3))
        for q in range(len(bones)):
            for d in range(3):
                blo[q, d] = min(a[bones[q], d], b[bones[q], d]) - rs
                bhi[q, d] = max(a[bones[q], d], b[bones[q], d]) + rs
        n = np.empty(3, np.int64)
        size = np.empty(3)
        for d in range(3):
            extent = hi[s, d] - lo[s, d]
            n[d] = max(1, int(min(float(GRID_CELLS), extent / (2 * rs)))) if rs > 0 and extent > 0 else 1
            size[d] = extent / n[d]
        start, listed = _bone_grid(blo, bhi, lo[s], size, n)
        r2 = rs * rs
        for p in range(len(points)):
            x, y, z = points[p, 0], points[p, 1], points[p, 2]
            if hit[p] or not (lo[s, 0] <= x <= hi[s, 0] and lo[s, 1] <= y <= hi[s, 1] and lo[s, 2] <= z <= hi[s, 2]):
                continue
            c = (_cell(x, lo[s, 0], size[0], n[0]) * n[1] + _cell(y, lo[s, 1], size[1], n[1])) * n[2]
            c += _cell(z, lo[s, 2], size[2], n[2])
            for e in range(start[c], start[c + 1]):
                q = listed[e]
                inside = blo[q, 0] <= x <= bhi[q, 0] and blo[q, 1] <= y <= bhi[q, 1] and blo[q, 2] <= z <= bhi[q, 2]
                if inside and _within(x, y, z, a[bones[q]], b[bones[q]], r2):
                    hit[p] = True
                    break
    return hit


@numba.njit(nogil=True, inline="always")
def _within(x, y, z, a, b, r2):  # pragma: no cover - compiled
    """Whether (x, y, z) lies within √r2 of segment a → b (``accumulate.character_mask``'s arithmetic)."""
    ap0, ap1, ap2 = x - a[0], y - a[1], z - a[2]
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    t = ((ap0 * ab0 + ap1 * ab1) + ap2 * ab2) / max((ab0 * ab0 + ab1 * ab1) + ab2 * ab2, 1e-12)
    t = min(max(t, 0.0), 1.0)
    d0, d1, d2 = ap0 - t * ab0, ap1 - t * ab1, ap2 - t * ab2
    return (d0 * d0 + d1 * d1) + d2 * d2 <= r2


@numba.njit(nogil=True, inline="always")
def _cell(x, lo, size, n):  # pragma: no cover - compiled
    """A coordinate's cell along one axis of a grid of n cells of ``size`` from ``lo`` (clamped; monotone in x)."""
    return min(max(np.int64(np.floor((x - lo) / size)), 0), n - 1) if size > 0 else 0


@numba.njit(nogil=True)
def _bone_grid(blo, bhi, lo, size, n):  # pragma: no cover - compiled
    """The boxes (rows of ``blo``, ``bhi``) overlapping each cell of an n[0] × n[1] × n[2] grid of cells of ``size``
    from ``lo``, as (start (cells + 1,), listed): cell c lists ``listed[start[c]:start[c + 1]]``."""
    cells = n[0] * n[1] * n[2]
    start = np.zeros(cells + 1, np.int64)
    listed = np.empty(0, np.int64)
    for fill in (False, True):  # count, then fill
        at = start.copy()
        for q in range(len(blo)):
            x0, x1 = _cell(blo[q, 0], lo[0], size[0], n[0]), _cell(bhi[q, 0], lo[0], size[0], n[0])
            y0, y1 = _cell(blo[q, 1], lo[1], size[1], n[1]), _cell(bhi[q, 1], lo[1], size[1], n[1])
            z0, z1 = _cell(blo[q, 2], lo[2], size[2], n[2]), _cell(bhi[q, 2], lo[2], size[2], n[2])
            for i in range(x0, x1 + 1):
                for j in range(y0, y1 + 1):
                    for k in range(z0, z1 + 1):
                        c = (i * n[1] + j) * n[2] + k
                        if fill:
                            listed[at[c]] = q
                            at[c] += 1
                        else:
                            start[c + 1] += 1
        if not fill:
            start = np.cumsum(start)
            listed = np.empty(start[cells], np.int64)
    return start, listed


_MIX = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x165667B19E3779F9))


@numba.njit(cache=True, nogil=True)
def voxel_add(table, index, sums, counts, m, points, start, voxel_m):  # pragma: no cover - compiled
    """Add ``points[start:]`` (P, 3) to running per-voxel sums; returns (m, stop).

    Voxel q < m has indices ``index[q]`` = floor(p / ``voxel_m``) (int64, (cap, 3)), ``sums[q]`` (cap, 3) and
    ``counts[q]`` (cap,); voxels are numbered in order of first appearance and a point's coordinates are
    added to its voxel's sums in point order. ``table`` (a power of 2 slots) maps a hash of the indices to the
    voxel number, −1 when free, with linear probing. Stops before point ``stop`` when its new voxel would fill
    ``cap`` or half the table (the caller grows them and goes on from ``stop``); ``stop`` = P when done."""
    mask = np.uint64(len(table) - 1)
    for p in range(start, len(points)):
        i0 = np.int64(np.floor(points[p, 0] / voxel_m))
        i1 = np.int64(np.floor(points[p, 1] / voxel_m))
        i2 = np.int64(np.floor(points[p, 2] / voxel_m))
        h = np.uint64(i0) * _MIX[0] + np.uint64(i1) * _MIX[1] + np.uint64(i2) * _MIX[2]
        slot = (h ^ (h >> np.uint64(29))) & mask
        while True:
            q = table[slot]
            if q < 0:
                if m + 1 > len(counts) or 2 * (m + 1) > len(table):
                    return m, p
                q = m
                table[slot] = q
                index[m, 0], index[m, 1], index[m, 2] = i0, i1, i2
                m += 1
                break
            if index[q, 0] == i0 and index[q, 1] == i1 and index[q, 2] == i2:
                break
            slot = (slot + np.uint64(1)) & mask
        for k in range(3):
            sums[q, k] += points[p, k]
        counts[q] += 1
    return m, len(points)


@numba.njit(cache=True, nogil=True)
def voxel_table(index, m, size):  # pragma: no cover - compiled
    """A ``voxel_add`` table of ``size`` slots (a power of 2 over 2 m) holding voxels 0 … m − 1 of ``index``."""
    table = np.full(size, -1, np.int64)
    mask = np.uint64(size - 1)
    for q in range(m):
        h = np.uint64(index[q, 0]) * _MIX[0] + np.uint64(index[q, 1]) * _MIX[1] + np.uint64(index[q, 2]) * _MIX[2]
        slot = (h ^ (h >> np.uint64(29))) & mask
        while table[slot] >= 0:
            slot = (slot + np.uint64(1)) & mask
        table[slot] = q
    return table
