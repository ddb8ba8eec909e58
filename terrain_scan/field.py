"""Querying the layered height field: heights, normals and the dynamics model's terrain features.

A ``LayeredField`` sits over sparse TRN2 chunks and loads, lazily, only the chunks a query touches.
Inside, every loaded chunk becomes one block of 10 000 rows in a slab: row = block × 10 000 + cell,
with the cell's valid layers sorted by height and ``+inf`` in the slots after them (block 0 is the
all-empty block every missing chunk maps to). ``W`` — the slab width — is the most layers any loaded
cell holds, so a single-layer stage costs one slot per cell whatever its files' ``max_layers``. The
slab is row-major, a cell's W heights side by side, and keeps the files' float32 heights as they are
(exact); every computation on them is float64.

The query (``query(x, z, ref_y)``, exact definition; ``docs/formats.md`` repeats it):

1. The four neighbours are the cells whose centres (gx + 0.5, gz + 0.5) surround the point:
   gx0 = floor(x − 0.5), gz0 = floor(z − 0.5), fx = (x − 0.5) − gx0, fz = (z − 0.5) − gz0, and
   k = 0..3 = (gx0, gz0), (gx0 + 1, gz0), (gx0, gz0 + 1), (gx0 + 1, gz0 + 1) with bilinear weights
   w = (1 − fx)(1 − fz), fx(1 − fz), (1 − fx)fz, fx·fz, fx and fz first clamped below at
   ``MIN_FRACTION`` (1e-9) so that every weight is positive (a point exactly on a hole cell's centre
   still takes its value from the neighbours that hold data; elsewhere this moves a value by < 1e-8 m).
2. Anchor a: the valid layer of the containing cell (floor(x), floor(z)) nearest ``ref_y``. If that
   cell has none, the valid layer nearest ``ref_y`` among the four neighbours.
3. Each neighbour contributes its valid layer nearest a, if within ``MATCH_M`` of a; otherwise it is
   left out, and the weights of the neighbours that contribute are renormalised.
4. query = Σ w_k h_k / Σ w_k over the contributing neighbours; NaN where none of the four holds a
   layer, or where x, z or ref_y is not finite. Ties pick the lower layer.

Every value lies within ``MATCH_M`` of one stored layer, so with layers farther apart than
2·``MATCH_M`` a floor and the roof above it never mix. Where all four neighbours hold the same layer
structure the surface is the continuous bilinear interpolant of the cell centres (it reproduces a
plane exactly); it jumps only where the layer the anchor picks changes (a deck edge, a hole).
``normal`` uses the same neighbours and weights on the stored layer normals, renormalised.

The torch path (``DenseRegion``, ``query_torch``, ``normal_torch`` and the ``*_torch`` features) runs
the same arithmetic on a dense block of cells copied from the slab, on any device.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from terrain_scan import _kernel
from terrain_scan.trn2 import CELL_COUNT, CELLS, Chunk, find_chunks, read_chunk

if TYPE_CHECKING:
    import torch

MATCH_M = 2.0  # a neighbour's layer joins the interpolation when within this of the anchor layer (m)
MIN_FRACTION = 1e-9  # fx, fz are clamped below at this so that every neighbour's weight is positive
_EMPTY_BLOCK = 0
_DENSE_TABLE_MAX = 1 << 20  # chunk boxes up to this many chunks use a lookup table, larger ones np.unique
_OFFSET_X = np.array([0, 1, 0, 1])  # neighbour k = dz·2 + dx
_OFFSET_Z = np.array([0, 0, 1, 1])

ChunkLoader = Callable[[int, int], "Chunk | None"]


def _compact(chunk: Chunk) -> tuple[np.ndarray, np.ndarray]:
    """A chunk's layers as (10000, Wc) float32 heights sorted ascending, +inf after the valid ones,
    and (10000, Wc, 3) float32 normals; Wc ≥ 1 is the most valid layers of any of its cells."""
    h = chunk.cells["h"].astype(np.float32)
    valid = chunk.valid() & np.isfinite(h) & np.isfinite(chunk.cells["n"]).all(axis=2)
    h = np.where(valid, h, np.float32(np.inf))
    order = np.argsort(h, axis=1, kind="stable")
    width = max(int(valid.sum(axis=1).max(initial=0)), 1)
    order = order[:, :width]
    h = np.take_along_axis(h, order, axis=1)
    n = np.take_along_axis(chunk.cells["n"].astype(np.float32), order[:, :, None], axis=1)
    n[~np.isfinite(h)] = 0.0
    return h, n


class LayeredField:
    """A layered height field over sparse TRN2 chunks, loaded lazily through ``load_chunk(cx, cz)``."""

    def __init__(self, load_chunk: ChunkLoader):
        self._load = load_chunk
        self._block: dict[tuple[int, int], int] = {}
        self._h = np.full((CELL_COUNT, 1), np.inf, np.float32)  # (blocks·10000, W) slab; block 0 is all empty
        self._n = np.zeros((CELL_COUNT, 1, 3), np.float32)
        self._blocks = 1

    # -- construction ------------------------------------------------------------------------------

    @staticmethod
    def from_chunks(chunks: Mapping[tuple[int, int], Chunk]) -> LayeredField:
        """A field over in-memory chunks keyed by (cx, cz); absent keys are empty."""
        for (cx, cz), c in chunks.items():
            if (c.cx, c.cz) != (cx, cz):
                raise ValueError(f"chunk keyed ({cx}, {cz}) says it is ({c.cx}, {c.cz})")
        return LayeredField(lambda cx, cz: chunks.get((cx, cz)))

    @property
    def loaded_chunks(self) -> set[tuple[int, int]]:
        """(cx, cz) of every chunk the field asked its loader for (including those that had no data)."""
        return set(self._block)

    @property
    def width(self) -> int:
        """W: the most layers any loaded cell holds (at least 1)."""
        return self._h.shape[1]

    # -- the slab ----------------------------------------------------------------------------------

    def _add(self, key: tuple[int, int]) -> int:
        chunk = self._load(*key)
        if chunk is None:
            self._block[key] = _EMPTY_BLOCK
            return _EMPTY_BLOCK
        h, n = _compact(chunk)
        width = max(self.width, h.shape[1])
        capacity = self._h.shape[0] // CELL_COUNT
        if width > self.width or self._blocks == capacity:
            rows = (2 * capacity if self._blocks == capacity else capacity) * CELL_COUNT
            new_h = np.full((rows, width), np.inf, np.float32)
            new_n = np.zeros((rows, width, 3), np.float32)
            used = self._blocks * CELL_COUNT
            new_h[:used, : self.width] = self._h[:used]
            new_n[:used, : self.width] = self._n[:used]
            self._h, self._n = new_h, new_n
        b = self._blocks
        rows = slice(b * CELL_COUNT, (b + 1) * CELL_COUNT)
        self._h[rows] = np.inf
        self._n[rows] = 0.0
        self._h[rows, : h.shape[1]] = h
        self._n[rows, : h.shape[1]] = n
        self._blocks += 1
        self._block[key] = b
        return b

    def _chunk_blocks(self, cx: np.ndarray, cz: np.ndarray) -> np.ndarray:
        """Slab block of each chunk (cx, cz) (int64 arrays of one shape), loading new chunks."""
        if cx.size == 0:
            return np.zeros(cx.shape, np.int64)
        x0, z0 = int(cx.min()), int(cz.min())
        nx, nz = int(cx.max()) - x0 + 1, int(cz.max()) - z0 + 1
        if nx * nz <= _DENSE_TABLE_MAX:
            key = (cz - z0) * nx + (cx - x0)
            used = np.flatnonzero(np.bincount(key.ravel(), minlength=nx * nz))
            table = np.zeros(nx * nz, np.int64)
            for k in used.tolist():
                c = (x0 + k % nx, z0 + k // nx)
                table[k] = self._block[c] if c in self._block else self._add(c)
            return table[key]
        pairs, inverse = np.unique(np.stack([cx.ravel(), cz.ravel()], axis=1), axis=0, return_inverse=True)
        blocks = np.array([self._block[c] if c in self._block else self._add(c) for c in map(tuple, pairs.tolist())], np.int64)
        return blocks[inverse.ravel()].reshape(cx.shape)

    def _rows(self, gx: np.ndarray, gz: np.ndarray) -> np.ndarray:
        """Slab rows of global cells (int64 arrays of one shape)."""
        cx, cz = gx // CELLS, gz // CELLS
        cell = (gz - cz * CELLS) * CELLS + (gx - cx * CELLS)
        return self._chunk_blocks(cx, cz) * CELL_COUNT + cell

    def _rows4(self, gxf: np.ndarray, gzf: np.ndarray) -> np.ndarray:
        """Slab rows (N, 4) of the four neighbours of lower-left cells (gxf, gzf) (integral float64).

        Fast path: all four usually share the lower-left cell's chunk, at rows r, r + 1, r + 100, r + 101;
        the few whose block crosses a chunk edge (column or row 99) are redone cell by cell."""
        cxf, czf = np.floor(gxf / CELLS), np.floor(gzf / CELLS)
        colf, rowf = gxf - cxf * CELLS, gzf - czf * CELLS
        block = self._chunk_blocks(cxf.astype(np.int64), czf.astype(np.int64))
        r0 = block * CELL_COUNT + (rowf * CELLS + colf).astype(np.int64)
        rows = r0[:, None] + np.array([0, 1, CELLS, CELLS + 1])
        edge = np.flatnonzero((colf == CELLS - 1) | (rowf == CELLS - 1))
        if edge.size:
            gx = gxf[edge].astype(np.int64)[:, None] + _OFFSET_X
            gz = gzf[edge].astype(np.int64)[:, None] + _OFFSET_Z
            rows[edge] = self._rows(gx, gz)
        return rows

    def _slots(self, rows: np.ndarray) -> list[np.ndarray]:
        """The slab's heights at ``rows``, slot by slot: W float64 arrays of rows' shape."""
        flat, first = self._h.ravel(), rows * self.width  # a 1-D gather per slot: numpy's fastest
        return [flat[first + s].astype(np.float64) for s in range(self.width)]

    def _known_table(self, cx0: int, cz0: int, nx: int, nz: int) -> np.ndarray:
        """(nx·nz,) slab block of each chunk (cx0 + k % nx, cz0 + k // nx) of a box, −1 where the field has
        not asked its loader for the chunk yet."""
        table = np.full(nx * nz, -1, np.int64)
        if nx * nz <= len(self._block):
            for k in range(nx * nz):
                table[k] = self._block.get((cx0 + k % nx, cz0 + k // nx), -1)
        else:
            for (cx, cz), b in self._block.items():
                if 0 <= cx - cx0 < nx and 0 <= cz - cz0 < nz:
                    table[(cz - cz0) * nx + (cx - cx0)] = b
        return table

    # -- cells -------------------------------------------------------------------------------------

    def cell_layers(self, gx: np.ndarray, gz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Layers of global cells: heights (..., W) float64 sorted ascending with NaN in the empty slots
        after the valid ones, and normals (..., W, 3) float64 (NaN where empty)."""
        gx, gz = np.broadcast_arrays(np.asarray(gx, np.int64), np.asarray(gz, np.int64))
        rows = self._rows(gx, gz)
        h = self._h[rows].astype(np.float64)
        n = self._n[rows].astype(np.float64)
        empty = ~np.isfinite(h)
        h[empty] = np.nan
        n[empty] = np.nan
        return h, n

    def cell_height(self, x: np.ndarray, z: np.ndarray, ref_y: np.ndarray) -> np.ndarray:
        """Height (m) of the containing cell's valid layer nearest ``ref_y``, no interpolation; NaN if none."""
        x, z, ref = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (x, z, ref_y)))
        out = np.full(x.shape, np.nan)
        ok = np.isfinite(x) & np.isfinite(z) & np.isfinite(ref)
        xs, zs, rs = x[ok], z[ok], ref[ok]
        rows = self._rows(np.floor(xs).astype(np.int64), np.floor(zs).astype(np.int64))
        out[ok] = _nearest_np(self._slots(rows), rs)[0]
        out[~np.isfinite(out)] = np.nan
        return out

    # -- the bilinear query ------------------------------------------------------------------------

    def _select(self, x: np.ndarray, z: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For 1-D finite points: slab rows (N, 4), chosen slots (N, 4), heights (N, 4) and weights
        (N, 4) of the contributing neighbours (0 for the others)."""
        xs, zs = x - 0.5, z - 0.5
        gxf, gzf = np.floor(xs), np.floor(zs)
        fx, fz = xs - gxf, zs - gzf  # (N,) in [0, 1)
        rows = self._rows4(gxf, gzf)  # (N, 4)
        n = len(x)
        contain = np.arange(0, 4 * n, 4) + (fx >= 0.5) + 2 * (fz >= 0.5)  # flat index of the containing cell
        fx, fz = np.maximum(fx, MIN_FRACTION), np.maximum(fz, MIN_FRACTION)
        ax, az = 1.0 - fx, 1.0 - fz
        w = np.empty((n, 4))
        np.multiply(ax, az, out=w[:, 0])
        np.multiply(fx, az, out=w[:, 1])
        np.multiply(ax, fz, out=w[:, 2])
        np.multiply(fx, fz, out=w[:, 3])
        H = self._slots(rows)  # W × (N, 4)
        anchor, _ = _nearest_np([h.ravel()[contain] for h in H], ref)  # (N,)
        lost = np.flatnonzero(~np.isfinite(anchor))
        if lost.size:  # containing cell empty: the layer nearest ref_y among the four neighbours
            cand = np.stack([h[lost] for h in H], axis=-1).reshape(lost.size, -1)  # (n_lost, 4·W), neighbour-major
            anchor[lost] = cand[np.arange(lost.size), np.abs(cand - ref[lost, None]).argmin(1)]
        hk, slot = _nearest_np(H, anchor[:, None])  # (N, 4)
        use = np.abs(hk - anchor[:, None]) <= MATCH_M  # false for empty slots and a missing anchor
        return rows, slot, np.where(use, hk, 0.0), np.where(use, w, 0.0)

    def _query_flat(self, x, z, ref_y) -> tuple[tuple[int, ...], np.ndarray, tuple[np.ndarray, ...]]:
        x, z, ref = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (x, z, ref_y)))
        ok = (np.isfinite(x) & np.isfinite(z) & np.isfinite(ref)).ravel()
        with np.errstate(invalid="ignore"):  # inf − inf where a point has no anchor: compares false, as meant
            if ok.all():
                return x.shape, ok, self._select(x.ravel(), z.ravel(), ref.ravel())
            return x.shape, ok, self._select(x.ravel()[ok], z.ravel()[ok], ref.ravel()[ok])

    def query(self, x: np.ndarray, z: np.ndarray, ref_y: np.ndarray) -> np.ndarray:
        """Surface height (m, float64) at world (x, z) on the layer nearest ``ref_y``: the module's
        bilinear definition; NaN where no valid layer covers the point. Inputs broadcast.

        Runs the compiled kernel (``terrain_scan._kernel``); ``query_reference`` is the numpy path it
        matches bit for bit. Points spread over more than ``_DENSE_TABLE_MAX`` chunks take the numpy path."""
        x, z, ref = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (x, z, ref_y)))
        shape = x.shape
        x, z, ref = (np.ascontiguousarray(v).ravel() for v in (x, z, ref))
        count, gx_min, gx_max, gz_min, gz_max = _kernel.finite_box(x, z, ref)
        if count == 0:
            return np.full(shape, np.nan)[()]
        cx0, cz0 = int(gx_min) // CELLS, int(gz_min) // CELLS
        nx = (int(gx_max) + 1) // CELLS - cx0 + 1  # the upper neighbours lie one cell past the bounds
        nz = (int(gz_max) + 1) // CELLS - cz0 + 1
        if nx * nz > _DENSE_TABLE_MAX:
            return self.query_reference(x, z, ref).reshape(shape)[()]
        table, out = self._known_table(cx0, cz0, nx, nz), np.empty(x.size)
        if _kernel.bilinear(x, z, ref, table, cx0, cz0, nx, self._h, MATCH_M, MIN_FRACTION, out):
            # points needed chunks the field had not asked for: load exactly those, and run again
            for k in np.flatnonzero(_kernel.missing_chunks(x, z, out, table, cx0, cz0, nx)).tolist():
                table[k] = self._add((cx0 + k % nx, cz0 + k // nx))
            _kernel.bilinear(x, z, ref, table, cx0, cz0, nx, self._h, MATCH_M, MIN_FRACTION, out)
        return out.reshape(shape)[()]

    def query_reference(self, x: np.ndarray, z: np.ndarray, ref_y: np.ndarray) -> np.ndarray:
        """``query`` in plain numpy: the reference the compiled kernel is tested against."""
        shape, ok, (_, _, hk, w) = self._query_flat(x, z, ref_y)
        val = _combine(hk, w, xp=np)
        if ok.all():
            return val.reshape(shape)[()]
        out = np.full(ok.shape, np.nan)
        out[ok] = val
        return out.reshape(shape)[()]

    def normal(self, x: np.ndarray, z: np.ndarray, ref_y: np.ndarray) -> np.ndarray:
        """(..., 3) unit surface normal at (x, z) on the layer nearest ``ref_y``: the stored normals of
        the layers ``query`` interpolates, with its weights, renormalised; NaN where it is NaN."""
        shape, ok, (rows, slot, _, w) = self._query_flat(x, z, ref_y)
        nk = self._n.reshape(-1, 3)[rows * self.width + slot].astype(np.float64)  # (N, 4, 3)
        val = _combine_normals(nk, w, xp=np)
        out = np.full((ok.size, 3), np.nan)
        out[ok] = val
        return out.reshape(*shape, 3)


def open_stage(stage_dir: Path) -> LayeredField:
    """A read-only field over a stage directory's chunks, in our naming (``chunks/chunk_<cx>_<cz>.trn2``) or the
    upstream release's (``c_<cx>_<cz>.bin``, no manifest): ``trn2.find_chunks``, which names a missing, empty or
    foreign directory. A chunk the directory does not hold is empty."""
    files = find_chunks(stage_dir)

    def load(cx: int, cz: int) -> Chunk | None:
        path = files.get((cx, cz))
        return None if path is None else read_chunk(path, at=(cx, cz))

    return LayeredField(load)


# -- arithmetic ---------------------------------------------------------------------------------------
# The numpy path works slot by slot (fast for the few layers a cell holds); the torch path reduces over
# the slot axis. Both pick the first of equal distances and sum the four neighbours in the same order.


def _nearest_np(hs: list[np.ndarray], ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of layers given slot by slot (W arrays of one shape, +inf = empty), the one nearest ref and its
    slot; the first on ties (slots are sorted, so the lower). +inf where none."""
    best, slot = hs[0].copy(), np.zeros(hs[0].shape, np.int64)
    if len(hs) == 1:
        return best, slot
    dist = np.abs(best - ref)
    for s, h in enumerate(hs[1:], 1):
        d = np.abs(h - ref)
        better = d < dist
        np.copyto(best, h, where=better)
        np.copyto(dist, d, where=better)
        np.copyto(slot, s, where=better)
    return best, slot


def _combine(hk, w, xp):
    """Σ w_k h_k / Σ w_k over the four neighbours (N, 4); NaN where Σ w_k = 0."""
    tot = ((w[:, 0] + w[:, 1]) + w[:, 2]) + w[:, 3]
    num = ((w[:, 0] * hk[:, 0] + w[:, 1] * hk[:, 1]) + w[:, 2] * hk[:, 2]) + w[:, 3] * hk[:, 3]
    val = num / xp.where(tot > 0, tot, xp.ones_like(tot))
    return xp.where(tot > 0, val, xp.full_like(val, np.nan))


def _combine_normals(nk, w, xp):
    """Renormalised Σ w_k n_k over the four neighbours (N, 4, 3); NaN where it vanishes."""
    s = ((w[:, 0, None] * nk[:, 0] + w[:, 1, None] * nk[:, 1]) + w[:, 2, None] * nk[:, 2]) + w[:, 3, None] * nk[:, 3]
    norm = (s[:, 0] * s[:, 0] + s[:, 1] * s[:, 1] + s[:, 2] * s[:, 2])[:, None] ** 0.5
    ok = (norm > 1e-12) & ((w[:, 0] + w[:, 1] + w[:, 2] + w[:, 3]) > 0)[:, None]
    return xp.where(ok, s / xp.where(ok, norm, xp.ones_like(norm)), xp.full_like(s, np.nan))


def _nearest_torch(h: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Of layers h (..., W) (+inf = empty), the one nearest ref (...) and its slot; first on ties."""
    slot = (h - ref[..., None]).abs().argmin(dim=-1)
    return h.gather(-1, slot[..., None])[..., 0], slot


def _select_rows_torch(H: torch.Tensor, fx: torch.Tensor, fz: torch.Tensor, ref: torch.Tensor):
    """H (N, 4, W) layers of the four neighbours → slot (N, 4), heights (N, 4), weights (N, 4) of the
    contributing neighbours (0 for the others); the module's definition, as ``LayeredField._select``."""
    import torch

    n, _, width = H.shape
    contain = (fx >= 0.5).long() + 2 * (fz >= 0.5).long()  # neighbour k holding the point
    fx, fz = fx.clamp(min=MIN_FRACTION), fz.clamp(min=MIN_FRACTION)
    ax, az = 1.0 - fx, 1.0 - fz
    w = torch.stack([ax * az, fx * az, ax * fz, fx * fz], dim=-1)  # (N, 4)
    anchor, _ = _nearest_torch(H.gather(1, contain[:, None, None].expand(-1, 1, width))[:, 0], ref)  # (N,)
    # containing cell empty: the layer nearest ref_y among the four neighbours
    cand = H.reshape(n, 4 * width)
    fallback = cand.gather(1, (cand - ref[:, None]).abs().argmin(dim=1)[:, None])[:, 0]
    anchor = torch.where(torch.isfinite(anchor), anchor, fallback)
    hk, slot = _nearest_torch(H, anchor[:, None])  # (N, 4)
    use = (hk - anchor[:, None]).abs() <= MATCH_M  # false for empty slots and a missing anchor
    zero = torch.zeros_like(w)
    return slot, torch.where(use, hk, zero), torch.where(use, w, zero)


# -- the torch path --------------------------------------------------------------------------------------


@dataclass
class DenseRegion:
    """A dense block of cells [gx0, gx0 + nx) × [gz0, gz0 + nz) copied from a field, as tensors:
    ``h`` (nz·nx, W) heights (+inf = empty slot), ``n`` (nz·nx, W, 3) normals; row = iz·nx + ix."""

    gx0: int
    gz0: int
    nx: int
    nz: int
    h: torch.Tensor
    n: torch.Tensor

    @staticmethod
    def from_field(
        field: LayeredField,
        x_min: float,
        x_max: float,
        z_min: float,
        z_max: float,
        dtype: torch.dtype | None = None,
        device: str | torch.device = "cpu",
    ) -> DenseRegion:
        """The cells ``query`` needs for any point in [x_min, x_max] × [z_min, z_max] (world m)."""
        import torch

        gx0, gz0 = int(np.floor(x_min - 0.5)), int(np.floor(z_min - 0.5))
        nx, nz = int(np.floor(x_max - 0.5)) + 2 - gx0, int(np.floor(z_max - 0.5)) + 2 - gz0
        gz, gx = np.meshgrid(np.arange(gz0, gz0 + nz), np.arange(gx0, gx0 + nx), indexing="ij")
        rows = field._rows(gx.ravel(), gz.ravel())
        dtype = dtype or torch.float32
        h = torch.from_numpy(field._h[rows]).to(device=device, dtype=dtype)
        n = torch.from_numpy(field._n[rows]).to(device=device, dtype=dtype)
        return DenseRegion(gx0, gz0, nx, nz, h, n)


def _select_torch(region: DenseRegion, x, z, ref_y):
    import torch

    x, z, ref = torch.broadcast_tensors(x, z, ref_y)
    shape = x.shape
    x, z, ref = x.reshape(-1).to(region.h.dtype), z.reshape(-1).to(region.h.dtype), ref.reshape(-1).to(region.h.dtype)
    xs, zs = x - 0.5, z - 0.5
    gxf, gzf = torch.floor(xs), torch.floor(zs)
    fx, fz = xs - gxf, zs - gzf
    finite = torch.isfinite(x) & torch.isfinite(z) & torch.isfinite(ref)
    ix = torch.where(finite, gxf, torch.zeros_like(gxf)).long() - region.gx0
    iz = torch.where(finite, gzf, torch.zeros_like(gzf)).long() - region.gz0
    inside = finite & (ix >= 0) & (ix + 1 < region.nx) & (iz >= 0) & (iz + 1 < region.nz)
    base = torch.where(inside, iz * region.nx + ix, torch.zeros_like(ix))
    rows = base[:, None] + torch.tensor([0, 1, region.nx, region.nx + 1], device=base.device)  # (N, 4)
    zero = torch.zeros_like(fx)
    fx, fz, ref = torch.where(inside, fx, zero), torch.where(inside, fz, zero), torch.where(inside, ref, zero)
    slot, hk, w = _select_rows_torch(region.h[rows], fx, fz, ref)
    w = torch.where(inside[:, None], w, torch.zeros_like(w))
    return shape, rows, slot, hk, w


def query_torch(region: DenseRegion, x: torch.Tensor, z: torch.Tensor, ref_y: torch.Tensor) -> torch.Tensor:
    """``LayeredField.query`` on tensors (region's dtype and device); NaN outside the region."""
    import torch

    shape, _, _, hk, w = _select_torch(region, x, z, ref_y)
    return _combine(hk, w, xp=torch).reshape(shape)


def normal_torch(region: DenseRegion, x: torch.Tensor, z: torch.Tensor, ref_y: torch.Tensor) -> torch.Tensor:
    """``LayeredField.normal`` on tensors: (..., 3); NaN outside the region."""
    import torch

    shape, rows, slot, _, w = _select_torch(region, x, z, ref_y)
    width = region.h.shape[1]
    nk = region.n.reshape(-1, 3)[rows * width + slot]  # (N, 4, 3)
    return _combine_normals(nk, w, xp=torch).reshape(*shape, 3)


# -- dynamics features ---------------------------------------------------------------------------------


def _patch_offsets(size: int, cell_m: float, ahead_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(size,) offsets along forward (rows, increasing ahead) and along right (columns), metres."""
    centred = (np.arange(size) - (size - 1) / 2) * cell_m
    return ahead_m + centred, centred


def _heading_xz(R, forward_axis, xp):
    """Unit forward (fx, fz) on the ground plane of bodies R (N, 3, 3) (local → world)."""
    f = (R * forward_axis[None, None, :]).sum(-1)  # (N, 3) = R @ forward_axis
    fx, fz = f[:, 0], f[:, 2]
    norm = (fx * fx + fz * fz) ** 0.5
    flat = norm < 1e-9  # body's forward points straight up or down: fall back to world +z
    safe = xp.where(flat, xp.ones_like(norm), norm)
    return xp.where(flat, xp.zeros_like(fx), fx / safe), xp.where(flat, xp.ones_like(fz), fz / safe)


def _patch_points(root, R, forward_axis, size, cell_m, ahead_m, xp):
    fwd, right = _patch_offsets(size, cell_m, ahead_m)
    if xp is not np:
        fwd = xp.as_tensor(fwd, dtype=root.dtype, device=root.device)
        right = xp.as_tensor(right, dtype=root.dtype, device=root.device)
    hx, hz = _heading_xz(R, forward_axis, xp)  # (N,)
    # right = forward × up = (−fz, 0, fx)
    px = root[:, 0, None, None] + fwd[None, :, None] * hx[:, None, None] - right[None, None, :] * hz[:, None, None]
    pz = root[:, 2, None, None] + fwd[None, :, None] * hz[:, None, None] + right[None, None, :] * hx[:, None, None]
    return px, pz  # (N, size, size)


def egocentric_patch(
    field: LayeredField,
    root_world: np.ndarray,
    R: np.ndarray,
    forward_axis: np.ndarray,
    size: int = 11,
    cell_m: float = 0.4,
    ahead_m: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Terrain heights (N, size, size) relative to the root's y (m) and the mask of known ones.

    Samples ``query(·, ·, ref_y = root y)`` on a size × size grid of ``cell_m`` spacing centred
    ``ahead_m`` ahead of the root along the body's forward axis (``R @ forward_axis``, R local →
    world) projected on the ground plane, yaw-aligned: row i lies (i − (size−1)/2)·cell_m + ahead_m
    along forward (row 0 nearest the body), column j (j − (size−1)/2)·cell_m along the body's right
    (forward × up). The patch is NaN where the terrain is unknown; a model feeds
    ``nan_to_num(patch, 0)`` with ``mask`` as a second channel."""
    root = np.asarray(root_world, np.float64)
    px, pz = _patch_points(root, np.asarray(R, np.float64), np.asarray(forward_axis, np.float64), size, cell_m, ahead_m, np)
    ref = np.broadcast_to(root[:, 1, None, None], px.shape)
    patch = field.query(px, pz, ref) - root[:, 1, None, None]
    return patch, np.isfinite(patch)


def egocentric_patch_torch(
    region: DenseRegion,
    root_world: torch.Tensor,
    R: torch.Tensor,
    forward_axis: torch.Tensor,
    size: int = 11,
    cell_m: float = 0.4,
    ahead_m: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``egocentric_patch`` on tensors over a region that covers the patches."""
    import torch

    root = root_world.to(region.h.dtype)
    px, pz = _patch_points(root, R.to(root.dtype), forward_axis.to(root.dtype), size, cell_m, ahead_m, torch)
    ref = root[:, 1, None, None].expand_as(px)
    patch = query_torch(region, px, pz, ref) - root[:, 1, None, None]
    return patch, torch.isfinite(patch)


def joint_clearances(field: LayeredField, joints_world: np.ndarray, ref_y: np.ndarray) -> np.ndarray:
    """(N, K) signed clearance y_j − H(x_j, z_j) (m), H the surface layer nearest the entity's root
    height ``ref_y`` (N,), as the evaluation's penetration uses; NaN where H is unknown."""
    j = np.asarray(joints_world, np.float64)
    ref = np.broadcast_to(np.asarray(ref_y, np.float64)[:, None], j.shape[:2])
    return j[..., 1] - field.query(j[..., 0], j[..., 2], ref)


def joint_clearances_torch(region: DenseRegion, joints_world: torch.Tensor, ref_y: torch.Tensor) -> torch.Tensor:
    """``joint_clearances`` on tensors."""
    j = joints_world.to(region.h.dtype)
    ref = ref_y.to(j.dtype)[:, None].expand(j.shape[:2])
    return j[..., 1] - query_torch(region, j[..., 0], j[..., 2], ref)
