"""The bilinear layered query compiled with numba: the same arithmetic as ``LayeredField``'s numpy path.

The numpy path (``LayeredField.query_reference``) is the reference; this kernel must give the same
float64 values bit for bit (tests compare them). It works in two passes over the points, because
chunks load lazily and the loader is Python: ``mark_chunks`` flags, in a dense table over the
points' chunk bounding box, every chunk one of a point's four neighbours lies in; the caller loads
those and fills the table with their slab blocks; ``bilinear`` then evaluates the query per point
with no temporaries (one pass over the slab rows it needs).
"""

from __future__ import annotations

import numba
import numpy as np

from terrain_scan.trn2 import CELL_COUNT, CELLS


@numba.njit(cache=True, nogil=True)
def mark_chunks(x, z, ok, cx0, cz0, nx, nz):  # pragma: no cover - compiled
    """(nx·nz,) uint8: 1 for every chunk of the box (cx0, cz0, nx, nz) a neighbour of a point lies in."""
    used = np.zeros(nx * nz, np.uint8)
    for i in range(x.size):
        if not ok[i]:
            continue
        gx0 = np.int64(np.floor(x[i] - 0.5))
        gz0 = np.int64(np.floor(z[i] - 0.5))
        for dz in range(2):
            cz = (gz0 + dz) // CELLS
            for dx in range(2):
                cx = (gx0 + dx) // CELLS
                used[(cz - cz0) * nx + (cx - cx0)] = 1
    return used


@numba.njit(cache=True, nogil=True)
def _nearest(H, row, ref):  # pragma: no cover - compiled
    """The layer of slab row ``row`` nearest ``ref`` (first on ties, +inf when the row is empty)."""
    best = H[0, row]
    dist = abs(best - ref)
    for s in range(1, H.shape[0]):
        d = abs(H[s, row] - ref)
        if d < dist:
            best = H[s, row]
            dist = d
    return best


@numba.njit(cache=True, nogil=True)
def bilinear(x, z, ref, ok, table, cx0, cz0, nx, H, match_m, min_fraction, out):  # pragma: no cover - compiled
    """``out[i]`` = the bilinear layered query at point i (NaN where ``ok[i]`` is false or no layer)."""
    rows = np.empty(4, np.int64)
    w = np.empty(4)
    for i in range(x.size):
        if not ok[i]:
            out[i] = np.nan
            continue
        xs = x[i] - 0.5
        zs = z[i] - 0.5
        gxf = np.floor(xs)
        gzf = np.floor(zs)
        fx = xs - gxf
        fz = zs - gzf
        gx0 = np.int64(gxf)
        gz0 = np.int64(gzf)
        for k in range(4):
            gx = gx0 + (k & 1)
            gz = gz0 + (k >> 1)
            cx = gx // CELLS
            cz = gz // CELLS
            rows[k] = table[(cz - cz0) * nx + (cx - cx0)] * CELL_COUNT + (gz - cz * CELLS) * CELLS + (gx - cx * CELLS)
        contain = (1 if fx >= 0.5 else 0) + (2 if fz >= 0.5 else 0)
        fx = max(fx, min_fraction)
        fz = max(fz, min_fraction)
        ax = 1.0 - fx
        az = 1.0 - fz
        w[0] = ax * az
        w[1] = fx * az
        w[2] = ax * fz
        w[3] = fx * fz
        r = ref[i]
        anchor = _nearest(H, rows[contain], r)
        if not np.isfinite(anchor):  # the containing cell is empty: the nearest among all four
            anchor = H[0, rows[0]]
            dist = abs(anchor - r)
            for k in range(4):
                for s in range(H.shape[0]):
                    d = abs(H[s, rows[k]] - r)
                    if d < dist:
                        anchor = H[s, rows[k]]
                        dist = d
        tot = 0.0
        num = 0.0
        for k in range(4):
            hk = _nearest(H, rows[k], anchor)
            if abs(hk - anchor) <= match_m:  # false for inf − inf
                tot += w[k]
                num += w[k] * hk
        out[i] = num / tot if tot > 0 else np.nan
    return out
