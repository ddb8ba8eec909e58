"""Layers from observations: the deterministic merge rule of the layered height field.

An observation is (global cell, height, normal, hits, last_ts, hugs). Within a cell, observations sorted
by height are merged greedily: one joins the current layer while it lies within ``MERGE_M`` of that
layer's hit-weighted mean height, else it opens a new layer. A merged layer's height is the
hit-weighted mean, its normal the hit-weighted mean direction, its hits the sum, its last_ts the
newest, its hugs those of all its observations (bitwise or). At most ``max_layers`` layers per cell are kept (the least-hit dropped; ties keep the
lower). Sorting first makes the result independent of the order observations arrive in, so adding
recordings in any order gives the same layers; a recording's observations are kept apart (its
*contribution*) so that re-scanning it replaces them instead of counting its hits twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MERGE_M = 0.5
MAX_LAYERS = 8
# the four cell edges as bits of ``Observations.hugs``, each with the step to the cell across it: west, east,
# south, north (edge e's opposite, the same edge seen from the other cell, is e ^ 1)
EDGES = ((-1, 0), (1, 0), (0, -1), (0, 1))
AWAY = 1 << 4  # an ``Observations.hugs`` bit: some point lies away from every edge of its cell
SURFACE = 1 << 5  # an ``Observations.hugs`` bit: a surface by other evidence (a contact, a hole fill, an imported chunk)
ALIAS_FRACTION = 0.25  # a layer with under this share of its cell's strongest layer's hits ...
ALIAS_DOMINANCE = 5  # ... that a 4-neighbour holds at the same height with this many times its hits ...
ALIAS_SUPPORT = 16  # ... is an alias while it has fewer hits than this (one recording's 4 × 4 voxels of a cell at 0.25 m)


@dataclass
class Observations:
    """Columns of per-cell observations: cell (gx, gz int64), h, n (·, 3), hits (int64), ts (int64)."""

    gx: np.ndarray
    gz: np.ndarray
    h: np.ndarray
    n: np.ndarray
    hits: np.ndarray
    ts: np.ndarray
    # uint8 bits: the cell edges (``EDGES``) its points lie close to, and ``AWAY`` when some point lies away from
    # all four (a scan's measure, ``accumulate.edge_bits``); ``SURFACE`` (the default) where there are no points
    # to tell (a contact, a hole fill, an imported chunk): never an alias
    hugs: np.ndarray | None = None

    FIELDS = ("gx", "gz", "h", "n", "hits", "ts", "hugs")

    def __post_init__(self) -> None:
        if self.hugs is None:
            self.hugs = np.full(len(self.h), SURFACE, np.uint8)

    @staticmethod
    def empty() -> Observations:
        return Observations(
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0),
            np.zeros((0, 3)),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
        )

    def __len__(self) -> int:
        return len(self.h)

    @staticmethod
    def concat(parts: list[Observations]) -> Observations:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Observations.empty()
        return Observations(*(np.concatenate([getattr(p, f) for p in parts]) for f in Observations.FIELDS))

    def take(self, idx: np.ndarray) -> Observations:
        return Observations(*(getattr(self, f)[idx] for f in Observations.FIELDS))

    def finite(self) -> Observations:
        """Drop observations with a non-finite height or normal (nothing NaN ever reaches a layer)."""
        ok = np.isfinite(self.h) & np.isfinite(self.n).all(axis=1) & (self.hits > 0)
        return self.take(np.flatnonzero(ok))


def merge(obs: Observations, merge_m: float = MERGE_M, max_layers: int = MAX_LAYERS) -> Observations:
    """Merge observations into layers (at most ``max_layers`` per cell); rows sorted by (gx, gz, h)."""
    obs = obs.finite()
    if not len(obs):
        return Observations.empty()
    # total order: cell, height, then the other fields, so equal heights merge identically in any input order
    order = np.lexsort((obs.hugs, obs.ts, obs.hits, obs.n[:, 2], obs.n[:, 1], obs.n[:, 0], obs.h, obs.gz, obs.gx))
    o = obs.take(order)
    h, w = o.h, o.hits.astype(np.float64)
    label = layer_labels(o.gx, o.gz, h, w, merge_m)
    n_layers = int(label[-1]) + 1
    hits = np.bincount(label, weights=w, minlength=n_layers)
    hm = np.bincount(label, weights=w * h, minlength=n_layers) / hits
    nsum = np.stack([np.bincount(label, weights=w * o.n[:, k], minlength=n_layers) for k in range(3)], axis=1)
    nn = np.linalg.norm(nsum, axis=1, keepdims=True)
    normal = np.where(nn > 1e-12, nsum / np.maximum(nn, 1e-12), np.array([0.0, 1.0, 0.0]))
    ts = np.zeros(n_layers, np.int64)
    np.maximum.at(ts, label, o.ts)
    first = np.flatnonzero(np.r_[True, label[1:] != label[:-1]])
    hugs = np.bitwise_or.reduceat(o.hugs, first)
    layers = Observations(o.gx[first], o.gz[first], hm, normal, np.rint(hits).astype(np.int64), ts, hugs)
    return _cap(layers, max_layers)


def layer_labels(gx: np.ndarray, gz: np.ndarray, h: np.ndarray, w: np.ndarray, merge_m: float = MERGE_M) -> np.ndarray:
    """Layer index (0, 1, ... over all cells) of each row by the greedy rule of the module docstring;
    rows sorted by (gx, gz, h), ``w`` their hit weights."""
    new_cell = np.ones(len(h), bool)
    new_cell[1:] = (gx[1:] != gx[:-1]) | (gz[1:] != gz[:-1])
    # sequential within a cell (clusters are few per cell)
    label = np.empty(len(h), np.int64)
    cur, w_sum, hw_sum = -1, 0.0, 0.0
    for i in range(len(h)):
        if new_cell[i] or abs(h[i] - hw_sum / w_sum) > merge_m:
            cur += 1
            w_sum, hw_sum = 0.0, 0.0
        w_sum += w[i]
        hw_sum += w[i] * h[i]
        label[i] = cur
    return label


def _cap(layers: Observations, max_layers: int) -> Observations:
    """Keep the ``max_layers`` most-hit layers of each cell (ties: the lower); result sorted by (cell, h)."""
    order = np.lexsort((layers.h, -layers.hits, layers.gz, layers.gx))
    l2 = layers.take(order)
    new_cell = np.r_[True, (l2.gx[1:] != l2.gx[:-1]) | (l2.gz[1:] != l2.gz[:-1])]
    start = np.maximum.accumulate(np.where(new_cell, np.arange(len(l2)), 0))
    rank = np.arange(len(l2)) - start
    kept = l2.take(np.flatnonzero(rank < max_layers))
    return kept.take(np.lexsort((kept.h, kept.gz, kept.gx)))


def drop_aliases(layers: Observations, **rule) -> Observations:
    """Drop the layers that are a neighbouring cell's surface seen across a cell edge (``aliases``, whose keywords
    ``rule`` passes on). Rows keep their (cell, h) order."""
    return layers.take(np.flatnonzero(~aliases(layers, **rule)))


def aliases(
    layers: Observations,
    merge_m: float = MERGE_M,
    fraction: float = ALIAS_FRACTION,
    dominance: float = ALIAS_DOMINANCE,
    support: int = ALIAS_SUPPORT,
) -> np.ndarray:
    """(n,) bool: the layers that are a neighbouring cell's surface seen across a cell edge (any row order).

    A surface that ends on a cell edge (a wall's side, a deck's rim) leaks points a few cm into the
    next cell, which then holds a layer at the neighbour's height. Two tests, on merged layers (so as
    order-independent as ``merge``):

    - **By position** (any hits): every point merged into the layer, from every recording, lay near its
      cell's border (within the scan's ``edge_m`` of an edge: ``hugs`` without ``AWAY`` or ``SURFACE``)
      and the cell across one of the edges it hugs holds a layer within ``merge_m`` of its height that is
      a surface in its own right (points away from every edge, or ``SURFACE``). Each recording applies
      it to its own layers (``accumulate.edge_leaks``); here it catches a leak whose source cell another
      recording saw.
    - **By hits**, for what position cannot tell (a lip seen past at a grazing angle leaks inside the
      cell): a weakly supported layer — under ``support`` hits, under ``fraction`` of its cell's
      strongest layer's — that an edge neighbour holds at the same height ``dominance`` times over.

    A layer with ``support`` hits or more and points inside its cell — a ledge or a deck reaching into
    the cell, however weakly seen beside a stronger neighbour — is never dropped, nor is a ``SURFACE``
    layer (contacts, hole fills, imported chunks, whose hit counts come from elsewhere).
    """
    if not len(layers):
        return np.zeros(0, bool)
    hugs = layers.hugs
    own = (hugs & (AWAY | SURFACE)) != 0
    g = DenseGrid.of(layers)  # its one-cell margin keeps neighbours in range
    H = g.scatter(layers.h, np.nan)  # (X, Z, L)
    S = g.scatter(own, False)
    W = g.scatter(layers.hits.astype(np.float64), 0.0)
    weak = (layers.hits < fraction * W.max(axis=2)[g.cx, g.cz]) & (layers.hits < support) & ((hugs & SURFACE) == 0)
    alias = np.zeros(len(layers), bool)
    for e, (dx, dz) in enumerate(EDGES):
        Hn, Sn, Wn = H[g.cx + dx, g.cz + dz], S[g.cx + dx, g.cz + dz], W[g.cx + dx, g.cz + dz]  # (n, L)
        same = np.abs(Hn - layers.h[:, None]) <= merge_m  # NaN compares False
        hugged = ~own & ((hugs & (1 << e)) != 0)
        alias |= hugged & (same & Sn).any(axis=1)
        alias |= weak & (same & (Wn >= dominance * layers.hits[:, None])).any(axis=1)
    return alias


@dataclass
class DenseGrid:
    """Layers laid out on a dense (X, Z, L) grid over their bounding box plus a ``margin`` of cells:
    layer i sits at [cx[i], cz[i], slot[i]], slots in height order within a cell."""

    x0: int
    z0: int
    shape: tuple[int, int, int]
    cx: np.ndarray
    cz: np.ndarray
    slot: np.ndarray

    @staticmethod
    def of(layers: Observations, margin: int = 1) -> DenseGrid:
        x0, z0 = int(layers.gx.min()) - margin, int(layers.gz.min()) - margin
        X, Z = int(layers.gx.max()) - x0 + 1 + margin, int(layers.gz.max()) - z0 + 1 + margin
        cx, cz = layers.gx - x0, layers.gz - z0
        key = cx * Z + cz
        order = np.lexsort((layers.h, key))
        ks = key[order]
        start = np.r_[0, np.flatnonzero(ks[1:] != ks[:-1]) + 1]
        slot = np.empty(len(key), np.int64)
        slot[order] = np.arange(len(key)) - np.repeat(start, np.diff(np.r_[start, len(key)]))
        return DenseGrid(x0, z0, (X, Z, int(slot.max()) + 1), cx, cz, slot)

    def scatter(self, values: np.ndarray, fill) -> np.ndarray:
        """(X, Z, L, ...) array holding ``values`` (one per layer) and ``fill`` elsewhere."""
        values = np.asarray(values)
        out = np.full(self.shape + values.shape[1:], fill, dtype=np.result_type(values, np.asarray(fill)))
        out[self.cx, self.cz, self.slot] = values
        return out
