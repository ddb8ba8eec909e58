"""The bilinear layered query compiled with numba: the same arithmetic as ``LayeredField``'s numpy path.

The numpy path (``LayeredField.query_reference``) is the reference; this kernel must give the same
float64 values bit for bit (tests compare them). Chunks load lazily and the loader is Python, so the
caller works in passes over the points: ``finite_box`` bounds the cells the points read; the caller
fills a dense table over that box's chunks with their slab blocks, −1 for chunks the field has not
asked its loader for yet; ``bilinear`` evaluates the query per point with no temporaries, leaving
−inf at the points that need a −1 chunk. Only where there are such points does the caller ask
``missing_chunks`` which chunks those are, load them and run ``bilinear`` again; once a field has
loaded the chunks its queries need, a query is the two passes.

Speed comes from two things. A cell's layers are one row of the (rows, W) float32 slab (W·4 bytes),
and most cells hold at most one layer, so ``_nearest`` looks past the first slot only where the
second holds a layer. And points arrive in any order over a stage of many megabytes, so each slab
read would wait on memory (random points over a 54-chunk, 8-slot stage ran 6× slower than over a
cached one): ``bilinear`` prefetches the neighbour rows of the point ``PREFETCH_AHEAD`` ahead and
keeps the row it found for that point's turn, whose reads then find them in cache.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from terrain_scan.trn2 import CELL_COUNT, CELLS

PREFETCH_AHEAD = 16  # points: about the memory latency over the time one point takes (a power of 2)


@intrinsic
def _prefetch(typingctx, H, offset):  # pragma: no cover - compiled
    """Hint the cache line of element ``offset`` of C-contiguous ``H`` into the caches: LLVM's
    ``llvm.prefetch`` (a read, high locality, data), which numba does not expose. A hint only: it never
    faults, so any offset is safe."""

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.gep(ary.data, [args[1]])  # not inbounds: the offset may point anywhere
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [ptr.type, i32, i32, i32])
        builder.call(cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0"), [ptr, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return types.void(H, types.intp), codegen


@numba.njit(cache=True, nogil=True)
def finite_box(x, z, ref):  # pragma: no cover - compiled
    """(count, gx_min, gx_max, gz_min, gz_max): how many points have finite x, z and ref, and the bounds
    of floor(x − 0.5), floor(z − 0.5) (the lower-left neighbour's cell) over those points."""
    count = 0
    gx_min = gz_min = np.inf
    gx_max = gz_max = -np.inf
    for i in range(x.size):
        if np.isfinite(x[i]) and np.isfinite(z[i]) and np.isfinite(ref[i]):
            count += 1
            gx = np.floor(x[i] - 0.5)
            gz = np.floor(z[i] - 0.5)
            gx_min = min(gx_min, gx)
            gx_max = max(gx_max, gx)
            gz_min = min(gz_min, gz)
            gz_max = max(gz_max, gz)
    return count, gx_min, gx_max, gz_min, gz_max


@numba.njit(nogil=True, inline="always")
def _nearest(H, row, ref):  # pragma: no cover - compiled
    """The layer of slab row ``row`` nearest ``ref`` (first on ties, +inf when the row is empty).

    The row is sorted with +inf after its layers, so a row whose second slot is +inf holds at most
    one layer: its first slot is the answer, whatever ``ref``."""
    best = np.float64(H[row, 0])
    if H.shape[1] > 1 and H[row, 1] != np.inf:
        dist = abs(best - ref)
        for s in range(1, H.shape[1]):
            h = np.float64(H[row, s])
            d = abs(h - ref)
            better = d < dist
            best = h if better else best
            dist = d if better else dist
    return best


@numba.njit(nogil=True, inline="always")
def _block_row(x, z, ref, table, cx0, cz0, nx, H):  # pragma: no cover - compiled
    """Slab row r of the lower-left neighbour of point (x, z) where its 2 × 2 neighbours are rows r,
    r + 1, r + 100, r + 101 of one loaded chunk, with those rows prefetched; −1 elsewhere (a point
    that is not finite, on a chunk's last column or row, or in a chunk not loaded yet)."""
    if not (np.isfinite(x) and np.isfinite(z) and np.isfinite(ref)):
        return -1
    gx0 = np.int64(np.floor(x - 0.5))
    gz0 = np.int64(np.floor(z - 0.5))
    cx = gx0 // CELLS
    cz = gz0 // CELLS
    col = gx0 - cx * CELLS
    row = gz0 - cz * CELLS
    b = table[(cz - cz0) * nx + (cx - cx0)]
    if col == CELLS - 1 or row == CELLS - 1 or b < 0:
        return -1
    r = b * CELL_COUNT + row * CELLS + col
    width = H.shape[1]
    _prefetch(H, r * width)  # rows r, r + 1: first and last element, as the pair may span two cache lines
    _prefetch(H, (r + 1) * width + width - 1)
    _prefetch(H, (r + CELLS) * width)
    _prefetch(H, (r + CELLS + 1) * width + width - 1)
    return r


@numba.njit(nogil=True, inline="always")
def _query_point(x, z, ref, r0, table, cx0, cz0, nx, H, match_m, min_fraction):  # pragma: no cover - compiled
    """The bilinear layered query at one finite point (``field``'s definition, step for step), given
    ``_block_row`` of the point; −inf (which the query never gives) where a neighbour's chunk is −1
    in the table."""
    xs = x - 0.5
    zs = z - 0.5
    gxf = np.floor(xs)
    gzf = np.floor(zs)
    fx = xs - gxf  # in [0, 1)
    fz = zs - gzf
    # neighbours k = 0..3 = (gx0, gz0), (gx0 + 1, gz0), (gx0, gz0 + 1), (gx0 + 1, gz0 + 1) at slab rows r0..r3
    if r0 >= 0:
        r1 = r0 + 1
        r2 = r0 + CELLS
        r3 = r2 + 1
    else:  # past column or row 99 a neighbour lies in the next chunk along x or z
        gx0 = np.int64(gxf)
        gz0 = np.int64(gzf)
        cx = gx0 // CELLS
        cz = gz0 // CELLS
        col = gx0 - cx * CELLS
        row = gz0 - cz * CELLS
        t0 = (cz - cz0) * nx + (cx - cx0)
        t1 = t0 + 1 if col == CELLS - 1 else t0
        t2 = t0 + nx if row == CELLS - 1 else t0
        t3 = t2 + (t1 - t0)
        b0, b1, b2, b3 = table[t0], table[t1], table[t2], table[t3]
        if b0 < 0 or b1 < 0 or b2 < 0 or b3 < 0:
            return -np.inf  # a neighbour's chunk is not loaded yet
        col1 = 0 if col == CELLS - 1 else col + 1
        row1 = 0 if row == CELLS - 1 else row + 1
        r0 = b0 * CELL_COUNT + row * CELLS + col
        r1 = b1 * CELL_COUNT + row * CELLS + col1
        r2 = b2 * CELL_COUNT + row1 * CELLS + col
        r3 = b3 * CELL_COUNT + row1 * CELLS + col1
    contain = (r1 if fx >= 0.5 else r0) if fz < 0.5 else (r3 if fx >= 0.5 else r2)
    fx = max(fx, min_fraction)
    fz = max(fz, min_fraction)
    ax = 1.0 - fx
    az = 1.0 - fz

    anchor = _nearest(H, contain, ref)
    if anchor == np.inf:  # the containing cell is empty: the nearest among the four, the first on ties
        anchor = _nearest(H, r0, ref)
        dist = abs(anchor - ref)
        h = _nearest(H, r1, ref)
        d = abs(h - ref)
        if d < dist:
            anchor, dist = h, d
        h = _nearest(H, r2, ref)
        d = abs(h - ref)
        if d < dist:
            anchor, dist = h, d
        h = _nearest(H, r3, ref)
        d = abs(h - ref)
        if d < dist:
            anchor, dist = h, d
        if anchor == np.inf:
            return np.nan

    h0 = _nearest(H, r0, anchor)
    h1 = _nearest(H, r1, anchor)
    h2 = _nearest(H, r2, anchor)
    h3 = _nearest(H, r3, anchor)
    u0 = abs(h0 - anchor) <= match_m  # false for an empty row
    u1 = abs(h1 - anchor) <= match_m
    u2 = abs(h2 - anchor) <= match_m
    u3 = abs(h3 - anchor) <= match_m
    w0 = ax * az if u0 else 0.0
    w1 = fx * az if u1 else 0.0
    w2 = ax * fz if u2 else 0.0
    w3 = fx * fz if u3 else 0.0
    h0 = h0 if u0 else 0.0
    h1 = h1 if u1 else 0.0
    h2 = h2 if u2 else 0.0
    h3 = h3 if u3 else 0.0
    tot = ((w0 + w1) + w2) + w3  # the reference's order and zeros, so that the bits match
    num = ((w0 * h0 + w1 * h1) + w2 * h2) + w3 * h3
    return num / tot if tot > 0 else np.nan


@numba.njit(cache=True, nogil=True)
def bilinear(x, z, ref, table, cx0, cz0, nx, H, match_m, min_fraction, out):  # pragma: no cover - compiled
    """``out[i]`` = the bilinear layered query at point i (NaN where x, z or ref is not finite, or no layer).

    ``table`` maps chunk (cx0 + k % nx, cz0 + k // nx) to its slab block, −1 where not loaded yet; every
    finite point must lie in its box. ``H`` is the (rows, W) float32 slab. A point that needs a −1 chunk
    gets −inf; returns how many did (``missing_chunks`` names the chunks).

    ``_block_row`` runs ``PREFETCH_AHEAD`` points ahead of the query (its rows prefetched), and a ring
    of its results carries them to the point's turn."""
    n = x.size
    ring = np.empty(2 * PREFETCH_AHEAD, np.int64)
    mask = 2 * PREFETCH_AHEAD - 1
    for j in range(min(PREFETCH_AHEAD, n)):
        ring[j] = _block_row(x[j], z[j], ref[j], table, cx0, cz0, nx, H)
    left = 0
    for i in range(n):
        j = i + PREFETCH_AHEAD
        if j < n:
            ring[j & mask] = _block_row(x[j], z[j], ref[j], table, cx0, cz0, nx, H)
        if np.isfinite(x[i]) and np.isfinite(z[i]) and np.isfinite(ref[i]):
            v = _query_point(x[i], z[i], ref[i], ring[i & mask], table, cx0, cz0, nx, H, match_m, min_fraction)
            left += v == -np.inf
            out[i] = v
        else:
            out[i] = np.nan
    return left


@numba.njit(cache=True, nogil=True)
def missing_chunks(x, z, out, table, cx0, cz0, nx):  # pragma: no cover - compiled
    """(nx·nz,) uint8: 1 for each chunk −1 in ``table`` that a neighbour of a point ``bilinear`` left at
    −inf lies in."""
    flags = np.zeros(table.size, np.uint8)
    for i in range(x.size):
        if out[i] != -np.inf:
            continue
        gx0 = np.int64(np.floor(x[i] - 0.5))
        gz0 = np.int64(np.floor(z[i] - 0.5))
        for dz in range(2):
            cz = (gz0 + dz) // CELLS
            for dx in range(2):
                t = (cz - cz0) * nx + ((gx0 + dx) // CELLS - cx0)
                if table[t] < 0:
                    flags[t] = 1
    return flags
