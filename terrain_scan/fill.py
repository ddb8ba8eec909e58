"""Hole fill: an empty cell whose 8 neighbours agree gets a filled layer.

A round looks at every cell with no layer. For each candidate window [a, a + AGREE_M] whose lower
end a is one of its neighbours' layer heights, it counts the neighbours with a layer inside the
window; the window with the most neighbours (ties: the lower) wins. With at least MIN_NEIGHBOURS of
the 8, not all on one line (a hole is filled, a border is not extrapolated), it becomes a filled
layer: the height of a least-squares plane through those neighbours' layers (per neighbour the layer
nearest the window's middle) at the cell's centre, their mean normal, hits 0, flags valid | filled,
last_ts the newest of them. Cells filled in a round count as neighbours in the next; rounds are
bounded.
"""

from __future__ import annotations

import numpy as np

from terrain_scan.layers import DenseGrid, Observations

AGREE_M = 2.0
MIN_NEIGHBOURS = 3
OFFSETS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def fill_holes(
    layers: Observations, rounds: int = 2, agree_m: float = AGREE_M, min_neighbours: int = MIN_NEIGHBOURS
) -> tuple[Observations, np.ndarray]:
    """Return (layers + filled layers, filled mask) — rows sorted by (gx, gz, h)."""
    if not len(layers) or rounds <= 0:
        return layers, np.zeros(len(layers), bool)
    filled_parts: list[Observations] = []
    current = layers
    for _ in range(rounds):
        new = _fill_round(current, agree_m, min_neighbours)
        if not len(new):
            break
        filled_parts.append(new)
        current = Observations.concat([current, new])
    allrows = Observations.concat([layers] + filled_parts)
    filled = np.r_[np.zeros(len(layers), bool), np.ones(len(allrows) - len(layers), bool)]
    order = np.lexsort((allrows.h, allrows.gz, allrows.gx))
    return allrows.take(order), filled[order]


def _fill_round(layers: Observations, agree_m: float, min_neighbours: int) -> Observations:
    g = DenseGrid.of(layers, margin=1)
    x0, z0 = g.x0, g.z0
    X, Z, _ = g.shape
    H = g.scatter(layers.h, np.nan)
    N = g.scatter(layers.n, 0.0)
    T = g.scatter(layers.ts, 0)
    has = ~np.isnan(H).all(axis=2)
    # neighbour stacks, (8, X, Z, L)
    pad = lambda A, fill: np.pad(A, [(1, 1), (1, 1)] + [(0, 0)] * (A.ndim - 2), constant_values=fill)  # noqa: E731
    Hp, Np, Tp, hasp = pad(H, np.nan), pad(N, 0.0), pad(T, 0), pad(has, False)
    nb_has = np.stack([hasp[1 + dx : 1 + dx + X, 1 + dz : 1 + dz + Z] for dx, dz in OFFSETS])
    cand = ~has & (nb_has.sum(0) >= min_neighbours)
    ix, iz = np.nonzero(cand)
    if not len(ix):
        return Observations.empty()
    nh = np.stack([Hp[1 + dx + ix, 1 + dz + iz] for dx, dz in OFFSETS], axis=1)  # (C, 8, L)
    nn = np.stack([Np[1 + dx + ix, 1 + dz + iz] for dx, dz in OFFSETS], axis=1)  # (C, 8, L, 3)
    nt = np.stack([Tp[1 + dx + ix, 1 + dz + iz] for dx, dz in OFFSETS], axis=1)  # (C, 8, L)
    C = len(ix)
    a = nh.reshape(C, -1)  # candidate window starts (C, 8L)
    inside = (nh[:, None, :, :] >= a[:, :, None, None]) & (nh[:, None, :, :] <= a[:, :, None, None] + agree_m)  # (C, 8L, 8, L)
    count = inside.any(axis=3).sum(axis=2)  # neighbours in each window
    count = np.where(np.isnan(a), -1, count)
    # best window: most neighbours, then the lowest start
    a_key = np.where(np.isnan(a), np.inf, a)
    best = np.lexsort((a_key, -count), axis=-1)[:, 0]
    bc = count[np.arange(C), best]
    ok = bc >= min_neighbours
    if not ok.any():
        return Observations.empty()
    lo = a[np.arange(C), best]
    mid = lo + agree_m / 2
    win = inside[np.arange(C), best]  # (C, 8, L)
    dist = np.where(win, np.abs(nh - mid[:, None, None]), np.inf)
    pick = dist.argmin(axis=2)  # (C, 8)
    use = np.isfinite(dist.min(axis=2))  # neighbours with a layer in the window
    ph = np.take_along_axis(nh, pick[:, :, None], 2)[:, :, 0]
    pn = np.take_along_axis(nn, pick[:, :, None, None], 2)[:, :, 0]
    pt = np.take_along_axis(nt, pick[:, :, None], 2)[:, :, 0]
    # height: a plane h = a + b·dx + c·dz fitted to the agreeing neighbours, evaluated at the centre
    # (exact on sloped ground, where a plain mean is biased towards the side the neighbours are on)
    off = np.asarray(OFFSETS, np.float64)  # (8, 2)
    A = np.concatenate([np.ones((8, 1)), off], axis=1)  # (8, 3)
    w = use.astype(np.float64)
    AtA = np.einsum("ck,ki,kj->cij", w, A, A)
    Atb = np.einsum("ck,ki,ck->ci", w, A, np.where(use, ph, 0.0))
    # the offsets must span the plane: neighbours all on one line would make this an extrapolation
    spans = np.linalg.det(AtA) > 1e-6
    ok &= spans
    h = np.zeros(C)
    if spans.any():
        h[spans] = np.linalg.solve(AtA[spans], Atb[spans][..., None])[:, 0, 0]
    nsum = np.where(use[:, :, None], pn, 0).sum(1)
    n = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-12)
    ts = np.where(use, pt, 0).max(1)
    sel = np.flatnonzero(ok)
    return Observations(
        (ix[sel] + x0).astype(np.int64),
        (iz[sel] + z0).astype(np.int64),
        h[sel],
        n[sel],
        np.zeros(len(sel), np.int64),
        ts[sel].astype(np.int64),
    )
