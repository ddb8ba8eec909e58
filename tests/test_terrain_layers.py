"""The layer merge rule: order independence, hit weighting, layer cap, no NaN."""

import numpy as np

from terrain_scan.layers import AWAY, SURFACE, Observations, drop_aliases, merge
from terrain_scan.store import Stage
from terrain_scan.trn2 import FLAG_VALID, read_chunk


def obs(rows):
    a = np.asarray(rows, np.float64).reshape(-1, 6)  # gx, gz, h, ny, hits, ts
    n = np.zeros((len(a), 3))
    n[:, 1] = a[:, 3]
    return Observations(
        a[:, 0].astype(np.int64), a[:, 1].astype(np.int64), a[:, 2], n, a[:, 4].astype(np.int64), a[:, 5].astype(np.int64)
    )


def as_rows(o):
    return sorted(zip(o.gx.tolist(), o.gz.tolist(), np.round(o.h, 9).tolist(), o.hits.tolist(), o.ts.tolist()))


def test_hit_weighted_merge_within_half_a_metre_and_separate_levels():
    o = obs(
        [[-951, 850, 10.0, 1, 3, 100], [-951, 850, 10.4, 1, 1, 200], [-951, 850, 15.2, 1, 5, 50], [-951, 850, 15.0, 1, 5, 60]]
    )
    L = merge(o)
    assert as_rows(L) == [(-951, 850, 10.1, 4, 200), (-951, 850, 15.1, 10, 60)]
    np.testing.assert_allclose(L.n, [[0, 1, 0], [0, 1, 0]])


def test_order_of_arrival_does_not_matter():
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(400):
        gx, gz = rng.integers(-3, 3), rng.integers(-3, 3)
        base = 20.0 + (6.0 if rng.random() < 0.3 else 0.0)
        rows.append([gx, gz, base + rng.normal(0, 0.1), 1, rng.integers(1, 9), rng.integers(0, 1000)])
    o = obs(rows)
    ref = merge(o)
    for seed in range(5):
        perm = np.random.default_rng(seed).permutation(len(o))
        got = merge(o.take(perm))
        assert as_rows(got) == as_rows(ref)
        np.testing.assert_array_equal(got.n, ref.n)
    # merging per-part results again equals merging everything at once (contributions compose)
    half = len(o) // 2
    two_step = merge(Observations.concat([merge(o.take(np.arange(half))), merge(o.take(np.arange(half, len(o))))]))
    assert {(r[0], r[1]) for r in as_rows(two_step)} == {(r[0], r[1]) for r in as_rows(ref)}
    assert sum(r[3] for r in as_rows(two_step)) == sum(r[3] for r in as_rows(ref))


def test_layer_cap_drops_the_least_hit_and_nan_never_enters():
    rows = [[0, 0, 2.0 * k, 1, k + 1, 0] for k in range(10)] + [[0, 0, float("nan"), 1, 50, 0], [0, 0, 1.0, float("nan"), 50, 0]]
    L = merge(obs(rows), max_layers=8)
    assert len(L) == 8 and sorted(L.hits.tolist()) == list(range(3, 11))
    assert np.isfinite(L.h).all() and np.isfinite(L.n).all()
    assert len(merge(Observations.empty())) == 0


def _field(rows):
    """Observations from rows (gx, gz, h, hits, hugs)."""
    gx, gz, h, hits, hugs = (np.array(c) for c in zip(*rows))
    n = len(h)
    return Observations(
        gx, gz, h.astype(float), np.tile([0.0, 1.0, 0.0], (n, 1)), hits, np.zeros(n, np.int64), hugs.astype(np.uint8)
    )


def _kept(layers):
    return set(zip(layers.gx.tolist(), layers.gz.tolist(), np.round(layers.h, 3).tolist()))


WEST, EAST = 1, 2  # layers.EDGES bits


def test_a_well_supported_ledge_beside_a_stronger_neighbour_survives_the_stage_merge(tmp_path):
    """Cell (0, 0) is floor (h 0, 4000 hits) under the end of a ledge (h 5) that cell (1, 0) holds with 60,000
    hits: 900 hits of its own, under a quarter of its floor's, spread inside the cell (AWAY). The hit rule alone
    (a weak layer a neighbour dominates) would drop it; it is kept through merge, aliases and the stage's
    rebuild. Beside it: a 9-hit layer hugging (2, 0)'s west edge at (1, 0)'s height (a leak by position,
    dropped whatever its hits would say), the same sliver with 900 hits (dropped: position, not hits), a 2-hit
    interior speck a neighbour dominates (dropped by hits), and an imported layer (SURFACE) like it (kept)."""
    rows = [
        (0, 0, 0.0, 4000, AWAY),
        (0, 0, 5.0, 900, AWAY),  # the ledge reaching into the cell
        (1, 0, 5.0, 60000, AWAY),
        (2, 0, 1.0, 500, AWAY),
        (2, 0, 5.1, 9, WEST),  # a leak from (1, 0) over (2, 0)'s west edge
        (0, 5, 0.0, 500, AWAY),
        (1, 5, 5.0, 500, AWAY),
        (2, 5, 1.0, 500, AWAY),
        (2, 5, 5.1, 900, WEST),  # the same sliver, strongly hit: still only points on the edge
        (0, 9, 0.0, 400, AWAY),
        (1, 9, 3.0, 400, AWAY),
        (0, 9, 3.2, 2, AWAY),  # a speck inside (0, 9) at (1, 9)'s height, weakly supported
        (0, 12, 0.0, 400, SURFACE),
        (1, 12, 3.0, 400, SURFACE),
        (0, 12, 3.2, 2, SURFACE),  # the same speck from an imported chunk: its counts are not a scan's
    ]
    layers = merge(_field(rows))
    kept = _kept(drop_aliases(layers))
    assert (0, 0, 5.0) in kept and (0, 12, 3.2) in kept
    assert not {(2, 0, 5.1), (2, 5, 5.1), (0, 9, 3.2)} & kept
    assert len(kept) == len(rows) - 3
    # the stage keeps the ledge through its rebuild (merge, aliases, hole fill) into the chunk file
    st = Stage(tmp_path / "s")
    st.put("r", _field(rows), "h", 1767225600)
    st.rebuild()
    cell = read_chunk(tmp_path / "s" / "chunks" / "chunk_0_0.trn2").cells[0]
    valid = (cell["flags"] & FLAG_VALID) != 0
    assert sorted(cell["h"][valid].tolist()) == [0.0, 5.0] and sorted(cell["hits"][valid].tolist()) == [900, 4000]


def test_aliases_by_position_merge_across_recordings():
    """A layer is a leak by position only while every recording's points hug the border: one recording's
    points inside the cell make it a surface; an edge sliver whose source cell holds only another sliver
    (no surface of its own) is not a leak."""
    leak = (2, 0, 5.1, 30, WEST)
    source = (1, 0, 5.0, 500, AWAY)
    assert not _kept(drop_aliases(merge(_field([source, leak])))) & {(2, 0, 5.1)}
    seen_inside = merge(_field([source, leak, (2, 0, 5.1, 30, AWAY)]))  # another recording saw it inside
    assert (2, 0, 5.1) in _kept(drop_aliases(seen_inside))
    slivers = merge(_field([(1, 0, 5.0, 500, EAST), leak]))  # both cells only touch their shared edge
    assert len(drop_aliases(slivers)) == 2
